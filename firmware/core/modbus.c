/* Modbus RTU slave; see modbus.h for the contract. */
#include "modbus.h"

#include <string.h>

#include "crc.h"

/* Spec quantity limits (Modbus Application Protocol v1.1b3). */
#define MB_READ_BITS_MAX 2000u
#define MB_READ_REGS_MAX 125u
#define MB_WRITE_BITS_MAX 1968u
#define MB_WRITE_REGS_MAX 123u
#define MB_RW_READ_MAX 125u
#define MB_RW_WRITE_MAX 121u
#define MB_PDU_MAX 253u
#define MB_POLL_READ_BUDGET (2u * MB_ADU_MAX) /* bytes drained per mb_poll: bounded, never spins */

enum {
    FC_READ_COILS = 0x01,
    FC_READ_DISCRETE_INPUTS = 0x02,
    FC_READ_HOLDING_REGISTERS = 0x03,
    FC_READ_INPUT_REGISTERS = 0x04,
    FC_WRITE_SINGLE_COIL = 0x05,
    FC_WRITE_SINGLE_REGISTER = 0x06,
    FC_WRITE_MULTIPLE_COILS = 0x0F,
    FC_WRITE_MULTIPLE_REGISTERS = 0x10,
    FC_READ_FILE_RECORD = 0x14,
    FC_WRITE_FILE_RECORD = 0x15,
    FC_READ_WRITE_MULTIPLE_REGISTERS = 0x17,
    FC_ENCAPSULATED_INTERFACE = 0x2B,
};
#define MEI_READ_DEVICE_ID 0x0Eu

static uint16_t get16(const uint8_t *p) { return (uint16_t)((p[0] << 8) | p[1]); }

static void put16(uint8_t *p, uint16_t v) {
    p[0] = (uint8_t)(v >> 8);
    p[1] = (uint8_t)v;
}

uint32_t mb_t35_us(uint32_t baud) {
    if (baud == 0) baud = 19200u;
    if (baud > 19200u) return 1750u;
    /* 3.5 characters x 11 bits (start + 8 data + parity/stop + stop), rounded up. */
    return (uint32_t)((38500000ull + baud - 1u) / baud);
}

void mb_set_baud(mb_slave_t *s, uint32_t baud) { s->t35_us = mb_t35_us(baud); }

void mb_set_address(mb_slave_t *s, uint8_t address) {
    if (address >= 1u && address <= MB_ADDRESS_MAX) s->address = address;
}

const mb_counters_t *mb_counters(const mb_slave_t *s) { return &s->counters; }

int mb_request_is_broadcast(const mb_slave_t *s) { return s->in_broadcast; }

void mb_init(mb_slave_t *s, uint8_t address, uint32_t baud, const mb_io_t *io, const mb_app_t *app) {
    memset(s, 0, sizeof *s);
    s->io = io;
    s->app = app;
    s->address = 1u;
    mb_set_address(s, address);
    mb_set_baud(s, baud);
    s->last_rx_us = io->now_us(io->ctx);
}

/* ------------------------------------------------------------------------------- dispatching */

/* Each handler gets the request PDU (function code first) and builds the reply PDU in `out`;
 * it returns the reply length, or 0x100 | exception code. */
#define EXC(code) (0x100u | (code))

static unsigned check_range(uint16_t addr, uint16_t qty, uint16_t max) {
    if (qty < 1u || qty > max) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    if ((uint32_t)addr + qty > 0x10000u) return EXC(MB_EX_ILLEGAL_DATA_ADDRESS);
    return 0;
}

