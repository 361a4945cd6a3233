/* Flash storage for the HAL: the four storage regions, each one whole sector (flash_layout.h). */
#ifndef TRIMETER_STM32F405_FLASH_H
#define TRIMETER_STM32F405_FLASH_H

#include <stddef.h>
#include <stdint.h>

#include "hal.h"

int flash_region_read(void *ctx, enum hal_region region, uint32_t offset, void *buf, size_t len);
int flash_region_write(void *ctx, enum hal_region region, uint32_t offset, const void *buf, size_t len);
int flash_region_erase(void *ctx, enum hal_region region);
/* A map region's bytes where the flash is memory-mapped; NULL for a config region. */
const uint8_t *flash_region_map_bytes(void *ctx, enum hal_region region);

#endif
