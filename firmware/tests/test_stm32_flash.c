/* The STM32F405 flash driver (ports/stm32f405/flash.c) against a fake flash controller that
 * follows RM0090 §3.5-3.8: the unlock key sequence (a wrong key locks CR until reset), CR ignored
 * while locked, BSY for a while after every operation, PGSERR/PGPERR/PGAERR for programming
 * without PG, at the wrong width or unaligned, NOR semantics (programming only clears bits), sector
 * erase to 0xFF, and ART caches that keep serving what they held until reset — a reset counts
 * only while the cache is disabled. Reads through the data cache are modelled pessimistically:
 * with DCEN set they return the flash as it was at the last cache reset. */
#include <stdint.h>
#include <string.h>

#include "check.h"
#include "flash.h"
#include "flash_io.h"
#include "flash_layout.h"
#include "regs.h"

#define FLASH_BYTES (1024u * 1024u)
#define BUSY_POLLS 3 /* SR reads that still see BSY after an operation starts */

static struct {
    uint8_t memory[FLASH_BYTES];
    uint8_t dcache_view[FLASH_BYTES]; /* what the data cache serves until it is reset */
    uint32_t acr, sr, cr;
    int key_stage;     /* 0: expect KEY1, 1: expect KEY2 */
    int locked_for_good;
    int busy_polls;
    int program8_ops, program32_ops, erases;
    int erased_sector;
    int violations;    /* accesses the reference manual forbids (a bus stall or ignored write) */
    int cache_stale;   /* flash changed since the caches were last reset */
    uint32_t inject_sr_error; /* raised by the next operation */
} fc;

static void fake_power_on(void)
{
    memset(&fc, 0, sizeof fc);
    memset(fc.memory, 0xFF, sizeof fc.memory);
    memset(fc.dcache_view, 0xFF, sizeof fc.dcache_view);
    fc.cr = FLASH_CR_LOCK;
    fc.acr = FLASH_ACR_PRFTEN | FLASH_ACR_ICEN | FLASH_ACR_DCEN | 5u; /* as clock_init leaves it */
    fc.erased_sector = -1;
}

static int busy(void) { return fc.busy_polls > 0; }

static void start_operation(void)
{
    fc.busy_polls = BUSY_POLLS;
    fc.cache_stale = 1;
    fc.sr |= fc.inject_sr_error;
    fc.inject_sr_error = 0;
}

uint32_t flash_io_read_reg(enum flash_reg reg)
{
    switch (reg) {
    case FLASH_REG_ACR: return fc.acr;
    case FLASH_REG_SR:
        if (fc.busy_polls > 0) {
            fc.busy_polls--;
            return fc.sr | FLASH_SR_BSY;
        }
        return fc.sr;
    case FLASH_REG_CR: return fc.cr;
    default: return 0;
    }
}