static unsigned fc_read_bits(mb_slave_t *s, const uint8_t *pdu, size_t n, uint8_t *out) {
    if (!s->app->read_bits) return EXC(MB_EX_ILLEGAL_FUNCTION);
    if (n != 5) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    uint16_t addr = get16(pdu + 1), qty = get16(pdu + 3);
    unsigned rc = check_range(addr, qty, MB_READ_BITS_MAX);
    if (rc) return rc;
    uint8_t nbytes = (uint8_t)((qty + 7u) / 8u);
    memset(out + 2, 0, nbytes);
    mb_table_t table = pdu[0] == FC_READ_COILS ? MB_TABLE_COILS : MB_TABLE_DISCRETE_INPUTS;
    uint8_t ex = s->app->read_bits(s->app->ctx, table, addr, qty, out + 2);
    if (ex) return EXC(ex);
    if (qty % 8u) out[2 + nbytes - 1] &= (uint8_t)((1u << (qty % 8u)) - 1u); /* pad with zeros */
    out[0] = pdu[0];
    out[1] = nbytes;
    return 2u + nbytes;
}

static unsigned fc_read_regs(mb_slave_t *s, const uint8_t *pdu, size_t n, uint8_t *out) {
    if (!s->app->read_regs) return EXC(MB_EX_ILLEGAL_FUNCTION);
    if (n != 5) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    uint16_t addr = get16(pdu + 1), qty = get16(pdu + 3);
    unsigned rc = check_range(addr, qty, MB_READ_REGS_MAX);
    if (rc) return rc;
    mb_table_t table =
        pdu[0] == FC_READ_HOLDING_REGISTERS ? MB_TABLE_HOLDING_REGISTERS : MB_TABLE_INPUT_REGISTERS;
    memset(s->regs, 0, qty * sizeof s->regs[0]);
    uint8_t ex = s->app->read_regs(s->app->ctx, table, addr, qty, s->regs);
    if (ex) return EXC(ex);
    out[0] = pdu[0];
    out[1] = (uint8_t)(2u * qty);
    for (uint16_t i = 0; i < qty; i++) put16(out + 2 + 2u * i, s->regs[i]);
    return 2u + 2u * qty;
}

static unsigned fc_write_single_coil(mb_slave_t *s, const uint8_t *pdu, size_t n, uint8_t *out) {
    if (!s->app->write_bits) return EXC(MB_EX_ILLEGAL_FUNCTION);
    if (n != 5) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    uint16_t value = get16(pdu + 3);
    if (value != 0x0000u && value != 0xFF00u) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    uint8_t bit = value ? 1u : 0u;
    uint8_t ex = s->app->write_bits(s->app->ctx, get16(pdu + 1), 1, &bit);
    if (ex) return EXC(ex);
    memcpy(out, pdu, 5);
    return 5;
}

static unsigned fc_write_single_reg(mb_slave_t *s, const uint8_t *pdu, size_t n, uint8_t *out) {
    if (!s->app->write_regs) return EXC(MB_EX_ILLEGAL_FUNCTION);
    if (n != 5) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    uint16_t value = get16(pdu + 3);
    uint8_t ex = s->app->write_regs(s->app->ctx, get16(pdu + 1), 1, &value);
    if (ex) return EXC(ex);
    memcpy(out, pdu, 5);
    return 5;
}

static unsigned fc_write_multiple_coils(mb_slave_t *s, const uint8_t *pdu, size_t n, uint8_t *out) {
    if (!s->app->write_bits) return EXC(MB_EX_ILLEGAL_FUNCTION);
    if (n < 6) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    uint16_t addr = get16(pdu + 1), qty = get16(pdu + 3);
    uint8_t nbytes = pdu[5];
    if (qty < 1u || qty > MB_WRITE_BITS_MAX || nbytes != (qty + 7u) / 8u || n != 6u + nbytes)
        return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    unsigned rc = check_range(addr, qty, MB_WRITE_BITS_MAX);
    if (rc) return rc;
    uint8_t ex = s->app->write_bits(s->app->ctx, addr, qty, pdu + 6);
    if (ex) return EXC(ex);
    memcpy(out, pdu, 5);
    return 5;
}

