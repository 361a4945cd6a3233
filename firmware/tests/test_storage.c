/* Power loss at every byte: a config save and a map upload (erase, write, verify, commit) cut
 * after each unit of flash work must leave the last good config and map active after reboot. */
#include <stdlib.h>
#include <string.h>

#include "../core/crc.h"
#include "../core/storage.h"
#include "check.h"
#include "fake_hal.h"
#include "table_fixture.h"

static fake_hal_t *f;
static storage_t st;
/* Storage images, saved and restored around each power cut. */
static uint8_t saved_config[2][HAL_CONFIG_REGION_SIZE];
static uint8_t saved_map[2][HAL_MAP_REGION_SIZE];

static void snapshot(void)
{
    memcpy(saved_config, f->config, sizeof saved_config);
    memcpy(saved_map, f->map, sizeof saved_map);
}

static void restore(void)
{
    memcpy(f->config, saved_config, sizeof saved_config);
    memcpy(f->map, saved_map, sizeof saved_map);
    fake_hal_power_on(f);
}

static void fill_config(uint16_t *cfg, uint16_t tag)
{
    for (unsigned i = 0; i < STORAGE_CONFIG_WORDS; i++) cfg[i] = (uint16_t)(tag * 100 + i);
}

static bool config_is(const storage_t *s, uint16_t tag)
{
    uint16_t want[STORAGE_CONFIG_WORDS];
    fill_config(want, tag);
    return s->config_valid && memcmp(s->config, want, sizeof want) == 0;
}

static void save_config(uint16_t tag)
{
    fill_config(st.config, tag);
    CHECK_EQ_INT(storage_commit(&st), STORAGE_OK);
}

static void test_empty_storage_has_no_config_and_no_map(void)
{
    storage_load(&st, &f->hal);
    CHECK(!st.config_valid);
    CHECK_EQ_INT(storage_map_active(&st), -1);
    CHECK_EQ_INT(st.seq, 0);
}

static void test_newest_valid_copy_wins(void)
{
    storage_load(&st, &f->hal);
    save_config(1);
    save_config(2);
    storage_load(&st, &f->hal);
    CHECK(config_is(&st, 2));
    CHECK_EQ_INT(st.seq, 2);
    /* a flipped bit in the newest copy: the older one is used */
    uint8_t *newest = st.region == HAL_REGION_CONFIG_A ? f->config[0] : f->config[1];
    newest[30] ^= 0x10;
    storage_load(&st, &f->hal);
    CHECK(config_is(&st, 1));
    /* both bad: nothing valid (the app then uses the register-map defaults) */
    f->config[0][30] ^= 0x10;
    f->config[1][30] ^= 0x10;
    f->config[0][30] ^= 0x01;
    f->config[1][31] ^= 0x01;
    storage_load(&st, &f->hal);
    CHECK(!st.config_valid);
}

/* The work (bytes programmed + erase units) a config save needs, measured with no cut. */
static long work_of_config_save(void)
{
    restore();
    storage_load(&st, &f->hal);
    long before = f->bytes_programmed;
    save_config(99);
    return f->bytes_programmed - before;
}

static void cut_config_save_everywhere(uint16_t old_tag)
{
    snapshot();
    long work = work_of_config_save();
    CHECK(work > 100);
    printf("  config save: %ld units of flash work, each one a cut point\n", work);
    int wrong = 0, new_seen = 0;
    for (long budget = 0; budget <= work; budget++) {
        restore();
        storage_load(&st, &f->hal);
        f->power_budget = f->bytes_programmed + budget;
        fill_config(st.config, 77);
        int rc = storage_commit(&st);
        fake_hal_power_on(f); /* reboot */
        storage_load(&st, &f->hal);
        bool old_ok = config_is(&st, old_tag), new_ok = config_is(&st, 77);
        if (rc == STORAGE_OK ? !new_ok : !(old_ok || new_ok)) wrong++;
        new_seen += new_ok;
    }
    CHECK_EQ_INT(wrong, 0);
    CHECK(new_seen >= 1); /* the uncut save did land */
    restore();
}

