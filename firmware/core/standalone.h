/* Standalone presses: what the device computes from a press's captures (registers.toml, enums.standalone_*).
 * The press sequence itself (moves, shutters, LEDs, captures, the fit) is app.c's; this module turns the
 * captures into bins, keeps the calibration, builds the fit's input and keeps the result (file
 * standalone_result), so it can be tested without a port.
 *
 * Each set-up is captured at its own integration time (the press's auto-exposure, app.c) with a dark
 * capture at that time right after it. Bins: adjacent pixel pairs (1-2, 3-4, ...), 144 of them, within the
 * fit's capacity; each bin's rate is the pair's mean of (light - dark) in counts/s. A bin is lit when the calibration's diffuse and collimated
 * rates are both at least STANDALONE_LIT_FRACTION of their maxima: an unlit bin gets NaN inputs (the fit
 * flags it unusable) and the no-reference-light capture flag, and does not make a result "flagged".
 *
 * The lamps: each press keeps, per lamp, its lamp-monitor photodiode's reading with the lamp's shutter open
 * (the set-up's light capture, after it) and with every shutter closed (the dark capture, after it); their
 * difference is the lamp's light. A measurement press compares it with the calibration press's: off by more
 * than STANDALONE_LAMP_TOLERANCE (registers.toml, enums.standalone_lamp, says what bias that is) the result
 * is kept but its status is lamp_changed (recalibrate). A calibration photodiode span under
 * STANDALONE_LAMP_MIN_SPAN_COUNTS (no photodiode fitted, or it saw no lamp) leaves that lamp unchecked (NaN).
 *
 * A calibration press checks its references before they become the calibration (registers.toml,
 * enums.standalone_holder and standalone_check, say what and why): enough lit bins, rho_black below the white
 * reference's and the empty holder's bound, and, against a calibration kept since boot, the same rho_black and the
 * same collimated beam per its lamp-monitor light. A refused press keeps the calibration it had, so a sample left
 * in the holder never becomes the reference every later host-less result is measured against. */
#ifndef TRIMETER_STANDALONE_H
#define TRIMETER_STANDALONE_H

#include <stdbool.h>
#include <stdint.h>

#include "c12880.h"
#include "hal.h"
#include "registers_gen.h"

#define STANDALONE_PIXELS_PER_BIN 2u
#define STANDALONE_BINS (C12880_PIXELS / STANDALONE_PIXELS_PER_BIN)
#define STANDALONE_LIT_FRACTION 0.01f
/* A pixel whose frame average is this close to the ADC's full scale saturated in (nearly) every frame. */
#define STANDALONE_SATURATED_COUNTS (C12880_ADC_FULL_SCALE - 16u)
/* trimeter.domain.capture.CaptureFlag */
#define STANDALONE_CAPTURE_SATURATED 1u
#define STANDALONE_CAPTURE_NO_REFERENCE_LIGHT 4u
#define STANDALONE_LAMP_TOLERANCE (TRIMETER_STANDALONE_LAMP_TOLERANCE_PERMILLE / 1000.0f)
/* trimeter.sequences.lamp_monitor.MIN_SPAN_COUNTS: a lamp through its open shutter adds at least this */
#define STANDALONE_LAMP_MIN_SPAN_COUNTS 300.0f

enum standalone_setup { STANDALONE_BLACK, STANDALONE_WHITE, STANDALONE_OPEN, STANDALONE_SETUPS };

typedef struct standalone {
    uint16_t words[STANDALONE_BINS * TRIMETER_STANDALONE_WORD_STRIDE]; /* file standalone_result */
    uint16_t light[STANDALONE_SETUPS][C12880_PIXELS];                  /* this press's captures, counts x 16 */
    uint16_t dark[STANDALONE_SETUPS][C12880_PIXELS];                   /* ... each set-up's dark */
    uint32_t integration_us[STANDALONE_SETUPS];                        /* ... each set-up's integration time */
    uint16_t lamp_lit[HAL_LED_COUNT], lamp_dark[HAL_LED_COUNT];        /* ... each lamp-monitor photodiode, counts */
    float lamp_span[HAL_LED_COUNT];                                    /* calibration: lit - dark, counts */
    float lamp_level[HAL_LED_COUNT]; /* this measurement's lamp light / the calibration's (NaN: not compared) */
    float diffuse[STANDALONE_BINS], collimated[STANDALONE_BINS], rho_black[STANDALONE_BINS]; /* calibration */
    bool lit[STANDALONE_BINS];
    bool saturated[STANDALONE_BINS]; /* this press: some pixel of the bin saturated in some set-up */
    bool calibration_saturated[STANDALONE_BINS];
    bool calibrated;
    float rho_white;
    float thickness_mm;     /* the last measurement's: the active table's */
    uint32_t table_crc32;   /* ... and that table's own CRC-32 */
    uint16_t bins;          /* bins readable in words */
    uint16_t flagged_bins;
    uint16_t sequence;
    trimeter_standalone_status_t status;
    trimeter_standalone_check_t check; /* the last calibration press's check */
    float check_value;                 /* ... what it saw (NaN: no calibration press yet) */
} standalone_t;

void standalone_init(standalone_t *s);

/* This press's bins from the set-ups' captures (light, dark, integration_us > 0): wavelengths (from the
 * unit's polynomial) and rates into the result's words; saturation per bin. */
void standalone_reduce(standalone_t *s, const float wl_coeff[C12880_WL_COEFFS]);

/* A calibration press: the reduced rates become the calibration (diffuse = white / rho_white) when they pass
 * the check (against the kept calibration too when `against_kept`); else the kept one stays. Sets check,
 * check_value and the status (calibrated or calibration_refused); true when calibrated. */
bool standalone_calibrate(standalone_t *s, float rho_white, bool against_kept);

/* A measurement press: the fit's input (file fit_input's layout, fit.h) for every bin, I_b = black /
 * diffuse, I_w = white / diffuse, I_c = open / collimated, rho_b = the calibration's, rho_w = rho_white;
 * NaN for an unlit or saturated bin. Returns the bin count. */
uint16_t standalone_fit_input(standalone_t *s, uint16_t *fit_in);

/* The fit's output (file fit_output's layout) into the result; counts the flagged lit bins, compares the
 * lamps with the calibration's and sets the status done, flagged or lamp_changed (which wins). */
void standalone_take_fit(standalone_t *s, const uint16_t *fit_out, uint16_t n);

/* The status LED's pattern for the status (status_pattern values). */
trimeter_status_pattern_t standalone_pattern(trimeter_standalone_status_t status);

bool standalone_is_file(uint16_t file);
uint8_t standalone_read_records(const standalone_t *s, uint16_t file, uint16_t record, uint16_t n, uint16_t *out);

#endif
