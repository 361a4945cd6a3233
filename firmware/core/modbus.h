/* Modbus RTU slave: framing, CRC, dispatch of function codes to application callbacks.
 *
 * C11, no malloc, no port headers: the port injects byte I/O and a microsecond clock (mb_io_t),
 * the application injects its data model (mb_app_t). mb_poll() never waits: it drains the bytes
 * available now, and once the line has been silent for t3.5 it handles the frame and writes the
 * reply in the same call. Callbacks must return at once (a motion command only sets a target), so a
 * reply is never held while a motor moves.
 *
 * Supported function codes: 01, 02, 03, 04, 05, 06, 0F, 10, 17, 14/15 (file records, reference
 * type 6), 2B/0E (device identification: basic + regular objects, stream and individual access).
 * Anything else: exception 01. Quantities are limited as the spec says (e.g. FC03 1..125) and
 * checked before any callback runs (exception 03); address + quantity past 65536: exception 02.
 * Broadcast (address 0): write codes are executed and never answered; reads are ignored. While a
 * callback runs, mb_request_is_broadcast() tells the app which (it refuses what a broadcast must
 * never do, e.g. destructive commands).
 * Frames for other addresses, bad CRC, overlong (> 256 bytes) and truncated frames are dropped.
 * A request whose function code is >= 0x80 is answered with exception 01 like any unknown code.
 *
 * Not handled here (the port's job): RS-485 direction control and the local echo of a half-duplex
 * transceiver (discard RX while transmitting), TX buffering (io->write must not block), baud
 * changes on the UART itself (call mb_set_baud after reconfiguring it).
 *
 * Timing: a frame ends after 3.5 character times of silence (11 bits per character at 8N1/8E1),
 * the spec's fixed 1750 us above 19200 baud. The t1.5 inter-character rule is not enforced (a
 * slow poll loop cannot see it reliably); instead, if the bytes gathered between two silences do
 * not form one valid frame, the parser splits back-to-back requests by their function code's
 * length and CRC, and recovers a request that noise was glued in front of (one for this address
 * or broadcast, ending with the bytes, length and CRC agreeing); everything else is dropped.
 */
#ifndef TRIMETER_MODBUS_H
#define TRIMETER_MODBUS_H

#include <stddef.h>
#include <stdint.h>

/* Callback results: MB_OK or one of the exception codes. */
#define MB_OK 0u
#define MB_EX_ILLEGAL_FUNCTION 0x01u      /* also: "the server is in the wrong state for this" */
#define MB_EX_ILLEGAL_DATA_ADDRESS 0x02u
#define MB_EX_ILLEGAL_DATA_VALUE 0x03u
#define MB_EX_SERVER_DEVICE_FAILURE 0x04u
#define MB_EX_SERVER_DEVICE_BUSY 0x06u    /* "retry later": e.g. a rate limit */

#define MB_ADDRESS_BROADCAST 0u
#define MB_ADDRESS_MAX 247u
#define MB_ADU_MAX 256u               /* address + PDU (<= 253) + CRC */
#define MB_FILE_RECORD_MAX 9999u      /* record numbers 0..9999 (0x270F) */
#define MB_FILE_REFERENCE_TYPE 6u

/* The four data tables, numbered as the Modbus reference prefix (0xxxx, 1xxxx, 3xxxx, 4xxxx);
 * same numbers as regmap_table_t in registers_gen.h. */
typedef enum {
    MB_TABLE_COILS = 0,
    MB_TABLE_DISCRETE_INPUTS = 1,
    MB_TABLE_INPUT_REGISTERS = 3,
    MB_TABLE_HOLDING_REGISTERS = 4,
} mb_table_t;

/* Platform I/O, provided by the port. */
typedef struct {
    size_t (*read)(void *ctx, uint8_t *buf, size_t max);          /* non-blocking: 0 if none */
    void (*write)(void *ctx, const uint8_t *buf, size_t n);       /* queue a whole reply */
    uint32_t (*now_us)(void *ctx);                                /* free-running, wraps */
    void *ctx;
} mb_io_t;