static void test_power_loss_at_every_byte_of_a_config_save(void)
{
    memset(f->config, 0xFF, sizeof f->config);
    fake_hal_power_on(f);
    storage_load(&st, &f->hal);
    save_config(1);
    save_config(2); /* newest in B: the save under test overwrites A */
    cut_config_save_everywhere(2);
    storage_load(&st, &f->hal);
    save_config(3); /* newest in A now: the save under test overwrites B */
    cut_config_save_everywhere(3);
}

#define MAP_GRID 5 /* a fixture table of 1586 bytes */
#define MAP_LEN 1586u
static uint8_t map_bytes[2][MAP_LEN];

static int upload(int which)
{
    storage_map_session_t w;
    const uint8_t *data = map_bytes[which];
    int rc = storage_map_begin(&st, &w, MAP_LEN, crc32_update(0, data, MAP_LEN), (uint16_t)(10 + which));
    /* in chunks of 240 bytes, as file records arrive */
    for (uint32_t off = 0; rc == STORAGE_OK && off < MAP_LEN; off += 240) {
        uint32_t n = MAP_LEN - off < 240 ? MAP_LEN - off : 240;
        rc = storage_map_session_write(&st, &w, off, data + off, n);
    }
    if (rc == STORAGE_OK) rc = storage_map_verify(&st, &w);
    if (rc == STORAGE_OK) rc = storage_map_activate(&st, &w);
    return rc;
}

static bool active_map_is(int which)
{
    static uint8_t got[MAP_LEN];
    int slot = storage_map_active(&st);
    if (slot < 0 || st.map[slot].length != MAP_LEN) return false;
    if (storage_map_read(&st, slot, 0, got, MAP_LEN) != STORAGE_OK) return false;
    return memcmp(got, map_bytes[which], MAP_LEN) == 0 && st.map[slot].version == 10 + which;
}

static void cut_map_upload_everywhere(int old_map, uint16_t cfg_tag)
{
    snapshot();
    restore();
    storage_load(&st, &f->hal);
    long before = f->bytes_programmed;
    CHECK_EQ_INT(upload(!old_map), STORAGE_OK);
    long work = f->bytes_programmed - before;
    CHECK(work > MAP_LEN);
    printf("  map upload: %ld units of flash work, each one a cut point\n", work);
    int wrong = 0, new_seen = 0;
    for (long budget = 0; budget <= work; budget++) {
        restore();
        storage_load(&st, &f->hal);
        f->power_budget = f->bytes_programmed + budget;
        int rc = upload(!old_map);
        fake_hal_power_on(f);
        storage_load(&st, &f->hal);
        bool old_ok = active_map_is(old_map), new_ok = active_map_is(!old_map);
        if (rc == STORAGE_OK ? !new_ok : !(old_ok || new_ok)) wrong++;
        if (!config_is(&st, cfg_tag)) wrong++; /* the config rides along untouched */
        new_seen += new_ok;
    }
    CHECK_EQ_INT(wrong, 0);
    CHECK(new_seen >= 1);
    restore();
}

static void test_power_loss_at_every_byte_of_a_map_upload(void)
{
    CHECK_EQ_INT(fixture_table(map_bytes[0], MAP_LEN, MAP_GRID, 1), MAP_LEN);
    CHECK_EQ_INT(fixture_table(map_bytes[1], MAP_LEN, MAP_GRID, 2), MAP_LEN);
    memset(f->config, 0xFF, sizeof f->config);
    memset(f->map, 0xFF, sizeof f->map);
    fake_hal_power_on(f);
    storage_load(&st, &f->hal);
    save_config(5);
    CHECK_EQ_INT(upload(0), STORAGE_OK); /* map 0 active in slot A */
    storage_load(&st, &f->hal);
    CHECK(active_map_is(0));
    CHECK_EQ_INT(storage_map_active(&st), 0);
    cut_map_upload_everywhere(0, 5); /* map 1 goes to slot B */
    storage_load(&st, &f->hal);
    CHECK_EQ_INT(upload(1), STORAGE_OK);
    storage_load(&st, &f->hal);
    CHECK_EQ_INT(storage_map_active(&st), 1);
    CHECK(st.map_valid[0]); /* the previous map stays as the fallback */
    cut_map_upload_everywhere(1, 5); /* map 0 goes to slot A, replacing the fallback */
}