static unsigned fc_write_multiple_regs(mb_slave_t *s, const uint8_t *pdu, size_t n, uint8_t *out) {
    if (!s->app->write_regs) return EXC(MB_EX_ILLEGAL_FUNCTION);
    if (n < 6) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    uint16_t addr = get16(pdu + 1), qty = get16(pdu + 3);
    uint8_t nbytes = pdu[5];
    if (qty < 1u || qty > MB_WRITE_REGS_MAX || nbytes != 2u * qty || n != 6u + nbytes)
        return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    unsigned rc = check_range(addr, qty, MB_WRITE_REGS_MAX);
    if (rc) return rc;
    for (uint16_t i = 0; i < qty; i++) s->regs[i] = get16(pdu + 6 + 2u * i);
    uint8_t ex = s->app->write_regs(s->app->ctx, addr, qty, s->regs);
    if (ex) return EXC(ex);
    memcpy(out, pdu, 5);
    return 5;
}

static unsigned fc_read_write_regs(mb_slave_t *s, const uint8_t *pdu, size_t n, uint8_t *out) {
    if (!s->app->read_regs || !s->app->write_regs) return EXC(MB_EX_ILLEGAL_FUNCTION);
    if (n < 10) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    uint16_t raddr = get16(pdu + 1), rqty = get16(pdu + 3);
    uint16_t waddr = get16(pdu + 5), wqty = get16(pdu + 7);
    uint8_t nbytes = pdu[9];
    if (rqty < 1u || rqty > MB_RW_READ_MAX || wqty < 1u || wqty > MB_RW_WRITE_MAX ||
        nbytes != 2u * wqty || n != 10u + nbytes)
        return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    unsigned rc = check_range(raddr, rqty, MB_RW_READ_MAX);
    if (!rc) rc = check_range(waddr, wqty, MB_RW_WRITE_MAX);
    if (rc) return rc;
    /* The spec performs the write before the read. */
    for (uint16_t i = 0; i < wqty; i++) s->regs[i] = get16(pdu + 10 + 2u * i);
    uint8_t ex = s->app->write_regs(s->app->ctx, waddr, wqty, s->regs);
    if (ex) return EXC(ex);
    memset(s->regs, 0, rqty * sizeof s->regs[0]);
    ex = s->app->read_regs(s->app->ctx, MB_TABLE_HOLDING_REGISTERS, raddr, rqty, s->regs);
    if (ex) return EXC(ex);
    out[0] = pdu[0];
    out[1] = (uint8_t)(2u * rqty);
    for (uint16_t i = 0; i < rqty; i++) put16(out + 2 + 2u * i, s->regs[i]);
    return 2u + 2u * rqty;
}

/* A file sub-request's header: reference type, file 1..65535, records inside 0..9999. */
static unsigned check_file_ref(const uint8_t *sub, uint16_t *file, uint16_t *record, uint16_t *len) {
    *file = get16(sub + 1);
    *record = get16(sub + 3);
    *len = get16(sub + 5);
    if (*len < 1u) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    if (sub[0] != MB_FILE_REFERENCE_TYPE || *file == 0u || *record > MB_FILE_RECORD_MAX ||
        (uint32_t)*record + *len - 1u > MB_FILE_RECORD_MAX)
        return EXC(MB_EX_ILLEGAL_DATA_ADDRESS);
    return 0;
}

static unsigned fc_read_file(mb_slave_t *s, const uint8_t *pdu, size_t n, uint8_t *out) {
    if (!s->app->read_file) return EXC(MB_EX_ILLEGAL_FUNCTION);
    if (n < 2) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    uint8_t nbytes = pdu[1];
    if (nbytes < 0x07u || nbytes > 0xF5u || nbytes % 7u || n != 2u + nbytes)
        return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    /* Validate every sub-request and the reply size before reading anything. */
    size_t reply = 2;
    for (size_t off = 2; off < n; off += 7) {
        uint16_t file, record, len;
        unsigned rc = check_file_ref(pdu + off, &file, &record, &len);
        if (rc) return rc;
        reply += 2u + 2u * (size_t)len;
        if (reply > MB_PDU_MAX) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    }
    size_t pos = 2;
    for (size_t off = 2; off < n; off += 7) {
        uint16_t file, record, len;
        (void)check_file_ref(pdu + off, &file, &record, &len);
        memset(s->regs, 0, len * sizeof s->regs[0]);
        uint8_t ex = s->app->read_file(s->app->ctx, file, record, len, s->regs);
        if (ex) return EXC(ex);
        out[pos] = (uint8_t)(1u + 2u * len);
        out[pos + 1] = MB_FILE_REFERENCE_TYPE;
        for (uint16_t i = 0; i < len; i++) put16(out + pos + 2 + 2u * i, s->regs[i]);
        pos += 2u + 2u * len;
    }
    out[0] = pdu[0];
    out[1] = (uint8_t)(pos - 2);
    return (unsigned)pos;
}

