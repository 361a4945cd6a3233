/* System records and map slots; see storage.h for the power-loss argument.
 * Records are serialised byte by byte (little-endian) so the layout never depends on a compiler's
 * struct padding: the sim's storage file and the MCU's flash hold the same bytes. */
#include "storage.h"

#include <string.h>

#include "crc.h"
#include "map_table.h"

/* Record layout: magic, u16 format, u16 config words, u32 seq, u32 register-map hash, u16 flags,
 * the map table at 20 (16 bytes per slot), from format 2 the erase counts (u32 per region) at 52,
 * then the config words and a CRC-32. Format 1 records (no erase counts) are still read. */
#define RECORD_MAGIC 0x5254534Du /* "MSTR" */
#define RECORD_FORMAT 2u
#define RECORD_V1_HEADER_BYTES 52u /* through the map table */
#define RECORD_HEADER_BYTES (RECORD_V1_HEADER_BYTES + 4u * HAL_REGION_COUNT)
#define RECORD_MAX_WORDS 512u      /* sanity bound when reading a foreign record */
#define RECORD_BYTES(header, words) ((header) + 2u * (words) + 4u)
#define FLAG_CONFIG_VALID 1u

static void put16(uint8_t *p, uint16_t v) { p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); }
static void put32(uint8_t *p, uint32_t v) { put16(p, (uint16_t)v); put16(p + 2, (uint16_t)(v >> 16)); }
static uint16_t get16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }
static uint32_t get32(const uint8_t *p) { return get16(p) | ((uint32_t)get16(p + 2) << 16); }

static uint32_t map_region_size(void) { return HAL_MAP_REGION_SIZE; }

/* Parses the record in `region` into `out` (config + map table, not the map validity).
 * Returns its sequence number, 0 when the region holds no valid record. */
static uint32_t read_record(const hal_t *hal, int region, storage_t *out)
{
    static uint8_t buf[RECORD_BYTES(RECORD_HEADER_BYTES, RECORD_MAX_WORDS)];
    if (hal->storage_read(hal->ctx, (enum hal_region)region, 0, buf, RECORD_V1_HEADER_BYTES) != 0) return 0;
    uint16_t format = get16(buf + 4);
    if (get32(buf) != RECORD_MAGIC || (format != 1u && format != RECORD_FORMAT)) return 0;
    uint32_t header = format == 1u ? RECORD_V1_HEADER_BYTES : RECORD_HEADER_BYTES;
    uint16_t words = get16(buf + 6);
    if (words > RECORD_MAX_WORDS) return 0;
    uint32_t size = RECORD_BYTES(header, words);
    if (hal->storage_read(hal->ctx, (enum hal_region)region, 0, buf, size) != 0) return 0;
    if (crc32_update(0, buf, size - 4) != get32(buf + size - 4)) return 0;
    uint32_t seq = get32(buf + 8);
    if (seq == 0) return 0;
    for (int s = 0; s < STORAGE_MAP_SLOTS; s++) {
        const uint8_t *m = buf + 20 + 16 * s;
        out->map[s] = (storage_map_slot_t){
            .length = get32(m), .crc32 = get32(m + 4), .seq = get32(m + 8), .version = get16(m + 12)};
        if (out->map[s].length > map_region_size()) out->map[s].length = 0;
    }
    for (int r = 0; r < HAL_REGION_COUNT; r++)
        out->erase_count[r] = format == 1u ? 0u : get32(buf + RECORD_V1_HEADER_BYTES + 4 * r);
    bool has_config = get16(buf + 16) & FLAG_CONFIG_VALID;
    out->config_valid = has_config && get32(buf + 12) == TRIMETER_REGMAP_HASH && words == STORAGE_CONFIG_WORDS;
    out->config_other_map = has_config && !out->config_valid;
    if (out->config_valid)
        for (unsigned i = 0; i < STORAGE_CONFIG_WORDS; i++) out->config[i] = get16(buf + header + 2 * i);
    return seq;
}

int storage_map_crc(const storage_t *st, int slot, uint32_t length, uint32_t *crc_out)
{
    uint8_t chunk[256];
    uint32_t crc = 0;
    if (slot < 0 || slot >= STORAGE_MAP_SLOTS || length > map_region_size()) return STORAGE_ERR_RANGE;
    for (uint32_t off = 0; off < length; off += sizeof chunk) {
        uint32_t n = length - off < sizeof chunk ? length - off : (uint32_t)sizeof chunk;
        if (st->hal->storage_read(st->hal->ctx, (enum hal_region)(HAL_REGION_MAP_A + slot), off, chunk, n) != 0)
            return STORAGE_ERR_IO;
        crc = crc32_update(crc, chunk, n);
    }
    *crc_out = crc;
    return STORAGE_OK;
}

/* The slot's first `length` bytes: their CRC-32 is `expected_crc` (else MISMATCH) and they are a
 * map table the firmware accepts (else FORMAT). One pass: the CRC of all but the last 4 bytes is
 * also the table's own body CRC. */
