/* What the app's tests share: the fake HAL the app runs on, the main loop run in simulated time, the
 * register reads and writes every test makes, and a map table flashed through the app's Modbus
 * callbacks as `trimeter map flash` does. Tests only. check.h counts per test binary: the helpers that
 * check are inline here, so that each test counts its own. */
#ifndef TRIMETER_APP_FIXTURE_H
#define TRIMETER_APP_FIXTURE_H

#include <stdint.h>

#include "../core/app.h"
#include "../core/regmap.h"
#include "check.h"
#include "fake_hal.h"

/* A new fake HAL for the app, the previous one freed, the main loop once per ms and no per-ms hook; the
 * app is not initialised on it yet (fixture_boot does that). The fixture owns it: fixture_free_hal() at
 * the end of the test. */
fake_hal_t *fixture_fresh_hal(void);
void fixture_free_hal(void);

/* Called before each simulated ms of run_ms, e.g. to put a test's light on the spectrometer; NULL: none. */
void fixture_each_ms(void (*hook)(void));

/* How often run_ms turns the main loop: every `period_us` (a divisor of 1000) of simulated time. */
void fixture_loop_every_us(uint32_t period_us);

/* The app's step-timer ISR in the fake HAL's form, for a test that runs the loop its own way. */
uint32_t fixture_step_isr(void *ctx);

/* Simulated time passes with the main loop running, as on the device: in slices of the loop's period
 * (1 ms unless set), the step timer's ISR at its own instants, then app_poll. */
void run_ms(uint32_t ms);

/* A request through the UART (address .. PDU; the CRC is added), handled after the line's silence:
 * 4 ms, more than t3.5 (2.0 ms at 19200 baud). The reply, if any, is in the HAL's tx buffer. */
void send_frame(const uint8_t *adu, size_t len);

/* The app (re)started on the fixture's HAL as at power-on (app_init), and its first millisecond run. */
void fixture_boot(void);

/* Uploads `table` (`length` bytes, even) into slot A, verifies and activates it; 0 when every step was
 * accepted and the slot reports activated, else the 1-based number of the first step that was not. */
int fixture_activate_table(const uint8_t *table, uint32_t length);

/* One input register, the read checked (0xDEAD when refused). */
static inline uint16_t ir(uint16_t addr)
{
    uint16_t v = 0xDEAD;
    CHECK_EQ_INT(app_read_regs(NULL, MB_TABLE_INPUT_REGISTERS, addr, 1, &v), MB_OK);
    return v;
}

/* Two input registers as one u32 (the register map's word order). */
static inline uint32_t ir32(uint16_t addr)
{
    uint16_t w[2] = {0xDEAD, 0xDEAD};
    CHECK_EQ_INT(app_read_regs(NULL, MB_TABLE_INPUT_REGISTERS, addr, 2, w), MB_OK);
    return regmap_get_u32(w);
}

/* One holding register written as FC 0x06 would; the Modbus exception code, MB_OK when accepted. */
static inline uint8_t write_reg(uint16_t addr, uint16_t v) { return app_write_regs(NULL, addr, 1, &v); }

#endif