static unsigned fc_write_file(mb_slave_t *s, const uint8_t *pdu, size_t n, uint8_t *out) {
    if (!s->app->write_file) return EXC(MB_EX_ILLEGAL_FUNCTION);
    if (n < 2) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    uint8_t nbytes = pdu[1];
    if (nbytes < 0x09u || nbytes > 0xFBu || n != 2u + nbytes) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    /* Walk the whole request first: a malformed tail must not leave earlier records written. */
    for (size_t off = 2; off < n;) {
        uint16_t file, record, len;
        if (n - off < 7u) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
        unsigned rc = check_file_ref(pdu + off, &file, &record, &len);
        if (rc == EXC(MB_EX_ILLEGAL_DATA_VALUE) || n - off - 7u < 2u * (size_t)len)
            return EXC(MB_EX_ILLEGAL_DATA_VALUE);
        if (rc) return rc;
        off += 7u + 2u * (size_t)len;
    }
    for (size_t off = 2; off < n;) {
        uint16_t file, record, len;
        (void)check_file_ref(pdu + off, &file, &record, &len);
        for (uint16_t i = 0; i < len; i++) s->regs[i] = get16(pdu + off + 7 + 2u * i);
        uint8_t ex = s->app->write_file(s->app->ctx, file, record, len, s->regs);
        if (ex) return EXC(ex);
        off += 7u + 2u * (size_t)len;
    }
    memcpy(out, pdu, n); /* the reply echoes the request */
    return (unsigned)n;
}

/* Device identification objects: 0..2 basic (mandatory), 3..4 regular (if the app gives them). */
static const char *device_id_object(const mb_app_t *app, uint8_t id) {
    switch (id) {
    case 0: return app->vendor;
    case 1: return app->product;
    case 2: return app->revision;
    case 3: return app->vendor_url;
    case 4: return app->product_name;
    default: return NULL;
    }
}

static unsigned fc_device_id(mb_slave_t *s, const uint8_t *pdu, size_t n, uint8_t *out) {
    const mb_app_t *app = s->app;
    if (n < 2 || pdu[1] != MEI_READ_DEVICE_ID) return EXC(MB_EX_ILLEGAL_FUNCTION);
    if (!app->vendor || !app->product || !app->revision) return EXC(MB_EX_ILLEGAL_FUNCTION);
    if (n != 4) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    uint8_t code = pdu[2], object = pdu[3];
    if (code < 1u || code > 4u) return EXC(MB_EX_ILLEGAL_DATA_VALUE);
    uint8_t has_regular = app->vendor_url || app->product_name;
    uint8_t last = 2; /* highest object id of the requested category that the app provides */
    if (code >= 2u && app->vendor_url) last = 3;
    if (code >= 2u && app->product_name) last = 4;
    out[0] = pdu[0];
    out[1] = MEI_READ_DEVICE_ID;
    out[2] = code;
    out[3] = has_regular ? 0x82u : 0x81u; /* conformity: stream + individual access */
    out[4] = 0x00u;                       /* more follows */
    out[5] = 0x00u;                       /* next object id */
    out[6] = 0;                           /* number of objects */
    size_t pos = 7;
    if (code == 4u) {
        const char *value = device_id_object(app, object);
        if (!value) return EXC(MB_EX_ILLEGAL_DATA_ADDRESS);
        size_t len = strlen(value);
        if (len > MB_PDU_MAX - pos - 2u) len = MB_PDU_MAX - pos - 2u;
        out[pos] = object;
        out[pos + 1] = (uint8_t)len;
        memcpy(out + pos + 2, value, len);
        out[6] = 1;
        return (unsigned)(pos + 2u + len);
    }
    /* Stream access: an object id outside the category restarts at 0, as the spec says. */
    if (object > last || !device_id_object(app, object)) object = 0;
    for (uint8_t id = object; id <= last; id++) {
        const char *value = device_id_object(app, id);
        if (!value) continue;
        size_t len = strlen(value);
        if (pos + 2u + len > MB_PDU_MAX) {
            if (out[6] == 0) { /* a single oversize object: truncate rather than never progress */
                len = MB_PDU_MAX - pos - 2u;
            } else {
                out[4] = 0xFFu;
                out[5] = id;
                break;
            }
        }
        out[pos] = id;
        out[pos + 1] = (uint8_t)len;
        memcpy(out + pos + 2, value, len);
        pos += 2u + len;
        out[6]++;
    }
    return (unsigned)pos;
}