static void test_map_session_rules(void)
{
    storage_map_session_t w = {0};
    uint8_t b[4] = {1, 2, 3, 4};
    storage_load(&st, &f->hal);
    CHECK_EQ_INT(storage_map_session_write(&st, &w, 0, b, 4), STORAGE_ERR_STATE); /* nothing open */
    CHECK_EQ_INT(storage_map_activate(&st, &w), STORAGE_ERR_STATE);
    CHECK_EQ_INT(storage_map_begin(&st, &w, 0, 0, 0), STORAGE_ERR_RANGE);
    CHECK_EQ_INT(storage_map_begin(&st, &w, HAL_MAP_REGION_SIZE + 1, 0, 0), STORAGE_ERR_RANGE);
    CHECK_EQ_INT(storage_map_begin(&st, &w, 4, crc32_update(0, b, 4), 1), STORAGE_OK);
    CHECK(w.slot != storage_map_active(&st)); /* never the active slot */
    CHECK_EQ_INT(storage_map_session_write(&st, &w, 2, b, 4), STORAGE_ERR_RANGE); /* past the length */
    CHECK_EQ_INT(storage_map_activate(&st, &w), STORAGE_ERR_STATE);               /* not verified */
    CHECK_EQ_INT(storage_map_session_write(&st, &w, 0, b, 3), STORAGE_OK);
    CHECK_EQ_INT(storage_map_verify(&st, &w), STORAGE_ERR_MISMATCH);
    CHECK_EQ_INT(storage_map_session_write(&st, &w, 3, b + 3, 1), STORAGE_OK);
    /* the right CRC, but four bytes are no map table: never activatable */
    CHECK_EQ_INT(storage_map_verify(&st, &w), STORAGE_ERR_FORMAT);
    CHECK_EQ_INT(storage_map_activate(&st, &w), STORAGE_ERR_STATE);
    static uint8_t table[MAP_LEN];
    CHECK_EQ_INT(fixture_table(table, MAP_LEN, MAP_GRID, 3), MAP_LEN);
    CHECK_EQ_INT(storage_map_begin(&st, &w, MAP_LEN, crc32_update(0, table, MAP_LEN), 1), STORAGE_OK);
    CHECK_EQ_INT(storage_map_session_write(&st, &w, 0, table, MAP_LEN), STORAGE_OK);
    CHECK_EQ_INT(storage_map_verify(&st, &w), STORAGE_OK);
    CHECK_EQ_INT(storage_map_activate(&st, &w), STORAGE_OK);
    CHECK_EQ_INT(storage_map_active(&st), w.slot);
}

/* A slot committed by older firmware that held junk with the right CRC: not a valid map at boot. */
static void test_a_committed_slot_that_is_no_table_is_invalid_at_boot(void)
{
    storage_load(&st, &f->hal);
    static uint8_t junk[64];
    for (int i = 0; i < 64; i++) junk[i] = (uint8_t)(i * 37 + 1);
    int slot = storage_map_active(&st) == 0 ? 1 : 0;
    CHECK_EQ_INT(storage_map_erase(&st, slot), STORAGE_OK);
    CHECK_EQ_INT(storage_map_write(&st, slot, 0, junk, sizeof junk), STORAGE_OK);
    st.map[slot] = (storage_map_slot_t){.length = sizeof junk, .crc32 = crc32_update(0, junk, sizeof junk),
                                        .seq = 1000, .version = 9};
    CHECK_EQ_INT(storage_commit(&st), STORAGE_OK); /* as if activated without the header check */
    storage_load(&st, &f->hal);
    CHECK(!st.map_valid[slot]);
    CHECK(storage_map_active(&st) != slot);
}

