/* adxl355_priv.h - what adxl355.c (registers, identification, configuration) and adxl355_data.c
 * (samples, the FIFO, self-test) share. Not an interface: only the two include it. */
#ifndef IB_ADXL355_PRIV_H
#define IB_ADXL355_PRIV_H

#include "adxl355.h"

#define RW_READ 0x01u
#define REGS_MAX 16u

int adxl355_xfer(ib_adxl355_t *dev, const uint8_t *tx, uint8_t *rx, size_t len);
void adxl355_delay_us(const ib_adxl355_t *dev, uint32_t us);
int adxl355_write_reg(ib_adxl355_t *dev, uint8_t addr, uint8_t val);
int adxl355_write_config(ib_adxl355_t *dev, const ib_adxl355_config_t *cfg);

#endif
