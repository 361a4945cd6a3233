/* Flash programming (RM0090 §3.6): byte programming (PSIZE x8, valid at any supply voltage),
 * sector erase. The F405 has one bank: the CPU stalls while it erases or programs, which is why the
 * app refuses map and config writes while the slider moves. Every busy-wait has a bound. */
#include "flash.h"

#include <string.h>

#include "regs.h"

#define FLASH_BUSY_LIMIT 50000000u /* loop turns: longer than a worst-case 128 KiB erase (2 s at x32) */

static const struct {
    uint32_t address;
    uint32_t size;
    uint8_t sector;
} regions[HAL_REGION_COUNT] = {
    [HAL_REGION_CONFIG_A] = {0x08008000u, HAL_CONFIG_REGION_SIZE, 2},
    [HAL_REGION_CONFIG_B] = {0x0800C000u, HAL_CONFIG_REGION_SIZE, 3},
    [HAL_REGION_MAP_A] = {0x08020000u, HAL_MAP_REGION_SIZE, 5},
    [HAL_REGION_MAP_B] = {0x08040000u, HAL_MAP_REGION_SIZE, 6},
};

static bool in_range(enum hal_region r, uint32_t offset, size_t len)
{
    return (unsigned)r < HAL_REGION_COUNT && offset <= regions[r].size && len <= regions[r].size - offset;
}

static int wait_idle(void)
{
    for (uint32_t i = 0; i < FLASH_BUSY_LIMIT; i++) {
        if (!(FLASH_SR & FLASH_SR_BSY)) {
            uint32_t errors = FLASH_SR & FLASH_SR_ERRORS;
            FLASH_SR = errors; /* write-1-to-clear */
            return errors ? -1 : 0;
        }
    }
    return -1;
}

static void unlock(void)
{
    if (FLASH_CR & FLASH_CR_LOCK) {
        FLASH_KEYR = FLASH_KEY1;
        FLASH_KEYR = FLASH_KEY2;
    }
}

static void lock(void) { FLASH_CR = FLASH_CR_LOCK; }

int flash_region_read(void *ctx, enum hal_region r, uint32_t offset, void *buf, size_t len)
{
    (void)ctx;
    if (!in_range(r, offset, len)) return -1;
    memcpy(buf, (const void *)(regions[r].address + offset), len);
    return 0;
}

int flash_region_write(void *ctx, enum hal_region r, uint32_t offset, const void *buf, size_t len)
{
    (void)ctx;
    if (!in_range(r, offset, len)) return -1;
    const uint8_t *src = buf;
    volatile uint8_t *dst = (volatile uint8_t *)(regions[r].address + offset);
    int rc = wait_idle();
    unlock();
    FLASH_CR = FLASH_CR_PSIZE_X8 | FLASH_CR_PG;
    for (size_t i = 0; rc == 0 && i < len; i++) {
        dst[i] = src[i];
        rc = wait_idle();
    }
    lock();
    return rc;
}

int flash_region_erase(void *ctx, enum hal_region r)
{
    (void)ctx;
    if ((unsigned)r >= HAL_REGION_COUNT) return -1;
    int rc = wait_idle();
    unlock();
    /* x32 parallelism erases twice as fast as x8 (needs 2.7-3.6 V, as the board has) */
    FLASH_CR = FLASH_CR_PSIZE_X32 | FLASH_CR_SER | ((uint32_t)regions[r].sector << FLASH_CR_SNB_SHIFT);
    FLASH_CR |= FLASH_CR_STRT;
    if (rc == 0) rc = wait_idle();
    lock();
    return rc;
}