static int check_slot_table(const storage_t *st, int slot, uint32_t length, uint32_t expected_crc)
{
    uint32_t body = 0, crc;
    uint8_t tail[4] = {0};
    static uint8_t header[MAP_TABLE_HEADER_BYTES];
    uint32_t body_len = length < 4u ? length : length - 4u;
    int rc = storage_map_crc(st, slot, body_len, &body);
    if (rc == STORAGE_OK && body_len < length) rc = storage_map_read(st, slot, body_len, tail, 4);
    if (rc != STORAGE_OK) return rc;
    crc = crc32_update(body, tail, length - body_len);
    if (crc != expected_crc) return STORAGE_ERR_MISMATCH;
    memset(header, 0, sizeof header);
    if (length >= MAP_TABLE_HEADER_BYTES && storage_map_read(st, slot, 0, header, sizeof header) != STORAGE_OK)
        return STORAGE_ERR_IO;
    return map_table_check(header, length, body, get32(tail)) == MAP_TABLE_OK ? STORAGE_OK : STORAGE_ERR_FORMAT;
}

void storage_load(storage_t *st, const hal_t *hal)
{
    memset(st, 0, sizeof *st);
    st->hal = hal;
    st->region = -1;
    static storage_t candidate; /* static: keeps the stack small on the MCU */
    for (int region = HAL_REGION_CONFIG_A; region <= HAL_REGION_CONFIG_B; region++) {
        memset(&candidate, 0, sizeof candidate);
        uint32_t seq = read_record(hal, region, &candidate);
        if (seq > st->seq) {
            candidate.hal = hal;
            candidate.seq = seq;
            candidate.region = region;
            *st = candidate;
        }
    }
    for (int s = 0; s < STORAGE_MAP_SLOTS; s++)
        st->map_valid[s] = st->map[s].length > 0 && st->map[s].seq > 0 &&
                           check_slot_table(st, s, st->map[s].length, st->map[s].crc32) == STORAGE_OK;
    st->config_stored = st->config_valid;
    st->erase_budget = STORAGE_ERASE_BURST;
    st->erase_refill_mark_us = hal->now_us(hal->ctx);
}

void storage_poll(storage_t *st, uint32_t now_us)
{
    while (st->erase_budget < STORAGE_ERASE_BURST && now_us - st->erase_refill_mark_us >= STORAGE_ERASE_REFILL_US) {
        st->erase_budget++;
        st->erase_refill_mark_us += STORAGE_ERASE_REFILL_US;
    }
    if (st->erase_budget >= STORAGE_ERASE_BURST) st->erase_refill_mark_us = now_us; /* full: the clock restarts */
}

/* The one way anything is erased: rate limit, then count, then erase. */
static int erase_region(storage_t *st, enum hal_region region)
{
    storage_poll(st, st->hal->now_us(st->hal->ctx));
    if (st->erase_budget == 0) {
        st->erase_refusals++;
        return STORAGE_ERR_BUSY;
    }
    st->erase_budget--;
    st->erase_count[region]++;
    return st->hal->storage_erase(st->hal->ctx, region) != 0 ? STORAGE_ERR_IO : STORAGE_OK;
}

int storage_map_active(const storage_t *st)
{
    int best = -1;
    for (int s = 0; s < STORAGE_MAP_SLOTS; s++)
        if (st->map_valid[s] && (best < 0 || st->map[s].seq > st->map[best].seq)) best = s;
    return best;
}

int storage_commit(storage_t *st)
{
    static uint8_t buf[RECORD_BYTES(RECORD_HEADER_BYTES, STORAGE_CONFIG_WORDS)];
    const uint32_t size = sizeof buf;
    uint32_t seq = st->seq + 1;
    /* Overwrite the region that does not hold the newest valid record (A when none is valid). */
    int region = st->region == HAL_REGION_CONFIG_A ? HAL_REGION_CONFIG_B : HAL_REGION_CONFIG_A;
    const hal_t *hal = st->hal;
    int rc = erase_region(st, (enum hal_region)region); /* first: the record carries its count */
    if (rc != STORAGE_OK) return rc;
    memset(buf, 0, size);
    put32(buf, RECORD_MAGIC);
    put16(buf + 4, RECORD_FORMAT);
    put16(buf + 6, STORAGE_CONFIG_WORDS);
    put32(buf + 8, seq);
    put32(buf + 12, TRIMETER_REGMAP_HASH);
    put16(buf + 16, FLAG_CONFIG_VALID);
    for (int s = 0; s < STORAGE_MAP_SLOTS; s++) {
        uint8_t *m = buf + 20 + 16 * s;
        put32(m, st->map[s].length);
        put32(m + 4, st->map[s].crc32);
        put32(m + 8, st->map[s].seq);
        put16(m + 12, st->map[s].version);
    }
    for (int r = 0; r < HAL_REGION_COUNT; r++) put32(buf + RECORD_V1_HEADER_BYTES + 4 * r, st->erase_count[r]);
    for (unsigned i = 0; i < STORAGE_CONFIG_WORDS; i++) put16(buf + RECORD_HEADER_BYTES + 2 * i, st->config[i]);
    put32(buf + size - 4, crc32_update(0, buf, size - 4));

    if (hal->storage_write(hal->ctx, (enum hal_region)region, 0, buf, size) != 0) return STORAGE_ERR_IO;
    /* Read back: a record we can't read is no commit. */
    static storage_t check;
    memset(&check, 0, sizeof check);
    if (read_record(hal, region, &check) != seq) return STORAGE_ERR_IO;
    st->seq = seq;
    st->region = region;
    st->config_valid = true;
    st->config_stored = true;
    return STORAGE_OK;
}

