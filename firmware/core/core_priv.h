/* core_priv.h - what the core's files share (core.c: link and boot; core_params.c: parameters
 * and flash; core_sensors.c: the generic sensors; core_stream.c: sampling and batching;
 * core_cmd.c: commands). Not an
 * interface: only firmware/core/core*.c include it. */
#ifndef IB_CORE_PRIV_H
#define IB_CORE_PRIV_H

#include <math.h>
#include <string.h>

#include "core.h"
#include "param_store.h"
#include "wire.h"

#define G0_MPS2 9.80665f
#define RAD_PER_DEG (3.14159265358979f / 180.0f)
#define ACCEL_FIFO_MAX_SETS 32u
/* TX room always kept free for replies when a sample batch is queued. */
#define REPLY_RESERVE (2u * (IB_MAX_ENCODED + 1u))
#define STATS_PERIOD_MS 1000u
/* The calibrated span of factory defaults and of a migrated layout-1 or -2 block, degC. */
#define SPAN_DEFAULT_MIN_C ((int8_t)-40)
#define SPAN_DEFAULT_MAX_C ((int8_t)85)

/* core.c */
void ibc_fw_version(uint8_t v[3]); /* major, minor, patch (FW_VERSION_* in core.c) */
uint32_t ibc_now_us(const ib_core_t *c);
void ibc_update_uptime(ib_core_t *c);
void ibc_link_put(ib_core_t *c, const uint8_t *frame, size_t len);
size_t ibc_encode_msg(ib_core_t *c, uint8_t type, size_t payload_len, uint8_t *out);
void ibc_send_unsolicited(ib_core_t *c, uint8_t type, size_t payload_len);
/* core_params.c */
void ibc_correct_terms(const ib_params_t *p, int gyro, const ib_triad_corr_t *t, const float temp_c[3],
                          float unit, float per_unit, float bias[3], float w[3][3]);
void ibc_correct_apply(const float w[3][3], const float u[3], const float bias[3], float out[3]);
void ibc_identity_params(ib_params_t *p);
void ibc_set_factory(ib_core_t *c);
int ibc_read_stored(const ib_flash_if_t *fl, ib_params_t *p, ib_ps_info_t *info);
void ibc_load_params(ib_core_t *c);
/* core_sensors.c */
void ibc_sensors_init(ib_core_t *c);
const ib_part_desc_t *ibc_accel_part(const ib_core_t *c);
const ib_part_desc_t *ibc_gyro_part(const ib_core_t *c, int k);
uint32_t ibc_missing_detail(const ib_core_t *c, uint8_t sensor);
uint8_t ibc_range_code(const ib_core_t *c, uint8_t g);
int ibc_odr_for_rate(const ib_core_t *c, uint32_t rate_hz, uint32_t *avg);
/* core_stream.c */
void ibc_emit_fault(ib_core_t *c, uint8_t sensor, uint8_t kind, uint8_t active, uint32_t detail);
void ibc_sample_finish(ib_core_t *c);
void ibc_stream_stop(ib_core_t *c);
/* core_cmd.c */
void ibc_info_fill(ib_core_t *c, ib_msg_info_t *m, uint16_t rid);
void ibc_reply(ib_core_t *c, uint16_t rid, uint8_t command, uint8_t error, uint32_t value,
                  uint8_t data_type, size_t data_len);
int ibc_flush_reply(ib_core_t *c);
void ibc_on_frame(ib_core_t *c, int status, const ib_frame_t *f);

#endif