void flash_io_write_reg(enum flash_reg reg, uint32_t value)
{
    switch (reg) {
    case FLASH_REG_ACR: {
        uint32_t caches_after = value & (FLASH_ACR_ICEN | FLASH_ACR_DCEN);
        if (value & (FLASH_ACR_ICRST | FLASH_ACR_DCRST)) {
            /* a reset bit only works on a disabled cache */
            if (((value & FLASH_ACR_ICRST) && (caches_after & FLASH_ACR_ICEN)) ||
                ((value & FLASH_ACR_DCRST) && (caches_after & FLASH_ACR_DCEN)))
                fc.violations++;
            else if ((value & FLASH_ACR_ICRST) && (value & FLASH_ACR_DCRST)) {
                fc.cache_stale = 0;
                memcpy(fc.dcache_view, fc.memory, sizeof fc.memory);
            }
        }
        fc.acr = value;
        return;
    }
    case FLASH_REG_KEYR:
        if (fc.locked_for_good || !(fc.cr & FLASH_CR_LOCK)) {
            fc.locked_for_good = 1;
            fc.violations++;
        } else if (fc.key_stage == 0 && value == FLASH_KEY1) {
            fc.key_stage = 1;
        } else if (fc.key_stage == 1 && value == FLASH_KEY2) {
            fc.key_stage = 0;
            fc.cr &= ~FLASH_CR_LOCK;
        } else {
            fc.locked_for_good = 1;
            fc.violations++;
        }
        return;
    case FLASH_REG_SR: fc.sr &= ~(value & FLASH_SR_ERRORS); return;
    case FLASH_REG_CR:
        if (busy()) { /* the AHB bus stalls until BSY clears: a sequence error */
            fc.violations++;
            return;
        }
        if (fc.cr & FLASH_CR_LOCK) {
            if (!(value & FLASH_CR_LOCK)) fc.violations++; /* ignored: CR is locked */
            return;
        }
        fc.cr = value & ~FLASH_CR_STRT;
        if ((value & FLASH_CR_STRT) && (value & FLASH_CR_SER)) {
            uint32_t sector = (value & FLASH_CR_SNB_MASK) >> FLASH_CR_SNB_SHIFT;
            if (sector >= FLASH_SECTOR_COUNT || (value & FLASH_CR_PG)) {
                fc.sr |= 1u << 7; /* PGSERR */
                return;
            }
            memset(fc.memory + flash_sector_address(sector) - FLASH_MEMORY_BASE, 0xFF, flash_sector_size(sector));
            fc.erases++;
            fc.erased_sector = (int)sector;
            start_operation();
        }
        return;
    default: fc.violations++;
    }
}

static uint8_t *program_target(uint32_t address, uint32_t width, uint32_t psize)
{
    if (busy()) fc.violations++;
    if ((fc.cr & FLASH_CR_LOCK) || !(fc.cr & FLASH_CR_PG)) {
        fc.sr |= 1u << 7; /* PGSERR */
        return NULL;
    }
    if ((fc.cr & FLASH_CR_PSIZE_MASK) != psize) {
        fc.sr |= 1u << 6; /* PGPERR */
        return NULL;
    }
    if (address % width != 0) {
        fc.sr |= 1u << 5; /* PGAERR */
        return NULL;
    }
    if (address < FLASH_MEMORY_BASE || address - FLASH_MEMORY_BASE > FLASH_BYTES - width) {
        fc.violations++;
        return NULL;
    }
    start_operation();
    return fc.memory + (address - FLASH_MEMORY_BASE);
}

void flash_io_program8(uint32_t address, uint8_t value)
{
    uint8_t *p = program_target(address, 1, FLASH_CR_PSIZE_X8);
    if (p) {
        *p &= value;
        fc.program8_ops++;
    }
}

void flash_io_program32(uint32_t address, uint32_t value)
{
    uint8_t *p = program_target(address, 4, FLASH_CR_PSIZE_X32);
    if (p) {
        for (int i = 0; i < 4; i++) p[i] &= (uint8_t)(value >> (8 * i));
        fc.program32_ops++;
    }
}

void flash_io_read(uint32_t address, void *buf, size_t len)
{
    if (busy()) fc.violations++;
    const uint8_t *src = (fc.acr & FLASH_ACR_DCEN) ? fc.dcache_view : fc.memory;
    memcpy(buf, src + (address - FLASH_MEMORY_BASE), len);
}

const uint8_t *flash_io_map(uint32_t address)
{
    return ((fc.acr & FLASH_ACR_DCEN) ? fc.dcache_view : fc.memory) + (address - FLASH_MEMORY_BASE);
}

/* ---------------------------------------------------------------- the tests */

static const struct {
    enum hal_region region;
    uint32_t sector, size;
} layout[] = {
    {HAL_REGION_CONFIG_A, FLASH_STORAGE_SECTOR_CONFIG_A, HAL_CONFIG_REGION_SIZE},
    {HAL_REGION_CONFIG_B, FLASH_STORAGE_SECTOR_CONFIG_B, HAL_CONFIG_REGION_SIZE},
    {HAL_REGION_MAP_A, FLASH_STORAGE_SECTOR_MAP_A, HAL_MAP_REGION_SIZE},
    {HAL_REGION_MAP_B, FLASH_STORAGE_SECTOR_MAP_B, HAL_MAP_REGION_SIZE},
};

