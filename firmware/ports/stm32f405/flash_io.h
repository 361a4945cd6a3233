/* The flash driver's only contact with the hardware: the FLASH interface registers (RM0090 §3.8)
 * and the flash memory itself. flash_io.c implements it on the MCU; the host test
 * (firmware/tests/test_stm32_flash.c) implements it as a fake flash controller. */
#ifndef TRIMETER_STM32F405_FLASH_IO_H
#define TRIMETER_STM32F405_FLASH_IO_H

#include <stddef.h>
#include <stdint.h>

/* Values are the registers' offsets from the FLASH interface's base. */
enum flash_reg { FLASH_REG_ACR = 0x00, FLASH_REG_KEYR = 0x04, FLASH_REG_SR = 0x0C, FLASH_REG_CR = 0x10 };

uint32_t flash_io_read_reg(enum flash_reg reg);
void flash_io_write_reg(enum flash_reg reg, uint32_t value);
/* One program operation of the width PSIZE selects (x8: a byte, x32: an aligned word). */
void flash_io_program8(uint32_t address, uint8_t value);
void flash_io_program32(uint32_t address, uint32_t value);
void flash_io_read(uint32_t address, void *buf, size_t len);
/* The flash memory at `address` as the CPU reads it (memory-mapped, through the caches). */
const uint8_t *flash_io_map(uint32_t address);

#endif
