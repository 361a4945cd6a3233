/* The sim port's C12880MA: the chip behind the HAL's spectro_* operations (README.md, "The micro-spectrometer").
 *
 * A frame: the timing the core asked for is checked against what the chip does (CLK range, ST high/low
 * minimums, video from the 89th CLK, 288 pixels, EOS after the last) — a timing the chip would not answer
 * with EOS ends without it; it lasts (ST high + ST low) CLK periods of simulated time. The light on the chip
 * is the twin's (spectro_light components, composed here with the plant's slot, shutters and LED levels,
 * as the twin's optics compose them); each pixel reads it through its own wavelength (the unit's polynomial)
 * and the slit function (a Gaussian of fwhm_nm), times its bandwidth, over the integration time (ST high +
 * 48 CLK): shot noise in electrons, dark current, the video offset, read noise, the analog gain, the
 * video's saturation and the 12-bit ADC. */
#ifndef TRIMETER_SIM_C12880_CHIP_H
#define TRIMETER_SIM_C12880_CHIP_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "c12880.h"
#include "hal.h"
#include "plant.h"

#define CHIP_GRID_MAX 256 /* samples of one light component */

enum chip_component { CHIP_DIFFUSE_BLACK, CHIP_DIFFUSE_WHITE, CHIP_DIFFUSE_OPEN, CHIP_BEAM_OPEN, CHIP_COMPONENTS };

typedef struct chip {
    uint32_t clock_hz;
    double coeff[C12880_WL_COEFFS];   /* the unit's true wavelength polynomial (pixel 1..288) */
    double fwhm_nm;                   /* slit function */
    double electrons_per_count;       /* at gain 1 */
    double dark_counts_per_s;         /* at gain 1 */
    double offset_counts;             /* video output at no light */
    double read_noise_counts;
    double video_full_scale_counts;   /* the video output's saturation, before the ADC's 4095 */
    bool eos_broken;                  /* fault: EOS never comes */
    /* light components: counts/s per nm at gain 1 on a uniform grid (the twin's) */
    double grid_start_nm, grid_step_nm;
    int grid_n;
    double light[CHIP_COMPONENTS][CHIP_GRID_MAX];
    /* the frame in progress */
    bool running, eos_ok;
    uint64_t done_us;
    uint16_t video[C12880_PIXELS];
    uint64_t frames;
    uint64_t noise_state;
} chip_t;

void chip_init(chip_t *c);
uint32_t chip_clock_hz(const chip_t *c);
int chip_start(chip_t *c, const plant_t *p, const hal_spectro_timing_t *t, uint64_t now_us);
enum hal_spectro_result chip_read(chip_t *c, uint16_t *video, size_t pixels, uint64_t now_us);

/* A plant-socket request for the chip ("spectro" / "spectro_light"): true when it was one (the reply is in
 * out), false for anything else. */
bool chip_handle_request(chip_t *c, const char *line, char *out, size_t cap, size_t *len);

#endif