static int broadcast_allowed(uint8_t fc) {
    return fc == FC_WRITE_SINGLE_COIL || fc == FC_WRITE_SINGLE_REGISTER ||
           fc == FC_WRITE_MULTIPLE_COILS || fc == FC_WRITE_MULTIPLE_REGISTERS ||
           fc == FC_WRITE_FILE_RECORD;
}

static unsigned dispatch(mb_slave_t *s, const uint8_t *pdu, size_t n, uint8_t *out) {
    switch (pdu[0]) {
    case FC_READ_COILS:
    case FC_READ_DISCRETE_INPUTS: return fc_read_bits(s, pdu, n, out);
    case FC_READ_HOLDING_REGISTERS:
    case FC_READ_INPUT_REGISTERS: return fc_read_regs(s, pdu, n, out);
    case FC_WRITE_SINGLE_COIL: return fc_write_single_coil(s, pdu, n, out);
    case FC_WRITE_SINGLE_REGISTER: return fc_write_single_reg(s, pdu, n, out);
    case FC_WRITE_MULTIPLE_COILS: return fc_write_multiple_coils(s, pdu, n, out);
    case FC_WRITE_MULTIPLE_REGISTERS: return fc_write_multiple_regs(s, pdu, n, out);
    case FC_READ_FILE_RECORD: return fc_read_file(s, pdu, n, out);
    case FC_WRITE_FILE_RECORD: return fc_write_file(s, pdu, n, out);
    case FC_READ_WRITE_MULTIPLE_REGISTERS: return fc_read_write_regs(s, pdu, n, out);
    case FC_ENCAPSULATED_INTERFACE: return fc_device_id(s, pdu, n, out);
    default: return EXC(MB_EX_ILLEGAL_FUNCTION);
    }
}

void mb_handle_adu(mb_slave_t *s, const uint8_t *adu, size_t len) {
    if (len < 4u || len > MB_ADU_MAX || crc16_modbus(adu, len) != 0u) {
        s->counters.crc_errors++;
        return;
    }
    uint8_t address = adu[0];
    if (address != s->address && address != MB_ADDRESS_BROADCAST) {
        s->counters.frames_other++;
        return;
    }
    s->counters.frames_ok++;
    const uint8_t *pdu = adu + 1;
    size_t pdu_len = len - 3u;
    if (address == MB_ADDRESS_BROADCAST) {
        /* Execute writes, never answer (not even with an exception); ignore everything else. */
        if (broadcast_allowed(pdu[0])) {
            s->counters.broadcasts++;
            s->in_broadcast = 1;
            (void)dispatch(s, pdu, pdu_len, s->tx + 1);
            s->in_broadcast = 0;
        }
        return;
    }
    unsigned r = dispatch(s, pdu, pdu_len, s->tx + 1);
    size_t reply_len;
    if (r & 0x100u) {
        s->tx[1] = (uint8_t)(pdu[0] | 0x80u);
        s->tx[2] = (uint8_t)(r & 0xFFu);
        reply_len = 3;
        s->counters.exceptions++;
    } else {
        reply_len = 1u + r;
    }
    s->tx[0] = s->address;
    uint16_t crc = crc16_modbus(s->tx, reply_len);
    s->tx[reply_len] = (uint8_t)crc; /* CRC goes low byte first */
    s->tx[reply_len + 1] = (uint8_t)(crc >> 8);
    s->io->write(s->io->ctx, s->tx, reply_len + 2u);
}

