/* The sim port's C12880MA; see c12880_chip.h. */
#include "c12880_chip.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define SIM_CLOCK_HZ 500000u /* the STM32 port's CLK too: the ADC converts each pixel well inside a period */

/* What a unit's test sheet gives (pixel 1 ≈ 308 nm, 288 ≈ 885 nm, like the datasheet's typical unit); the
 * registers' defaults are the same, so a fresh device knows its chip. */
static const double DEFAULT_COEFF[C12880_WL_COEFFS] = {305.54, 2.7174, -1.1967e-3, -7.7011e-6, 9.2496e-9, 8.1508e-12};

static double weights[C12880_PIXELS][CHIP_GRID_MAX]; /* pixel p's slit × bandwidth on the light grid */
static bool weights_valid;

void chip_init(chip_t *c)
{
    memset(c, 0, sizeof *c);
    c->clock_hz = SIM_CLOCK_HZ;
    memcpy(c->coeff, DEFAULT_COEFF, sizeof c->coeff);
    c->fwhm_nm = 12.0; /* datasheet: 12 typ., 15 max */
    /* The datasheet's typical electrical figures (KACC1226E, p. 2) through the front end: it scales the video
     * output so that the chip's saturation (offset Vo 0.5 V + Vsat 4.3 V) lands just above the 12-bit ADC's
     * full scale, so that a saturated pixel reads 4095 and the driver flags it. */
    const double volts_per_count = (0.5 + 4.3) / 4200.0;
    c->electrons_per_count = volts_per_count / 50e-6;   /* conversion efficiency 50 uV/e- */
    c->dark_counts_per_s = 0.8e-3 / 10e-3 / volts_per_count; /* dark output 0.8 mV at 10 ms */
    c->offset_counts = 0.5 / volts_per_count;            /* output offset Vo */
    c->read_noise_counts = 1.8e-3 / volts_per_count;     /* readout noise 1.8 mV rms */
    c->video_full_scale_counts = 4.3 / volts_per_count;  /* Vsat above the offset */
    c->grid_n = 0;
    c->noise_state = 0xD1B54A32D192ED03ull;
    weights_valid = false;
}

uint32_t chip_clock_hz(const chip_t *c) { return c->clock_hz; }

static double uniform(chip_t *c)
{
    uint64_t x = c->noise_state;
    x ^= x >> 12, x ^= x << 25, x ^= x >> 27;
    c->noise_state = x;
    return ((x * 0x2545F4914F6CDD1Dull >> 11) + 0.5) / 9007199254740992.0;
}

static double gauss(chip_t *c) { return sqrt(-2.0 * log(uniform(c))) * cos(6.283185307179586 * uniform(c)); }

static double poisson(chip_t *c, double mean)
{
    if (mean <= 0) return 0;
    if (mean > 30) return fmax(0.0, round(mean + sqrt(mean) * gauss(c)));
    double l = exp(-mean), prod = uniform(c);
    int k = 0;
    while (prod > l) {
        k++;
        prod *= uniform(c);
    }
    return k;
}

static double wavelength(const chip_t *c, double pixel)
{
    double lam = 0;
    for (int i = C12880_WL_COEFFS - 1; i >= 0; i--) lam = lam * pixel + c->coeff[i];
    return lam;
}

static void build_weights(const chip_t *c)
{
    double sigma = c->fwhm_nm / (2.0 * sqrt(2.0 * log(2.0)));
    for (unsigned p = 0; p < C12880_PIXELS; p++) {
        double lam = wavelength(c, p + 1.0);
        double band = fabs(wavelength(c, p + 1.5) - wavelength(c, p + 0.5));
        for (int g = 0; g < c->grid_n; g++) {
            double x = (c->grid_start_nm + g * c->grid_step_nm - lam) / sigma;
            weights[p][g] = band * c->grid_step_nm * exp(-0.5 * x * x) / (sigma * 2.5066282746310002);
        }
    }
    weights_valid = true;
}

