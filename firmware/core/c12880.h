/* The micro-spectrometer driver: a Hamamatsu C12880MA (288 pixels, 340-850 nm) read through the HAL's
 * CLK/ST/TRG/EOS frame operations (hal.h: spectro_*), frames averaged here; the register map's spectro_*
 * items (registers.toml).
 *
 * The chip's timing, checked against Hamamatsu's datasheet KACC1226E (electrical characteristics p. 2,
 * timing chart and operation example pp. 7-8): CLK 0.2-5 MHz; ST high at least 6 CLK periods, low at least
 * 375 (so a start-pulse cycle of at least 381); the integration time is ST's high period + 48 CLK periods;
 * counting the first TRG after ST falls as the first, pixel 1 is sampled at the rising edge of the 89th TRG,
 * the 288 pixels one per CLK, and EOS rises after the last pixel. c12880_plan turns an integration time into that timing, or
 * refuses it; the port generates it (a timer for CLK and ST, the ADC + DMA triggered by TRG).
 *
 * A capture: spectro_frames frames, each checked for EOS and for a pixel at the ADC's full scale
 * (saturated: the capture completes flagged), summed and averaged to mean counts x 16 (file records).
 * A dark capture waits until the shutters the app closed have settled. */
#ifndef TRIMETER_C12880_H
#define TRIMETER_C12880_H

#include <stdbool.h>
#include <stdint.h>

#include "hal.h"
#include "registers_gen.h"

#define C12880_PIXELS 288u
#define C12880_CLOCK_HZ_MIN 200000u
#define C12880_CLOCK_HZ_MAX 5000000u
#define C12880_ST_HIGH_MIN_CLOCKS 6u
#define C12880_ST_LOW_MIN_CLOCKS 375u
#define C12880_INTEGRATION_EXTRA_CLOCKS 48u /* integration = ST high + this many CLK periods */
#define C12880_FIRST_VIDEO_CLOCK 89u        /* pixel 1 at the 89th CLK after ST falls */
#define C12880_EOS_CLOCK (C12880_FIRST_VIDEO_CLOCK + C12880_PIXELS)
#define C12880_ADC_FULL_SCALE 4095u         /* 12-bit ADC */
#define C12880_RECORD_SCALE 16u             /* file records: mean counts x 16 */
#define C12880_WL_COEFFS 6                  /* A0, B1..B5 of the test sheet */
#define C12880_WL_MIN_NM 200.0f             /* a polynomial outside this is not a C12880's */
#define C12880_WL_MAX_NM 1200.0f
/* A frame that has not ended this long after its planned end is a chip that never answered. */
#define C12880_FRAME_TIMEOUT_US 100000u

typedef struct c12880 {
    uint16_t light[C12880_PIXELS]; /* file spectro_light */
    uint16_t dark[C12880_PIXELS];  /* file spectro_dark */
    uint32_t sum[C12880_PIXELS];
    uint16_t video[C12880_PIXELS];
    hal_spectro_timing_t timing;
    uint32_t frame_us;             /* planned duration of one frame */
    uint32_t start_us, frame_start_us, capture_us;
    uint16_t frames, frames_done, peak, sequence;
    bool running, dark_capture, frame_started, light_valid, dark_valid, saturated;
    trimeter_spectro_status_t status;
} c12880_t;

void c12880_init(c12880_t *s);

/* The CLK rate is within the chip's range. */
bool c12880_clock_ok(uint32_t clock_hz);

/* The frame timing for integration_us at clock_hz (rounded to whole CLK periods), or false when the chip
 * cannot integrate that long at that clock (or the clock is out of range). */
bool c12880_plan(uint32_t clock_hz, uint32_t integration_us, uint16_t gain, hal_spectro_timing_t *t);

/* How long a planned frame takes, µs (rounded up). */
uint32_t c12880_frame_us(uint32_t clock_hz, const hal_spectro_timing_t *t);

/* The test-sheet polynomial at pixel 1..288, nm. */
float c12880_wavelength_nm(const float coeff[C12880_WL_COEFFS], unsigned pixel);
/* Finite, strictly increasing over pixels 1..288, and within C12880_WL_MIN_NM..C12880_WL_MAX_NM. */
bool c12880_wavelengths_valid(const float coeff[C12880_WL_COEFFS]);

/* spectro_command capture / capture_dark: MB_OK or the Modbus exception (01 no spectrometer, 03 the
 * integration time, 06 a capture runs). A dark capture starts once shutters_settled (c12880_poll). */
uint8_t c12880_start(c12880_t *s, const hal_t *hal, bool dark, uint16_t frames, uint32_t integration_us,
                     uint16_t gain, uint32_t now_us);
void c12880_abort(c12880_t *s);
bool c12880_busy(const c12880_t *s);
void c12880_poll(c12880_t *s, const hal_t *hal, bool shutters_settled, uint32_t now_us);

bool c12880_is_file(uint16_t file);
uint8_t c12880_read_records(const c12880_t *s, uint16_t file, uint16_t record, uint16_t n, uint16_t *out);

#endif