/* Application data, provided by the app. Every callback returns MB_OK or an exception code and
 * must not block. Addresses are 0-based PDU addresses; (addr, n) is already range-checked against
 * the spec's quantity limits and 65536, not against the app's map. A NULL callback makes its
 * function codes answer exception 01. Bits are packed LSB first as on the wire (bit i of the request
 * is out_bits[i / 8] >> (i % 8)); registers are host-order uint16_t. */
typedef struct {
    uint8_t (*read_bits)(void *ctx, mb_table_t table, uint16_t addr, uint16_t n, uint8_t *out_bits);
    uint8_t (*write_bits)(void *ctx, uint16_t addr, uint16_t n, const uint8_t *bits); /* coils */
    uint8_t (*read_regs)(void *ctx, mb_table_t table, uint16_t addr, uint16_t n, uint16_t *out);
    uint8_t (*write_regs)(void *ctx, uint16_t addr, uint16_t n, const uint16_t *vals); /* holding */
    /* File records (FC 0x14/0x15, reference type 6): file 1..65535, record 0..9999, n records. */
    uint8_t (*read_file)(void *ctx, uint16_t file, uint16_t record, uint16_t n, uint16_t *out);
    uint8_t (*write_file)(void *ctx, uint16_t file, uint16_t record, uint16_t n, const uint16_t *vals);
    /* Device identification (FC 0x2B/0x0E): basic objects must be non-NULL for the FC to work;
     * regular objects (vendor_url, product_name) are optional. */
    const char *vendor;    /* object 0x00 VendorName */
    const char *product;   /* object 0x01 ProductCode */
    const char *revision;  /* object 0x02 MajorMinorRevision */
    const char *vendor_url;    /* object 0x03, optional */
    const char *product_name;  /* object 0x04, optional */
    void *ctx;
} mb_app_t;

/* Counters the app may expose as status registers; they wrap. */
typedef struct {
    uint32_t frames_ok;     /* good CRC, for us or broadcast */
    uint32_t frames_other;  /* good CRC, for another slave address */
    uint32_t crc_errors;    /* dropped: bad CRC, too short, or unsplittable garbage */
    uint32_t overruns;      /* dropped: more than MB_ADU_MAX bytes before a silence */
    uint32_t exceptions;    /* exception replies sent */
    uint32_t broadcasts;    /* broadcast frames executed */
} mb_counters_t;

/* The slave's state: treat as opaque, allocate it statically. */
typedef struct {
    const mb_io_t *io;
    const mb_app_t *app;
    uint8_t address;
    uint32_t t35_us;
    uint32_t last_rx_us;
    uint16_t rx_len;
    uint8_t rx_overrun;
    uint8_t rx[MB_ADU_MAX];
    uint8_t tx[MB_ADU_MAX];
    uint16_t regs[125];     /* scratch for register/record payloads (largest: FC03/04/17 read) */
    uint8_t in_broadcast;   /* the request being dispatched was broadcast */
    mb_counters_t counters;
} mb_slave_t;

/* address: 1..247 (others are clamped to 1); baud: the line's baud rate, for t3.5. */
void mb_init(mb_slave_t *s, uint8_t address, uint32_t baud, const mb_io_t *io, const mb_app_t *app);
/* Drain available bytes; handle and answer a complete frame. Never waits. Call it often
 * (at least every t3.5 / 2 for prompt replies; it is correct at any rate). */
void mb_poll(mb_slave_t *s);
/* Configuration changes take effect from the next frame. An address outside 1..247 is ignored
 * (the old one stays), so a bad config value can never make the device deaf. */
void mb_set_address(mb_slave_t *s, uint8_t address);
void mb_set_baud(mb_slave_t *s, uint32_t baud);
const mb_counters_t *mb_counters(const mb_slave_t *s);
/* True while the app callbacks run for a broadcast request (address 0). */
int mb_request_is_broadcast(const mb_slave_t *s);

/* Handle one complete ADU (address .. CRC) as if it had arrived after a silence; writes the reply
 * (if any) through io->write. Exposed for tests and the fuzzer; mb_poll() calls it. */
void mb_handle_adu(mb_slave_t *s, const uint8_t *adu, size_t len);

/* t3.5 in microseconds for a baud rate (1750 us above 19200 baud). */
uint32_t mb_t35_us(uint32_t baud);

#endif