/* The chip does what the datasheet says; another timing gets no EOS from it. */
static bool timing_ok(const chip_t *c, const hal_spectro_timing_t *t)
{
    return c12880_clock_ok(c->clock_hz) && t->st_high_clocks >= C12880_ST_HIGH_MIN_CLOCKS &&
           t->st_low_clocks >= C12880_ST_LOW_MIN_CLOCKS && t->st_low_clocks > C12880_EOS_CLOCK &&
           t->first_video_clock == C12880_FIRST_VIDEO_CLOCK && t->pixels == C12880_PIXELS &&
           t->eos_clock == C12880_EOS_CLOCK;
}

int chip_start(chip_t *c, const plant_t *p, const hal_spectro_timing_t *t, uint64_t now_us)
{
    if (c->running) return -1;
    c->running = true;
    c->eos_ok = !c->eos_broken && timing_ok(c, t);
    c->done_us = now_us + (uint64_t)ceil(((double)t->st_high_clocks + t->st_low_clocks) * 1e6 / c->clock_hz);
    c->frames++;
    double t_int = ((double)t->st_high_clocks + C12880_INTEGRATION_EXTRA_CLOCKS) / c->clock_hz;
    double gain = t->gain ? t->gain : 1;
    /* the light on the chip now, as the twin's optics compose it */
    double lvl[HAL_LED_COUNT];
    for (int l = 0; l < HAL_LED_COUNT; l++)
        lvl[l] = p->led_permille[l] / 1000.0 * p->lamp_emission[l] * plant_shutter_opening(p, (enum hal_shutter)l);
    double diffuse = (lvl[HAL_LED_PANEL_LEFT] + lvl[HAL_LED_PANEL_RIGHT]) / 2.0, beam = lvl[HAL_LED_COLLIMATED];
    int slot = plant_slot(p);
    double w[CHIP_COMPONENTS] = {0};
    if (slot == 1) w[CHIP_DIFFUSE_WHITE] = diffuse;
    else if (slot == 2) w[CHIP_DIFFUSE_OPEN] = diffuse, w[CHIP_BEAM_OPEN] = beam;
    else w[CHIP_DIFFUSE_BLACK] = diffuse;
    if (!weights_valid) build_weights(c);
    double e_per_count = c->electrons_per_count / gain;
    for (unsigned px = 0; px < C12880_PIXELS; px++) {
        double rate = 0; /* counts/s at gain 1 */
        for (int g = 0; g < c->grid_n; g++) {
            double l = 0;
            for (int k = 0; k < CHIP_COMPONENTS; k++) l += w[k] * c->light[k][g];
            rate += weights[px][g] * l;
        }
        double mean_counts = (rate + c->dark_counts_per_s) * t_int * gain;
        double signal = poisson(c, mean_counts * e_per_count) / e_per_count;
        if (signal > c->video_full_scale_counts * gain) signal = c->video_full_scale_counts * gain; /* the chip */
        double v = c->offset_counts + signal + c->read_noise_counts * gauss(c);
        c->video[px] = (uint16_t)lround(v < 0 ? 0 : v > C12880_ADC_FULL_SCALE ? C12880_ADC_FULL_SCALE : v);
    }
    return 0;
}

enum hal_spectro_result chip_read(chip_t *c, uint16_t *video, size_t pixels, uint64_t now_us)
{
    if (!c->running) return HAL_SPECTRO_NO_EOS;
    if (now_us < c->done_us) return HAL_SPECTRO_PENDING;
    c->running = false;
    if (!c->eos_ok || pixels != C12880_PIXELS) return HAL_SPECTRO_NO_EOS;
    memcpy(video, c->video, sizeof c->video);
    return HAL_SPECTRO_OK;
}

/* ---------------------------------------------------------------- the plant socket's spectro commands */

static size_t reply(char *out, size_t cap, const char *error)
{
    int n = error ? snprintf(out, cap, "{\"ok\":false,\"error\":\"%s\"}\n", error) : snprintf(out, cap, "{\"ok\":true}\n");
    return n < 0 ? 0 : (size_t)n < cap ? (size_t)n : cap - 1;
}

/* The number after "key": in line (a flat object); false when absent or not a number. */
static bool number_field(const char *line, const char *key, double *v)
{
    char pattern[40];
    snprintf(pattern, sizeof pattern, "\"%s\":", key);
    const char *at = strstr(line, pattern);
    if (!at) return false;
    char *end;
    *v = strtod(at + strlen(pattern), &end);
    return end != at + strlen(pattern) && isfinite(*v);
}

