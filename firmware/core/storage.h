/* Persistent state that survives a power cut at any byte.
 *
 * Two kinds of data, one commit mechanism:
 *   - the *system record*: the saved configuration words plus the map-slot table (length, CRC-32,
 *     version, sequence of each committed map). It lives in two copies, one per config region;
 *     a save erases the region NOT holding the newest valid record and writes the new record
 *     there, with a higher sequence number and a trailing CRC-32. At boot the newest record whose
 *     CRC checks wins; a cut anywhere in a save leaves the previous record the newest valid one.
 *   - the map tables: raw bytes in the map regions A/B (a whole 128 KiB sector each, no header, so
 *     a full-size map fits). A map is written into the slot that is not active, checked, and made
 *     active by committing a system record that names it (the commit record). A slot is valid
 *     only if a record names it AND its bytes still have the recorded CRC-32 AND they form a map
 *     table whose header the firmware accepts (map_table.h), so a cut while erasing or writing a
 *     slot can only invalidate that (inactive) slot, and junk never becomes a valid map.
 *
 * Flash wear: every erase goes through one gate that counts it per region (the counts travel in
 * each system record, so they survive reboots; an erase not followed by a commit before a power
 * cut is lost from the count) and rate-limits all erases together: a burst of
 * STORAGE_ERASE_BURST, then one per STORAGE_ERASE_REFILL_US (refused: STORAGE_ERR_BUSY, counted in
 * erase_refusals). The budget refills with time, starting full at boot.
 *
 * The configuration words are the holding registers from STORAGE_CONFIG_FIRST up to the end of
 * the register map; a record written by firmware with a different register-map hash keeps its
 * map table but its configuration is ignored (defaults apply; input register config_source says
 * so, and the host restores a backup by name: `trimeter config import`). */
#ifndef TRIMETER_STORAGE_H
#define TRIMETER_STORAGE_H

#include <stdbool.h>
#include <stdint.h>

#include "hal.h"
#include "registers_gen.h"

#define STORAGE_CONFIG_FIRST REG_HR_STEPS_PER_MM /* first persisted holding register */
#define STORAGE_CONFIG_WORDS (REG_HR_SPAN - STORAGE_CONFIG_FIRST)
#define STORAGE_MAP_SLOTS 2
#define STORAGE_ERASE_BURST 8u                   /* erases allowed back to back */
#define STORAGE_ERASE_REFILL_US (60u * 1000000u) /* then one more per minute */

typedef struct storage_map_slot {
    uint32_t length; /* bytes; 0 = nothing committed */
    uint32_t crc32;
    uint32_t seq;    /* larger = newer commit */
    uint16_t version;
} storage_map_slot_t;

typedef struct storage {
    const hal_t *hal;
    uint32_t seq;          /* of the newest valid system record; 0 = none found */
    int region;            /* config region holding it, -1 = none */
    bool config_valid;     /* the record carried configuration for this register map */
    bool config_other_map; /* it carried configuration, but written for another register map */
    bool config_stored;    /* `config` is exactly what the newest record holds (a save would change nothing) */
    uint16_t config[STORAGE_CONFIG_WORDS];
    storage_map_slot_t map[STORAGE_MAP_SLOTS];
    bool map_valid[STORAGE_MAP_SLOTS];
    uint32_t erase_count[HAL_REGION_COUNT]; /* erases per region, ever (as persisted + since) */
    uint16_t erase_refusals;                /* erases refused by the rate limit since boot, wraps */
    uint32_t erase_budget;                  /* erases allowed now, <= STORAGE_ERASE_BURST */
    uint32_t erase_refill_mark_us;          /* when the budget last gained one (or was full) */
} storage_t;

enum storage_error {
    STORAGE_OK = 0,
    STORAGE_ERR_IO = -1,       /* the HAL refused an erase/write/read */
    STORAGE_ERR_RANGE = -2,    /* offset/length outside the slot or the expected length */
    STORAGE_ERR_STATE = -3,    /* no write open / not verified */
    STORAGE_ERR_MISMATCH = -4, /* verify: the bytes' CRC-32 is not the expected one */
    STORAGE_ERR_BUSY = -5,     /* an erase refused by the rate limit: nothing changed, retry later */
    STORAGE_ERR_FORMAT = -6,   /* verify: the CRC-32 matches but the bytes are no acceptable map table */
};

/* One map upload: begin (erase the inactive slot) → writes → verify → activate (commit). */
typedef struct storage_map_session {
    bool open;
    bool verified;
    int slot;
    uint32_t expected_length;
    uint32_t expected_crc32;
    uint16_t version;
    uint32_t bytes_written; /* highest offset written + 1 */
} storage_map_session_t;

/* Scans both config regions and both map slots. Never fails: with no valid record the storage is
 * empty (config_valid false, no valid map). */
void storage_load(storage_t *st, const hal_t *hal);

/* Refills the erase budget as time passes; call it from the main loop (a gap > 71 min between
 * calls only delays the refill). */
void storage_poll(storage_t *st, uint32_t now_us);

/* Commits `st->config` (marking it valid) and `st->map` as a new system record. On error the
 * previous record stays the valid one (and st->seq/region are unchanged). */
int storage_commit(storage_t *st);

/* The valid slot with the newest commit, or -1. */
int storage_map_active(const storage_t *st);

/* The active map table where it lies (hal storage_map_bytes), with its committed length; NULL when no
 * slot is valid or the port cannot map it. The bytes stay valid until that slot is erased, which needs
 * another activation first (begin_write erases only the inactive slot). */
const uint8_t *storage_map_active_bytes(const storage_t *st, uint32_t *length);

/* Map slot access (raw bytes in the slot's region). */
int storage_map_erase(storage_t *st, int slot);
int storage_map_write(storage_t *st, int slot, uint32_t offset, const uint8_t *data, uint32_t len);
int storage_map_read(const storage_t *st, int slot, uint32_t offset, uint8_t *data, uint32_t len);
/* CRC-32 of the first `length` bytes of the slot; STORAGE_ERR_* on failure. */
int storage_map_crc(const storage_t *st, int slot, uint32_t length, uint32_t *crc_out);

/* Opens an upload into the slot that is not active (A when none is) and erases it. */
int storage_map_begin(storage_t *st, storage_map_session_t *w, uint32_t length, uint32_t crc32, uint16_t version);
/* Bytes at `offset`; refused (RANGE) past the expected length, (STATE) with no upload open. */
int storage_map_session_write(storage_t *st, storage_map_session_t *w, uint32_t offset, const uint8_t *data,
                              uint32_t len);
/* OK when the bytes have the expected CRC-32 (else MISMATCH) and form an acceptable map table
 * (else FORMAT); only then can the upload be activated. */
int storage_map_verify(storage_t *st, storage_map_session_t *w);
/* Commits the verified slot as the newest map; the previous one stays valid as the fallback. */
int storage_map_activate(storage_t *st, storage_map_session_t *w);
void storage_map_abort(storage_map_session_t *w);

#endif