int storage_map_erase(storage_t *st, int slot)
{
    if (slot < 0 || slot >= STORAGE_MAP_SLOTS) return STORAGE_ERR_RANGE;
    int rc = erase_region(st, (enum hal_region)(HAL_REGION_MAP_A + slot));
    /* its bytes are (partly) gone; the record still names it until the next commit */
    if (rc != STORAGE_ERR_BUSY) st->map_valid[slot] = false;
    return rc;
}

int storage_map_write(storage_t *st, int slot, uint32_t offset, const uint8_t *data, uint32_t len)
{
    if (slot < 0 || slot >= STORAGE_MAP_SLOTS || offset > map_region_size() || len > map_region_size() - offset)
        return STORAGE_ERR_RANGE;
    st->map_valid[slot] = false;
    if (st->hal->storage_write(st->hal->ctx, (enum hal_region)(HAL_REGION_MAP_A + slot), offset, data, len) != 0)
        return STORAGE_ERR_IO;
    return STORAGE_OK;
}

const uint8_t *storage_map_active_bytes(const storage_t *st, uint32_t *length)
{
    int slot = storage_map_active(st);
    if (slot < 0 || !st->hal->storage_map_bytes) return NULL;
    const uint8_t *bytes = st->hal->storage_map_bytes(st->hal->ctx, (enum hal_region)(HAL_REGION_MAP_A + slot));
    if (bytes) *length = st->map[slot].length;
    return bytes;
}

int storage_map_read(const storage_t *st, int slot, uint32_t offset, uint8_t *data, uint32_t len)
{
    if (slot < 0 || slot >= STORAGE_MAP_SLOTS || offset > map_region_size() || len > map_region_size() - offset)
        return STORAGE_ERR_RANGE;
    if (st->hal->storage_read(st->hal->ctx, (enum hal_region)(HAL_REGION_MAP_A + slot), offset, data, len) != 0)
        return STORAGE_ERR_IO;
    return STORAGE_OK;
}

int storage_map_begin(storage_t *st, storage_map_session_t *w, uint32_t length, uint32_t crc32, uint16_t version)
{
    *w = (storage_map_session_t){0};
    if (length == 0 || length > map_region_size()) return STORAGE_ERR_RANGE;
    int active = storage_map_active(st);
    int slot = active == 0 ? 1 : 0;
    int rc = storage_map_erase(st, slot);
    if (rc != STORAGE_OK) return rc;
    *w = (storage_map_session_t){.open = true, .slot = slot, .expected_length = length,
                                 .expected_crc32 = crc32, .version = version};
    return STORAGE_OK;
}

int storage_map_session_write(storage_t *st, storage_map_session_t *w, uint32_t offset, const uint8_t *data,
                              uint32_t len)
{
    if (!w->open) return STORAGE_ERR_STATE;
    if (offset > w->expected_length || len > w->expected_length - offset) return STORAGE_ERR_RANGE;
    w->verified = false;
    int rc = storage_map_write(st, w->slot, offset, data, len);
    if (rc == STORAGE_OK && offset + len > w->bytes_written) w->bytes_written = offset + len;
    return rc;
}

int storage_map_verify(storage_t *st, storage_map_session_t *w)
{
    if (!w->open) return STORAGE_ERR_STATE;
    int rc = check_slot_table(st, w->slot, w->expected_length, w->expected_crc32);
    w->verified = rc == STORAGE_OK;
    return rc;
}

int storage_map_activate(storage_t *st, storage_map_session_t *w)
{
    if (!w->open || !w->verified) return STORAGE_ERR_STATE;
    uint32_t newest = 0;
    for (int s = 0; s < STORAGE_MAP_SLOTS; s++)
        if (st->map[s].seq > newest) newest = st->map[s].seq;
    storage_map_slot_t previous = st->map[w->slot];
    st->map[w->slot] = (storage_map_slot_t){.length = w->expected_length, .crc32 = w->expected_crc32,
                                            .seq = newest + 1, .version = w->version};
    int rc = storage_commit(st);
    if (rc != STORAGE_OK) {
        st->map[w->slot] = previous;
        return rc;
    }
    st->map_valid[w->slot] = true;
    w->open = false;
    w->verified = false;
    return STORAGE_OK;
}

void storage_map_abort(storage_map_session_t *w) { *w = (storage_map_session_t){0}; }
