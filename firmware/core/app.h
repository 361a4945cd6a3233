/* The application: binds the register map (registers_gen.h) to motion, actuators, config and
 * storage, and runs the Modbus slave. One instance (the step ISR needs to find it).
 *
 *   app_init(hal)   boot: load storage + config, outputs off, shutters closed, slave listening
 *   app_poll()      main loop body, never blocks: Modbus, timeouts, settle timers, button, LED
 *   app_step_isr()  the step-timer interrupt: returns the next interval in µs, 0 = stop
 *
 * Command semantics (holding register `command`, written alone or at the end of a block write):
 *   - home / goto_*: return at once; busy (discrete input) until the slider has arrived and
 *     motion_settle_ms passed. A motion command while one runs is accepted and queued: it starts
 *     when the current one ends (one pending command; a newer one replaces it).
 *   - refused (exception 01, "wrong state") when a fault is latched, or goto_* before homing;
 *     save_config while the slider moves (flash erase would stall the step timer) likewise.
 *   - a value write that fails the register map (02/03) or the cross-checks in config.c (03)
 *     changes nothing, including the command in the same write.
 * Map upload (map_command): always answered OK when the value is valid; the outcome is in
 * map_op_status (error_state when not allowed now, error_storage on a flash failure).
 *
 * Safeguards (the bus is shared and flash wears out):
 *   - destructive commands (save_config, load_defaults, map begin_write / activate) run only inside
 *     an unlock window: a write of `unlock` = key, in an earlier request, opens it for
 *     APP_UNLOCK_WINDOW_US and for ONE such command (else exception 01 / map_op_status error_locked).
 *     The same command again in that window with no other write in between (a master's retry after
 *     a lost reply) is acknowledged and not run twice; a failed one closes the window.
 *   - a broadcast write that would unlock, run a destructive command, send any map command or
 *     write map file records changes nothing.
 *   - save_config with nothing changed writes nothing; erases are rate-limited and counted
 *     (storage.h): a refused save answers exception 06, a refused begin_write / activate sets
 *     map_op_status error_busy.
 *   - verify accepts only a map table whose header the firmware accepts (map_table.h): error_table.
 * On-device fit (fit_command, files fit_input / fit_output; fit.h): run is refused with an exception and
 *   fit_status saying why; never by broadcast; while it runs, map begin_write / activate are refused
 *   (error_state), so the table it reads in place cannot be erased under it.
 * Standalone presses (standalone_mode not off; standalone.h): a press of the button runs the whole
 *   measurement on the device (home, black / white / open captures, one dark, the fit into file
 *   standalone_result); it writes fit_input / fit_output as a host's run would. While it runs, motion
 *   commands answer exception 06 and presses are ignored. Setting the mode to calibrate / measure switches
 *   every lamp on; they stay on between presses (shutters closed), and a press first waits until they have
 *   been on for standalone_warmup_s. Each press compares the lamps' photodiodes with the calibration's
 *   (standalone.h): a lamp changed beyond the tolerance ends it lamp_changed. */
#ifndef TRIMETER_APP_H
#define TRIMETER_APP_H

#include <stdbool.h>
#include <stdint.h>

#include "actuators.h"
#include "c12880.h"
#include "config.h"
#include "fit.h"
#include "hal.h"
#include "lamp_monitor.h"
#include "modbus.h"
#include "motion.h"
#include "registers_gen.h"
#include "standalone.h"
#include "storage.h"

#define APP_UNLOCK_WINDOW_US 2000000u /* an unlock allows one destructive command this long */

typedef struct app {
    const hal_t *hal;
    uint16_t hr[REG_HR_SPAN];   /* holding registers, the live values */
    config_t cfg;               /* decoded from hr */
    trimeter_config_source_t config_source; /* input register config_source */
    motion_t motion;
    actuators_t act;
    lamp_monitor_t lamp_monitor;
    storage_t storage;
    storage_map_session_t upload;
    fit_t fit;
    c12880_t spectro;
    standalone_t standalone;
    int press_step;             /* a standalone press's step (app.c), 0 = none runs */
    int press_setup;            /* ... the set-up it captures (enum standalone_setup) */
    int press_tries;            /* ... captures of this set-up so far (auto-exposure) */
    bool press_calibrating;
    uint16_t press_events_seen; /* button_events the press logic has seen */
    uint16_t lamps_lit_s;       /* whole seconds every lamp has been on (saturates): the presses' warm-up */
    uint16_t map_op_status;
    trimeter_fault_t app_fault; /* faults not from motion (storage) */
    int pending_command;        /* TRIMETER_COMMAND_* queued behind a running motion, 0 = none */
    bool unlock_open;           /* an unlock window is open (since unlock_us) */
    bool unlock_spent;          /* ... and ran the destructive write spent_reg = spent_value */
    bool spent_was_last;        /* ... which is the last write the device took (so a repeat is a retry) */
    bool retry_candidate;       /* spent_was_last as the write being handled arrived */
    uint32_t unlock_us;
    uint16_t spent_reg, spent_value;
    bool was_moving;
    uint32_t boot_us;
    uint32_t uptime_s;
    uint32_t uptime_mark_us;
    mb_io_t mb_io;
    mb_app_t mb_app;
    mb_slave_t mb;
} app_t;

void app_init(const hal_t *hal);
void app_poll(void);
uint32_t app_step_isr(void);

/* The one instance, read-only, for ports that report state (the sim's plant) and for tests. */
const app_t *app_get(void);
/* Modbus address for this run (the sim's --address); 0 keeps the configured one. */
void app_override_modbus_address(uint8_t address);

trimeter_state_t app_state(void);
trimeter_fault_t app_fault(void);
bool app_busy(void);

/* The Modbus data callbacks (exposed for the tests; mb_poll calls them). */
uint8_t app_read_bits(void *ctx, mb_table_t table, uint16_t addr, uint16_t n, uint8_t *out_bits);
uint8_t app_write_bits(void *ctx, uint16_t addr, uint16_t n, const uint8_t *bits);
uint8_t app_read_regs(void *ctx, mb_table_t table, uint16_t addr, uint16_t n, uint16_t *out);
uint8_t app_write_regs(void *ctx, uint16_t addr, uint16_t n, const uint16_t *vals);
uint8_t app_read_file(void *ctx, uint16_t file, uint16_t record, uint16_t n, uint16_t *out);
uint8_t app_write_file(void *ctx, uint16_t file, uint16_t record, uint16_t n, const uint16_t *vals);

#endif
