/* Flash storage (RM0090 §3.5-3.6): sector erase at x32 parallelism, programming in aligned words
 * (x32) with bytes (x8) only at unaligned ends; the board's 3.3 V supply allows x32.
 *
 * The F405 has one flash bank: while it erases or programs, any fetch from flash stalls the CPU
 * until the operation ends. Everything here that runs between starting an operation and seeing it
 * finish is in RAM (RAMFUNC, and flash_io.c's accessors), and so are the step timer's ISR and the
 * vector table the NVIC reads (main.c, startup.c): the step timer keeps running while map records
 * are programmed. Every busy-wait has a bound. */
#include "flash.h"

#include "flash_io.h"
#include "flash_layout.h"
#include "ramfunc.h"
#include "regs.h"

#define FLASH_BUSY_LIMIT 50000000u /* loop turns: longer than a worst-case 128 KiB erase (2 s at x32) */
#define FLASH_ACR_CACHES (FLASH_ACR_ICEN | FLASH_ACR_DCEN)
#define FLASH_ACR_CACHE_RESETS (FLASH_ACR_ICRST | FLASH_ACR_DCRST)

/* Read only before an operation starts (in flash, like every constant). */
static const uint8_t region_sector[HAL_REGION_COUNT] = {
    [HAL_REGION_CONFIG_A] = FLASH_STORAGE_SECTOR_CONFIG_A,
    [HAL_REGION_CONFIG_B] = FLASH_STORAGE_SECTOR_CONFIG_B,
    [HAL_REGION_MAP_A] = FLASH_STORAGE_SECTOR_MAP_A,
    [HAL_REGION_MAP_B] = FLASH_STORAGE_SECTOR_MAP_B,
};

static RAMFUNC uint32_t region_size(enum hal_region r)
{
    return r == HAL_REGION_CONFIG_A || r == HAL_REGION_CONFIG_B ? HAL_CONFIG_REGION_SIZE : HAL_MAP_REGION_SIZE;
}

static RAMFUNC bool in_range(enum hal_region r, uint32_t offset, size_t len)
{
    return (unsigned)r < HAL_REGION_COUNT && offset <= region_size(r) && len <= region_size(r) - offset;
}

/* Waits for BSY to clear; returns -1 on a timeout or an error the operation raised (cleared). */
static RAMFUNC int wait_idle(void)
{
    for (uint32_t i = 0; i < FLASH_BUSY_LIMIT; i++) {
        uint32_t sr = flash_io_read_reg(FLASH_REG_SR);
        if (!(sr & FLASH_SR_BSY)) {
            uint32_t errors = sr & FLASH_SR_ERRORS;
            if (errors) flash_io_write_reg(FLASH_REG_SR, errors); /* write-1-to-clear */
            return errors ? -1 : 0;
        }
    }
    return -1;
}

/* Idle and CR unlocked. An error flag an earlier operation left is cleared, not reported again. */
static RAMFUNC int begin(void)
{
    if (wait_idle() != 0 && (flash_io_read_reg(FLASH_REG_SR) & FLASH_SR_BSY)) return -1; /* timed out */
    if (flash_io_read_reg(FLASH_REG_CR) & FLASH_CR_LOCK) {
        flash_io_write_reg(FLASH_REG_KEYR, FLASH_KEY1);
        flash_io_write_reg(FLASH_REG_KEYR, FLASH_KEY2);
    }
    return 0;
}

/* The ART caches may still hold lines of what was just erased or overwritten (a read-back would
 * see the old bytes). RM0090 §3.5.2: a cache can only be reset while disabled; then it is enabled
 * again as it was. */
static RAMFUNC void reset_caches(void)
{
    uint32_t acr = flash_io_read_reg(FLASH_REG_ACR) & ~FLASH_ACR_CACHE_RESETS;
    uint32_t disabled = acr & ~FLASH_ACR_CACHES;
    flash_io_write_reg(FLASH_REG_ACR, disabled);
    flash_io_write_reg(FLASH_REG_ACR, disabled | FLASH_ACR_CACHE_RESETS);
    flash_io_write_reg(FLASH_REG_ACR, disabled);
    flash_io_write_reg(FLASH_REG_ACR, acr);
}

static RAMFUNC void end(void)
{
    flash_io_write_reg(FLASH_REG_CR, FLASH_CR_LOCK); /* also clears PG/SER */
    reset_caches();
}

int flash_region_read(void *ctx, enum hal_region r, uint32_t offset, void *buf, size_t len)
{
    (void)ctx;
    if (!in_range(r, offset, len)) return -1;
    flash_io_read(flash_sector_address(region_sector[r]) + offset, buf, len);
    return 0;
}

const uint8_t *flash_region_map_bytes(void *ctx, enum hal_region r)
{
    (void)ctx;
    if (r != HAL_REGION_MAP_A && r != HAL_REGION_MAP_B) return NULL;
    return flash_io_map(flash_sector_address(region_sector[r]));
}

RAMFUNC int flash_region_write(void *ctx, enum hal_region r, uint32_t offset, const void *buf, size_t len)
{
    (void)ctx;
    if (!in_range(r, offset, len)) return -1;
    if (len == 0) return 0;
    const uint8_t *src = buf;
    uint32_t address = flash_sector_address(region_sector[r]) + offset;
    int rc = begin();
    while (rc == 0 && len > 0) {
        if (address % 4u == 0 && len >= 4u) {
            uint32_t word = (uint32_t)src[0] | (uint32_t)src[1] << 8 | (uint32_t)src[2] << 16 | (uint32_t)src[3] << 24;
            flash_io_write_reg(FLASH_REG_CR, FLASH_CR_PSIZE_X32 | FLASH_CR_PG);
            flash_io_program32(address, word);
            address += 4u, src += 4, len -= 4u;
        } else {
            flash_io_write_reg(FLASH_REG_CR, FLASH_CR_PSIZE_X8 | FLASH_CR_PG);
            flash_io_program8(address, *src);
            address += 1u, src += 1, len -= 1u;
        }
        rc = wait_idle();
    }
    end();
    return rc;
}

RAMFUNC int flash_region_erase(void *ctx, enum hal_region r)
{
    (void)ctx;
    if ((unsigned)r >= HAL_REGION_COUNT) return -1;
    int rc = begin();
    if (rc == 0) {
        /* x32 parallelism erases twice as fast as x8 */
        flash_io_write_reg(FLASH_REG_CR, FLASH_CR_PSIZE_X32 | FLASH_CR_SER |
                                             ((uint32_t)region_sector[r] << FLASH_CR_SNB_SHIFT));
        flash_io_write_reg(FLASH_REG_CR, flash_io_read_reg(FLASH_REG_CR) | FLASH_CR_STRT);
        rc = wait_idle();
    }
    end();
    return rc;
}