static uint8_t *sector_bytes(uint32_t sector) { return fc.memory + flash_sector_address(sector) - FLASH_MEMORY_BASE; }

/* After every operation: locked, caches reset and enabled as before, no forbidden access. */
static void check_clean_end(uint32_t acr_before)
{
    CHECK(fc.cr & FLASH_CR_LOCK);
    CHECK(!(fc.cr & (FLASH_CR_PG | FLASH_CR_SER)));
    CHECK_EQ_INT(fc.cache_stale, 0);
    CHECK_EQ_INT(fc.acr, acr_before);
    CHECK_EQ_INT(fc.violations, 0);
    CHECK_EQ_INT(fc.locked_for_good, 0);
    CHECK(!busy());
}

static void test_each_region_is_one_whole_storage_sector(void)
{
    for (size_t i = 0; i < sizeof layout / sizeof layout[0]; i++) {
        CHECK_EQ_INT(flash_sector_size(layout[i].sector), layout[i].size);
        for (size_t j = 0; j < i; j++) CHECK(layout[i].sector != layout[j].sector);
    }
    CHECK_EQ_INT(flash_sector_address(2), 0x08008000u);
    CHECK_EQ_INT(flash_sector_address(4), 0x08010000u);
    CHECK_EQ_INT(flash_sector_address(5), 0x08020000u);
    CHECK_EQ_INT(flash_sector_address(11) + flash_sector_size(11), FLASH_MEMORY_BASE + FLASH_BYTES);
}

static void test_erase_clears_exactly_its_sector_and_resets_the_caches(void)
{
    for (size_t i = 0; i < sizeof layout / sizeof layout[0]; i++) {
        fake_power_on();
        memset(fc.memory, 0x00, sizeof fc.memory);
        memset(fc.dcache_view, 0x00, sizeof fc.dcache_view);
        uint32_t acr = fc.acr;
        CHECK_EQ_INT(flash_region_erase(NULL, layout[i].region), 0);
        CHECK_EQ_INT(fc.erases, 1);
        CHECK_EQ_INT(fc.erased_sector, (int)layout[i].sector);
        check_clean_end(acr);
        /* the whole region reads erased through the cache; the bytes either side are untouched */
        static uint8_t back[HAL_MAP_REGION_SIZE];
        CHECK_EQ_INT(flash_region_read(NULL, layout[i].region, 0, back, layout[i].size), 0);
        size_t ff = 0;
        while (ff < layout[i].size && back[ff] == 0xFF) ff++;
        CHECK_EQ_INT(ff, layout[i].size);
        CHECK_EQ_INT(sector_bytes(layout[i].sector)[-1], 0x00);
        CHECK_EQ_INT(sector_bytes(layout[i].sector)[layout[i].size], 0x00);
    }
}

static void test_erase_keeps_caches_disabled_when_they_were(void)
{
    fake_power_on();
    fc.acr = 0; /* the HSI fallback never turns the caches on */
    CHECK_EQ_INT(flash_region_erase(NULL, HAL_REGION_CONFIG_B), 0);
    check_clean_end(0);
}

