/* Register-map rules over the generated descriptor table; see regmap.h. */
#include "regmap.h"

#include <math.h>
#include <string.h>

#include "modbus.h"

static uint16_t table_span(regmap_table_t table) {
    switch (table) {
    case REGMAP_COIL: return REG_COIL_SPAN;
    case REGMAP_DISCRETE_INPUT: return REG_DI_SPAN;
    case REGMAP_INPUT_REGISTER: return REG_IR_SPAN;
    case REGMAP_HOLDING_REGISTER: return REG_HR_SPAN;
    }
    return 0;
}

const regmap_entry_t *regmap_find(regmap_table_t table, uint16_t address) {
    /* ~70 entries: a linear scan is smaller than an index and fast enough per request. */
    for (uint32_t i = 0; i < REGMAP_ENTRY_COUNT; i++) {
        const regmap_entry_t *e = &regmap_entries[i];
        if (e->table == (uint8_t)table && address >= e->address &&
            (uint32_t)address < (uint32_t)e->address + e->words)
            return e;
    }
    return NULL;
}

uint8_t regmap_check_read(regmap_table_t table, uint16_t addr, uint16_t n) {
    return ((uint32_t)addr + n <= table_span(table) && n > 0) ? MB_OK : MB_EX_ILLEGAL_DATA_ADDRESS;
}

uint8_t regmap_check_write_bits(uint16_t addr, uint16_t n) {
    for (uint32_t a = addr; a < (uint32_t)addr + n; a++) {
        const regmap_entry_t *e = a <= 0xFFFFu ? regmap_find(REGMAP_COIL, (uint16_t)a) : NULL;
        if (!e || !e->writable) return MB_EX_ILLEGAL_DATA_ADDRESS;
    }
    return n ? MB_OK : MB_EX_ILLEGAL_DATA_VALUE;
}

uint32_t regmap_get_u32(const uint16_t *words) { return ((uint32_t)words[0] << 16) | words[1]; }

void regmap_put_u32(uint16_t *words, uint32_t v) {
    words[0] = (uint16_t)(v >> 16);
    words[1] = (uint16_t)v;
}

float regmap_get_f32(const uint16_t *words) {
    uint32_t bits = regmap_get_u32(words);
    float f;
    memcpy(&f, &bits, sizeof f);
    return f;
}

void regmap_put_f32(uint16_t *words, float v) {
    uint32_t bits;
    memcpy(&bits, &v, sizeof bits);
    regmap_put_u32(words, bits);
}

static uint8_t check_value(const regmap_entry_t *e, const uint16_t *words) {
    int64_t v;
    switch (e->type) {
    case REGMAP_F32: {
        float f = regmap_get_f32(words);
        return (isfinite(f) && f >= e->min_f && f <= e->max_f) ? MB_OK : MB_EX_ILLEGAL_DATA_VALUE;
    }
    case REGMAP_I16: v = (int16_t)words[0]; break;
    case REGMAP_U32: v = regmap_get_u32(words); break;
    case REGMAP_I32: v = (int32_t)regmap_get_u32(words); break;
    default: v = words[0]; break;
    }
    if (v < e->min || v > e->max) return MB_EX_ILLEGAL_DATA_VALUE;
    if (e->allowed_count) {
        for (uint8_t i = 0; i < e->allowed_count; i++)
            if ((int64_t)e->allowed[i] == v) return MB_OK;
        return MB_EX_ILLEGAL_DATA_VALUE;
    }
    return MB_OK;
}

uint8_t regmap_check_write_regs(uint16_t addr, uint16_t n, const uint16_t *vals) {
    if (n == 0) return MB_EX_ILLEGAL_DATA_VALUE;
    /* Addresses first (02 outranks 03, as in the spec's processing order), then values. */
    for (uint32_t i = 0; i < n;) {
        uint32_t a = addr + i;
        const regmap_entry_t *e = a <= 0xFFFFu ? regmap_find(REGMAP_HOLDING_REGISTER, (uint16_t)a) : NULL;
        if (!e || !e->writable || e->address != a || i + e->words > n) return MB_EX_ILLEGAL_DATA_ADDRESS;
        i += e->words;
    }
    for (uint32_t i = 0; i < n;) {
        const regmap_entry_t *e = regmap_find(REGMAP_HOLDING_REGISTER, (uint16_t)(addr + i));
        uint8_t rc = check_value(e, &vals[i]);
        if (rc != MB_OK) return rc;
        i += e->words;
    }
    return MB_OK;
}

void regmap_fill_defaults(regmap_table_t table, uint16_t *bank, uint16_t span) {
    memset(bank, 0, (size_t)span * sizeof *bank);
    for (uint32_t i = 0; i < REGMAP_ENTRY_COUNT; i++) {
        const regmap_entry_t *e = &regmap_entries[i];
        if (e->table != (uint8_t)table || (uint32_t)e->address + e->words > span) continue;
        switch (e->type) {
        case REGMAP_F32: regmap_put_f32(&bank[e->address], e->def_f); break;
        case REGMAP_U32:
        case REGMAP_I32: regmap_put_u32(&bank[e->address], (uint32_t)e->def); break;
        default: bank[e->address] = (uint16_t)e->def; break;
        }
    }
}