/* --------------------------------------------------------------------------------- framing */

/* Length of the request starting at p if its function code tells it (0 if unknown or too few
 * bytes to tell). Used only to split bytes that did not form one frame. */
static size_t request_length(const uint8_t *p, size_t avail) {
    if (avail < 2) return 0;
    switch (p[1]) {
    case FC_READ_COILS:
    case FC_READ_DISCRETE_INPUTS:
    case FC_READ_HOLDING_REGISTERS:
    case FC_READ_INPUT_REGISTERS:
    case FC_WRITE_SINGLE_COIL:
    case FC_WRITE_SINGLE_REGISTER: return 8;
    case FC_WRITE_MULTIPLE_COILS:
    case FC_WRITE_MULTIPLE_REGISTERS: return avail >= 7 ? 9u + p[6] : 0;
    case FC_READ_WRITE_MULTIPLE_REGISTERS: return avail >= 11 ? 13u + p[10] : 0;
    case FC_READ_FILE_RECORD:
    case FC_WRITE_FILE_RECORD: return avail >= 3 ? 5u + p[2] : 0;
    case FC_ENCAPSULATED_INTERFACE: return 7;
    default: return 0;
    }
}

static void end_of_frame(mb_slave_t *s) {
    const uint8_t *buf = s->rx;
    size_t len = s->rx_len;
    if (s->rx_overrun) {
        s->counters.overruns++;
    } else if (len >= 4u && crc16_modbus(buf, len) == 0u) {
        mb_handle_adu(s, buf, len);
    } else {
        /* Not one frame: back-to-back requests gathered by a slow poll, or noise. Peel off
         * requests whose length and CRC check out; drop whatever is left. */
        size_t off = 0;
        while (len - off >= 4u) {
            size_t flen = request_length(buf + off, len - off);
            if (flen < 4u || flen > len - off || crc16_modbus(buf + off, flen) != 0u) break;
            mb_handle_adu(s, buf + off, flen);
            off += flen;
        }
        if (off < len) {
            s->counters.crc_errors++;
            /* Noise glued in front of a request (an RS-485 driver switching on, a glitch): look
             * for a request that ends exactly at the end of the bytes, for us or broadcast, whose
             * length and CRC agree. O(n^2) in the worst case, but only for frames already bad. */
            for (size_t start = off + 1u; start + 4u <= len; start++) {
                const uint8_t *p = buf + start;
                if (p[0] != s->address && p[0] != MB_ADDRESS_BROADCAST) continue;
                if (request_length(p, len - start) != len - start) continue;
                if (crc16_modbus(p, len - start) != 0u) continue;
                mb_handle_adu(s, p, len - start);
                break;
            }
        }
    }
    s->rx_len = 0;
    s->rx_overrun = 0;
}

void mb_poll(mb_slave_t *s) {
    const mb_io_t *io = s->io;
    uint8_t chunk[64];
    size_t budget = MB_POLL_READ_BUDGET;
    while (budget) {
        size_t want = budget < sizeof chunk ? budget : sizeof chunk;
        size_t got = io->read(io->ctx, chunk, want);
        if (got == 0) break;
        if (got > want) got = want; /* a misbehaving port must not overflow us */
        budget -= got;
        s->last_rx_us = io->now_us(io->ctx);
        size_t room = MB_ADU_MAX - s->rx_len;
        if (got > room) {
            s->rx_overrun = 1;
            got = room;
        }
        memcpy(s->rx + s->rx_len, chunk, got);
        s->rx_len = (uint16_t)(s->rx_len + got);
    }
    if ((s->rx_len || s->rx_overrun) && io->now_us(io->ctx) - s->last_rx_us >= s->t35_us)
        end_of_frame(s);
}
