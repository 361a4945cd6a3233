/* flash_io.h on the MCU: plain volatile accesses, in RAM because the driver calls them while the
 * flash is busy. */
#include "flash_io.h"

#include <string.h>

#include "ramfunc.h"
#include "regs.h"

RAMFUNC uint32_t flash_io_read_reg(enum flash_reg reg) { return REG32(FLASH_BASE_R + (uint32_t)reg); }

RAMFUNC void flash_io_write_reg(enum flash_reg reg, uint32_t value) { REG32(FLASH_BASE_R + (uint32_t)reg) = value; }

RAMFUNC void flash_io_program8(uint32_t address, uint8_t value) { *(volatile uint8_t *)address = value; }

RAMFUNC void flash_io_program32(uint32_t address, uint32_t value) { *(volatile uint32_t *)address = value; }

/* Only called with the flash idle, so it may live in flash like memcpy. */
void flash_io_read(uint32_t address, void *buf, size_t len) { memcpy(buf, (const void *)address, len); }

const uint8_t *flash_io_map(uint32_t address) { return (const uint8_t *)address; }
