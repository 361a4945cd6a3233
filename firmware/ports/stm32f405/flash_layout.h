/* Where the storage regions live in the STM32F405's flash, declared once. The flash driver maps
 * the HAL's regions onto these sectors; stm32f405.ld gives the program only the other sectors;
 * tests/firmware/test_stm32_image.py reads this file and fails if any flashable artifact of the
 * build holds a byte in one of them (flashing the program must never erase a saved config or map).
 * The sector numbers are fixed for good: boards in the field keep their config and maps there. */
#ifndef TRIMETER_STM32F405_FLASH_LAYOUT_H
#define TRIMETER_STM32F405_FLASH_LAYOUT_H

#include <stdint.h>

#define FLASH_STORAGE_SECTOR_CONFIG_A 2u /* 16 KiB at 0x08008000 */
#define FLASH_STORAGE_SECTOR_CONFIG_B 3u /* 16 KiB at 0x0800C000 */
#define FLASH_STORAGE_SECTOR_MAP_A 5u    /* 128 KiB at 0x08020000 */
#define FLASH_STORAGE_SECTOR_MAP_B 6u    /* 128 KiB at 0x08040000 */

/* RM0090 Table 5 (1 MiB parts): sectors 0-3 16 KiB, 4 64 KiB, 5-11 128 KiB from 0x08000000. */
#define FLASH_MEMORY_BASE 0x08000000u
#define FLASH_SECTOR_COUNT 12u

/* Always inlined: the flash driver's RAM functions use it while the flash is busy, so no copy of it may
 * live in flash. */
static inline __attribute__((always_inline)) uint32_t flash_sector_address(uint32_t sector)
{
    if (sector < 4u) return FLASH_MEMORY_BASE + sector * 0x4000u;
    if (sector == 4u) return FLASH_MEMORY_BASE + 0x10000u;
    return FLASH_MEMORY_BASE + 0x20000u + (sector - 5u) * 0x20000u;
}

static inline __attribute__((always_inline)) uint32_t flash_sector_size(uint32_t sector)
{
    return sector < 4u ? 0x4000u : sector == 4u ? 0x10000u : 0x20000u;
}

#endif