static void test_write_programs_words_and_only_unaligned_ends_as_bytes(void)
{
    static const struct { uint32_t offset, len, words, bytes; } cases[] = {
        {0, 244, 61, 0}, {1, 10, 1, 6}, {3, 1, 0, 1}, {2, 4, 0, 4}, {4096 - 3, 7, 1, 3}, {0, 3, 0, 3},
    };
    uint8_t data[256];
    for (size_t i = 0; i < sizeof data; i++) data[i] = (uint8_t)(i * 37u + 11u);
    for (size_t c = 0; c < sizeof cases / sizeof cases[0]; c++) {
        fake_power_on();
        uint32_t acr = fc.acr;
        CHECK_EQ_INT(flash_region_write(NULL, HAL_REGION_MAP_B, cases[c].offset, data, cases[c].len), 0);
        CHECK_EQ_INT(fc.program32_ops, cases[c].words);
        CHECK_EQ_INT(fc.program8_ops, cases[c].bytes);
        CHECK_EQ_INT(fc.sr, 0);
        check_clean_end(acr);
        uint8_t back[256];
        CHECK_EQ_INT(flash_region_read(NULL, HAL_REGION_MAP_B, cases[c].offset, back, cases[c].len), 0);
        CHECK_MEM(back, data, cases[c].len);
        uint8_t *sector = sector_bytes(FLASH_STORAGE_SECTOR_MAP_B);
        if (cases[c].offset > 0) CHECK_EQ_INT(sector[cases[c].offset - 1], 0xFF);
        CHECK_EQ_INT(sector[cases[c].offset + cases[c].len], 0xFF);
    }
}

static void test_write_lands_in_the_regions_own_sector(void)
{
    fake_power_on();
    const uint8_t record[8] = {1, 2, 3, 4, 5, 6, 7, 8};
    CHECK_EQ_INT(flash_region_write(NULL, HAL_REGION_CONFIG_B, 16, record, sizeof record), 0);
    CHECK_MEM(sector_bytes(FLASH_STORAGE_SECTOR_CONFIG_B) + 16, record, sizeof record);
    CHECK_EQ_INT(sector_bytes(FLASH_STORAGE_SECTOR_CONFIG_A)[16], 0xFF);
    CHECK_EQ_INT(flash_region_write(NULL, HAL_REGION_MAP_A, HAL_MAP_REGION_SIZE - 8, record, sizeof record), 0);
    CHECK_MEM(sector_bytes(FLASH_STORAGE_SECTOR_MAP_A) + HAL_MAP_REGION_SIZE - 8, record, sizeof record);
    CHECK_EQ_INT(sector_bytes(FLASH_STORAGE_SECTOR_MAP_B)[0], 0xFF);
}

static void test_out_of_range_is_refused_without_touching_the_controller(void)
{
    fake_power_on();
    uint8_t buf[8] = {0};
    CHECK(flash_region_write(NULL, HAL_REGION_CONFIG_A, HAL_CONFIG_REGION_SIZE - 4, buf, 8) < 0);
    CHECK(flash_region_write(NULL, HAL_REGION_MAP_A, HAL_MAP_REGION_SIZE + 1, buf, 0) < 0);
    CHECK(flash_region_write(NULL, HAL_REGION_COUNT, 0, buf, 1) < 0);
    CHECK(flash_region_erase(NULL, HAL_REGION_COUNT) < 0);
    CHECK(flash_region_read(NULL, HAL_REGION_CONFIG_B, 1, buf, HAL_CONFIG_REGION_SIZE) < 0);
    CHECK_EQ_INT(fc.erases + fc.program8_ops + fc.program32_ops, 0);
    CHECK(fc.cr & FLASH_CR_LOCK);
    CHECK_EQ_INT(fc.acr & (FLASH_ACR_ICEN | FLASH_ACR_DCEN), FLASH_ACR_ICEN | FLASH_ACR_DCEN);
}

static void test_an_error_the_controller_raises_fails_the_write_and_is_cleared(void)
{
    fake_power_on();
    uint32_t acr = fc.acr;
    const uint8_t data[12] = {0};
    fc.inject_sr_error = 1u << 4; /* WRPERR: the sector is write-protected */
    CHECK(flash_region_write(NULL, HAL_REGION_MAP_A, 0, data, sizeof data) < 0);
    CHECK_EQ_INT(fc.program32_ops, 1); /* stopped at the first failed word */
    CHECK_EQ_INT(fc.sr, 0);
    check_clean_end(acr);
    /* the next operation is not blamed for it */
    CHECK_EQ_INT(flash_region_write(NULL, HAL_REGION_MAP_A, 4, data, 4), 0);
}