static void test_erases_are_counted_persisted_and_rate_limited(void)
{
    memset(f->config, 0xFF, sizeof f->config);
    fake_hal_power_on(f);
    storage_load(&st, &f->hal);
    CHECK_EQ_INT(st.erase_count[HAL_REGION_CONFIG_A] + st.erase_count[HAL_REGION_CONFIG_B], 0);
    uint32_t map_a = st.erase_count[HAL_REGION_MAP_A];
    for (unsigned i = 0; i < STORAGE_ERASE_BURST - 1; i++) save_config((uint16_t)(10 + i));
    CHECK_EQ_INT(storage_map_erase(&st, 0), STORAGE_OK); /* the 8th erase of the burst */
    fill_config(st.config, 40);
    CHECK_EQ_INT(storage_commit(&st), STORAGE_ERR_BUSY); /* the 9th: refused, nothing touched */
    CHECK_EQ_INT(storage_map_erase(&st, 1), STORAGE_ERR_BUSY);
    CHECK_EQ_INT(st.erase_refusals, 2);
    CHECK_EQ_INT(st.seq, STORAGE_ERASE_BURST - 1);
    CHECK_EQ_INT(st.erase_count[HAL_REGION_CONFIG_A], 4);
    CHECK_EQ_INT(st.erase_count[HAL_REGION_CONFIG_B], 3);
    CHECK_EQ_INT(st.erase_count[HAL_REGION_MAP_A], map_a + 1);
    /* one more per refill interval */
    f->now_us += STORAGE_ERASE_REFILL_US - 1000;
    CHECK_EQ_INT(storage_commit(&st), STORAGE_ERR_BUSY);
    f->now_us += 1000;
    CHECK_EQ_INT(storage_commit(&st), STORAGE_OK);
    CHECK_EQ_INT(storage_commit(&st), STORAGE_ERR_BUSY);
    /* the counts come back at boot, the map erase included (this commit carried it) */
    storage_load(&st, &f->hal);
    CHECK(config_is(&st, 40));
    CHECK_EQ_INT(st.erase_count[HAL_REGION_CONFIG_A], 4);
    CHECK_EQ_INT(st.erase_count[HAL_REGION_CONFIG_B], 4); /* the saves alternate regions */
    CHECK_EQ_INT(st.erase_count[HAL_REGION_MAP_A], map_a + 1);
    CHECK_EQ_INT(st.erase_budget, STORAGE_ERASE_BURST); /* full again after a boot */
}

/* A record of format 1 (before the erase counts) is still read: config and map table kept. */
static void test_a_format_1_record_is_still_read(void)
{
    memset(f->config, 0xFF, sizeof f->config);
    fake_hal_power_on(f);
    storage_load(&st, &f->hal);
    save_config(6);
    int region = st.region;
    uint8_t *b = f->config[region];
    uint32_t words = (uint32_t)(b[6] | b[7] << 8), v2_header = 52u + 4u * HAL_REGION_COUNT;
    static uint8_t v1[HAL_CONFIG_REGION_SIZE];
    memset(v1, 0xFF, sizeof v1);
    memcpy(v1, b, 52);
    v1[4] = 1;
    memcpy(v1 + 52, b + v2_header, 2 * words);
    uint32_t size = 52u + 2u * words + 4u, crc = crc32_update(0, v1, size - 4);
    for (int i = 0; i < 4; i++) v1[size - 4 + i] = (uint8_t)(crc >> (8 * i));
    memcpy(b, v1, sizeof v1);
    storage_load(&st, &f->hal);
    CHECK(config_is(&st, 6));
    CHECK_EQ_INT(st.region, region);
    CHECK_EQ_INT(st.erase_count[HAL_REGION_CONFIG_A] + st.erase_count[HAL_REGION_CONFIG_B], 0);
}

int main(void)
{
    f = fake_hal_new();
    RUN_TEST(test_empty_storage_has_no_config_and_no_map);
    RUN_TEST(test_newest_valid_copy_wins);
    RUN_TEST(test_power_loss_at_every_byte_of_a_config_save);
    RUN_TEST(test_power_loss_at_every_byte_of_a_map_upload);
    RUN_TEST(test_map_session_rules);
    RUN_TEST(test_a_committed_slot_that_is_no_table_is_invalid_at_boot);
    RUN_TEST(test_erases_are_counted_persisted_and_rate_limited);
    RUN_TEST(test_a_format_1_record_is_still_read);
    fake_hal_free(f);
    return CHECK_SUMMARY();
}