static const char *const component_names[CHIP_COMPONENTS] = {"diffuse_black", "diffuse_white", "diffuse_open",
                                                             "beam_open"};

static const char *set_light(chip_t *c, const char *line)
{
    int which = -1;
    for (int k = 0; k < CHIP_COMPONENTS; k++) {
        char pattern[48];
        snprintf(pattern, sizeof pattern, "\"component\":\"%s\"", component_names[k]);
        if (strstr(line, pattern)) which = k;
    }
    if (which < 0) return "spectro_light: component must be diffuse_black, diffuse_white, diffuse_open or beam_open";
    double start, step;
    if (!number_field(line, "start_nm", &start) || !number_field(line, "step_nm", &step) || !(step > 0) ||
        start < 100 || start > 2000)
        return "spectro_light: start_nm (100..2000) and step_nm (> 0) numbers";
    const char *at = strstr(line, "\"values\":[");
    if (!at) return "spectro_light: values must be an array of numbers (counts/s per nm at gain 1)";
    static double values[CHIP_GRID_MAX];
    int n = 0;
    const char *s = at + strlen("\"values\":[");
    for (;;) {
        while (*s == ' ') s++;
        if (*s == ']') break;
        if (n == CHIP_GRID_MAX) return "spectro_light: at most 256 values";
        char *end;
        double v = strtod(s, &end);
        if (end == s || !isfinite(v) || v < 0) return "spectro_light: values must be finite numbers >= 0";
        values[n++] = v;
        s = end;
        while (*s == ' ') s++;
        if (*s == ',') s++;
        else if (*s != ']') return "spectro_light: bad values array";
    }
    if (n < 2) return "spectro_light: at least 2 values";
    bool same_grid = c->grid_n == n && c->grid_start_nm == start && c->grid_step_nm == step;
    if (!same_grid) { /* a new grid: the other components no longer line up with it */
        memset(c->light, 0, sizeof c->light);
        c->grid_n = n, c->grid_start_nm = start, c->grid_step_nm = step;
        weights_valid = false;
    }
    memcpy(c->light[which], values, (size_t)n * sizeof *values);
    return NULL;
}

static const char *set_chip(chip_t *c, const char *line)
{
    static const char *const coeff_names[C12880_WL_COEFFS] = {"a0", "b1", "b2", "b3", "b4", "b5"};
    chip_t next = *c;
    double v;
    for (int i = 0; i < C12880_WL_COEFFS; i++)
        if (number_field(line, coeff_names[i], &v)) next.coeff[i] = v;
    if (number_field(line, "fwhm_nm", &v)) {
        if (!(v >= 1 && v <= 50)) return "spectro: fwhm_nm must be within 1..50";
        next.fwhm_nm = v;
    }
    if (number_field(line, "dark_counts_per_s", &v)) {
        if (!(v >= 0 && v <= 1e6)) return "spectro: dark_counts_per_s must be within 0..1e6";
        next.dark_counts_per_s = v;
    }
    if (strstr(line, "\"eos_broken\":true")) next.eos_broken = true;
    if (strstr(line, "\"eos_broken\":false")) next.eos_broken = false;
    for (unsigned p = 1; p <= C12880_PIXELS; p++)
        if (!(wavelength(&next, p) > wavelength(&next, p - 1.0)))
            return "spectro: the wavelength polynomial must increase over pixels 1..288";
    *c = next;
    weights_valid = false;
    return NULL;
}

bool chip_handle_request(chip_t *c, const char *raw, char *out, size_t cap, size_t *len)
{
    /* none of these requests has a space inside a string: compact the line so the matching is exact */
    static char line[4097];
    size_t n = 0;
    for (const char *s = raw; *s && n < sizeof line - 1; s++)
        if (*s != ' ' && *s != '\t') line[n++] = *s;
    line[n] = 0;
    if (strstr(line, "\"cmd\":\"spectro_light\"")) *len = reply(out, cap, set_light(c, line));
    else if (strstr(line, "\"cmd\":\"spectro\"")) *len = reply(out, cap, set_chip(c, line));
    else return false;
    return true;
}
