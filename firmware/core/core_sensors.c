/* core_sensors.c - the generic sensors: each slot's driver picked at boot from the part table
 * (sensor.h), and what the rest of the core asks of a sensor whatever its part. */
#include "core_priv.h"

/* Try each distinct accelerometer driver of the part table in turn: the slot is the first one
 * whose init finds a part the table gives to it. With none, the slot keeps the last tried (its
 * ID read is reported) and is not present. */
static void accel_probe(ib_core_t *c, const ib_spi_bus_t *bus)
{
    for (size_t i = 0; i < ib_sensor_driver_count; i++) {
        const ib_accel_ops_t *ops = ib_sensor_drivers[i].accel;
        size_t j = 0;
        while (j < i && ib_sensor_drivers[j].accel != ops) {
            j++;
        }
        if (ops == NULL || j < i) { /* not an accelerometer, or a driver tried already */
            continue;
        }
        c->accel.ops = ops;
        c->accel.ctx = ops->instance(0);
        if (ops->init(c->accel.ctx, bus, IB_CS_ACCEL) != IB_SENSOR_OK) {
            continue;
        }
        const ib_part_desc_t *p = ops->part(c->accel.ctx);
        for (j = 0; p != NULL && j < ib_sensor_driver_count; j++) {
            if (ib_sensor_drivers[j].part == p->part && ib_sensor_drivers[j].accel == ops) {
                c->present |= 1u << IB_SENSOR_ACCEL;
                c->accel_range_g = (uint8_t)p->default_full_scale;
                return;
            }
        }
    }
}

/* The same for gyro slot k. */
static void gyro_probe(ib_core_t *c, const ib_spi_bus_t *bus, uint8_t k)
{
    for (size_t i = 0; i < ib_sensor_driver_count; i++) {
        const ib_gyro_ops_t *ops = ib_sensor_drivers[i].gyro;
        size_t j = 0;
        while (j < i && ib_sensor_drivers[j].gyro != ops) {
            j++;
        }
        if (ops == NULL || j < i) {
            continue;
        }
        c->gyro[k].ops = ops;
        c->gyro[k].ctx = ops->instance(k);
        if (ops->init(c->gyro[k].ctx, bus, (uint8_t)(IB_CS_GYRO_X + k)) != IB_SENSOR_OK) {
            continue;
        }
        const ib_part_desc_t *p = ops->part(c->gyro[k].ctx);
        for (j = 0; p != NULL && j < ib_sensor_driver_count; j++) {
            if (ib_sensor_drivers[j].part == p->part && ib_sensor_drivers[j].gyro == ops) {
                c->present |= (uint8_t)(1u << (IB_SENSOR_GYRO_X + k));
                return;
            }
        }
    }
}

void ibc_sensors_init(ib_core_t *c)
{
    const ib_spi_bus_t *bus = c->board->spi;
    c->present = 0;
    accel_probe(c, bus);
    for (uint8_t k = 0; k < IB_GYRO_SLOTS; k++) {
        gyro_probe(c, bus, k);
    }
}

/* The part in a slot, or with none found the slot's driver's base part (so that a stream with
 * a sensor missing still carries finite numbers on a known scale, flagged missing). */
const ib_part_desc_t *ibc_accel_part(const ib_core_t *c)
{
    const ib_part_desc_t *p = c->accel.ops->part(c->accel.ctx);
    return p ? p : ib_part_by_id(c->accel.ops->base_part);
}

const ib_part_desc_t *ibc_gyro_part(const ib_core_t *c, int k)
{
    const ib_part_desc_t *p = c->gyro[k].ops->part(c->gyro[k].ctx);
    return p ? p : ib_part_by_id(c->gyro[k].ops->base_part);
}

/* The detail of a MISSING fault (docs/protocol.md): what the slot's ID registers read. */
uint32_t ibc_missing_detail(const ib_core_t *c, uint8_t sensor)
{
    if (sensor == IB_SENSOR_ACCEL) {
        uint8_t id[4];
        c->accel.ops->ids(c->accel.ctx, id);
        return (uint32_t)id[0] << 16 | (uint32_t)id[1] << 8 | id[2];
    }
    uint16_t pid;
    uint32_t serial;
    c->gyro[sensor - 1u].ops->ids(c->gyro[sensor - 1u].ctx, &pid, &serial);
    return pid;
}

/* The register code of full scale g on the accelerometer's part (protocol/parts.toml); 0: none. */
uint8_t ibc_range_code(const ib_core_t *c, uint8_t g)
{
    const ib_part_range_t *r = ib_part_range(c->accel.ops->part(c->accel.ctx), g);
    return r ? r->code : 0u;
}

/* The ODR code for a stream rate: the lowest ODR of the accelerometer's driver of which the
 * stream period is a whole multiple of at most ACCEL_FIFO_MAX_SETS samples (averaged per
 * tick). -1: none. */
int ibc_odr_for_rate(const ib_core_t *c, uint32_t rate_hz, uint32_t *avg)
{
    if (rate_hz == 0u || 1000000u % rate_hz != 0u) {
        return -1;
    }
    const ib_accel_ops_t *ops = c->accel.ops;
    uint32_t period = 1000000u / rate_hz;
    for (int k = ops->odr_code_max; k >= 0; k--) {
        uint32_t odr_period = ops->odr_period_us((uint8_t)k);
        if (odr_period <= period && period % odr_period == 0u && period / odr_period <= ACCEL_FIFO_MAX_SETS) {
            *avg = period / odr_period;
            return k;
        }
    }
    return -1;
}