static void test_a_stale_error_flag_does_not_fail_the_next_operation(void)
{
    fake_power_on();
    uint32_t acr = fc.acr;
    fc.sr = 1u << 7; /* PGSERR left behind, e.g. by a debugger */
    CHECK_EQ_INT(flash_region_erase(NULL, HAL_REGION_CONFIG_A), 0);
    CHECK_EQ_INT(fc.erases, 1);
    check_clean_end(acr);
}

static void test_erase_then_write_then_read_back_sees_the_new_bytes(void)
{
    /* the storage layer's pattern: a config record rewritten in place of an older one */
    fake_power_on();
    uint8_t old[32], new[32], back[32];
    memset(old, 0x5A, sizeof old);
    for (size_t i = 0; i < sizeof new; i++) new[i] = (uint8_t)i;
    CHECK_EQ_INT(flash_region_write(NULL, HAL_REGION_CONFIG_A, 0, old, sizeof old), 0);
    CHECK_EQ_INT(flash_region_read(NULL, HAL_REGION_CONFIG_A, 0, back, sizeof back), 0);
    CHECK_MEM(back, old, sizeof old);
    CHECK_EQ_INT(flash_region_erase(NULL, HAL_REGION_CONFIG_A), 0);
    CHECK_EQ_INT(flash_region_write(NULL, HAL_REGION_CONFIG_A, 0, new, sizeof new), 0);
    CHECK_EQ_INT(flash_region_read(NULL, HAL_REGION_CONFIG_A, 0, back, sizeof back), 0);
    CHECK_MEM(back, new, sizeof new);
}

static void test_map_regions_read_in_place_at_their_sectors_and_config_regions_do_not(void)
{
    /* the fit reads its table where it lies: the pointer must be the slot's sector, showing what was written */
    fake_power_on();
    const uint8_t table[4] = {0x89, 'T', 'R', 'L'};
    CHECK_EQ_INT(flash_region_erase(NULL, HAL_REGION_MAP_B), 0);
    CHECK_EQ_INT(flash_region_write(NULL, HAL_REGION_MAP_B, 0, table, sizeof table), 0);
    const uint8_t *b = flash_region_map_bytes(NULL, HAL_REGION_MAP_B);
    CHECK(b == flash_io_map(flash_sector_address(FLASH_STORAGE_SECTOR_MAP_B)));
    CHECK_MEM(b, table, sizeof table);
    CHECK(flash_region_map_bytes(NULL, HAL_REGION_MAP_A) == flash_io_map(flash_sector_address(FLASH_STORAGE_SECTOR_MAP_A)));
    CHECK(flash_region_map_bytes(NULL, HAL_REGION_CONFIG_A) == NULL);
    CHECK(flash_region_map_bytes(NULL, HAL_REGION_COUNT) == NULL);
}

int main(void)
{
    RUN_TEST(test_each_region_is_one_whole_storage_sector);
    RUN_TEST(test_erase_clears_exactly_its_sector_and_resets_the_caches);
    RUN_TEST(test_erase_keeps_caches_disabled_when_they_were);
    RUN_TEST(test_write_programs_words_and_only_unaligned_ends_as_bytes);
    RUN_TEST(test_write_lands_in_the_regions_own_sector);
    RUN_TEST(test_out_of_range_is_refused_without_touching_the_controller);
    RUN_TEST(test_an_error_the_controller_raises_fails_the_write_and_is_cleared);
    RUN_TEST(test_a_stale_error_flag_does_not_fail_the_next_operation);
    RUN_TEST(test_erase_then_write_then_read_back_sees_the_new_bytes);
    RUN_TEST(test_map_regions_read_in_place_at_their_sectors_and_config_regions_do_not);
    return CHECK_SUMMARY();
}
