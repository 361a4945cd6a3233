/* Standalone presses: the captures' bins, the calibration, the fit's input and the result; see standalone.h. */
#include "standalone.h"

#include <math.h>
#include <string.h>

#include "modbus.h"
#include "regmap.h"

#define STRIDE TRIMETER_STANDALONE_WORD_STRIDE

void standalone_init(standalone_t *s)
{
    memset(s, 0, sizeof *s);
    for (int l = 0; l < HAL_LED_COUNT; l++) s->lamp_level[l] = NAN;
}

static float lamp_light(const standalone_t *s, int lamp) { return (float)s->lamp_lit[lamp] - (float)s->lamp_dark[lamp]; }

static float word_f32(const standalone_t *s, unsigned bin, unsigned word) { return regmap_get_f32(&s->words[bin * STRIDE + word]); }
static void put_f32(standalone_t *s, unsigned bin, unsigned word, float v) { regmap_put_f32(&s->words[bin * STRIDE + word], v); }

/* A bin's calibration words, no fit yet (NaN results) and its capture flags. */
static void put_bin(standalone_t *s, unsigned b, bool saturated, bool no_reference_light)
{
    put_f32(s, b, TRIMETER_STANDALONE_WORD_DIFFUSE, s->diffuse[b]);
    put_f32(s, b, TRIMETER_STANDALONE_WORD_COLLIMATED, s->collimated[b]);
    put_f32(s, b, TRIMETER_STANDALONE_WORD_RHO_BLACK, s->rho_black[b]);
    for (unsigned w = TRIMETER_STANDALONE_WORD_ALPHA; w <= TRIMETER_STANDALONE_WORD_G; w += 2) put_f32(s, b, w, NAN);
    s->words[b * STRIDE + TRIMETER_STANDALONE_WORD_FIT_FLAGS] = 0;
    s->words[b * STRIDE + TRIMETER_STANDALONE_WORD_CAPTURE_FLAGS] =
        (uint16_t)((saturated ? STANDALONE_CAPTURE_SATURATED : 0u) |
                   (no_reference_light ? STANDALONE_CAPTURE_NO_REFERENCE_LIGHT : 0u));
}

void standalone_reduce(standalone_t *s, const float wl_coeff[C12880_WL_COEFFS])
{
    static const unsigned rate_word[STANDALONE_SETUPS] = {TRIMETER_STANDALONE_WORD_BLACK, TRIMETER_STANDALONE_WORD_WHITE,
                                                          TRIMETER_STANDALONE_WORD_OPEN};
    for (unsigned b = 0; b < STANDALONE_BINS; b++) {
        unsigned p0 = b * STANDALONE_PIXELS_PER_BIN;
        float wl = 0.0f;
        for (unsigned k = 0; k < STANDALONE_PIXELS_PER_BIN; k++) wl += c12880_wavelength_nm(wl_coeff, p0 + k + 1u);
        put_f32(s, b, TRIMETER_STANDALONE_WORD_WAVELENGTH_NM, wl / (float)STANDALONE_PIXELS_PER_BIN);
        s->saturated[b] = false;
        for (unsigned setup = 0; setup < STANDALONE_SETUPS; setup++) {
            /* records are mean counts x 16 */
            float per_record = 1e6f / ((float)C12880_RECORD_SCALE * (float)s->integration_us[setup]);
            float net = 0.0f;
            for (unsigned k = 0; k < STANDALONE_PIXELS_PER_BIN; k++) {
                uint16_t light = s->light[setup][p0 + k];
                if (light >= STANDALONE_SATURATED_COUNTS * C12880_RECORD_SCALE) s->saturated[b] = true;
                net += (float)light - (float)s->dark[setup][p0 + k];
            }
            put_f32(s, b, rate_word[setup], net * per_record / (float)STANDALONE_PIXELS_PER_BIN);
        }
    }
    s->bins = STANDALONE_BINS;
}

void standalone_calibrate(standalone_t *s, float rho_white)
{
    float max_diffuse = 0.0f, max_collimated = 0.0f;
    for (unsigned b = 0; b < STANDALONE_BINS; b++) {
        s->diffuse[b] = word_f32(s, b, TRIMETER_STANDALONE_WORD_WHITE) / rho_white;
        s->collimated[b] = word_f32(s, b, TRIMETER_STANDALONE_WORD_OPEN);
        if (s->diffuse[b] > max_diffuse) max_diffuse = s->diffuse[b];
        if (s->collimated[b] > max_collimated) max_collimated = s->collimated[b];
    }
    for (unsigned b = 0; b < STANDALONE_BINS; b++) {
        s->calibration_saturated[b] = s->saturated[b];
        s->lit[b] = !s->saturated[b] && s->diffuse[b] >= STANDALONE_LIT_FRACTION * max_diffuse && max_diffuse > 0.0f &&
                    s->collimated[b] >= STANDALONE_LIT_FRACTION * max_collimated && max_collimated > 0.0f;
        s->rho_black[b] = s->lit[b] ? word_f32(s, b, TRIMETER_STANDALONE_WORD_BLACK) / s->diffuse[b] : NAN;
        put_bin(s, b, s->saturated[b], !s->lit[b] && !s->saturated[b]);
    }
    for (int l = 0; l < HAL_LED_COUNT; l++) {
        s->lamp_span[l] = lamp_light(s, l);
        s->lamp_level[l] = NAN;
    }
    s->rho_white = rho_white;
    s->calibrated = true;
    s->flagged_bins = 0;
    s->status = TRIMETER_STANDALONE_STATUS_CALIBRATED;
}

uint16_t standalone_fit_input(standalone_t *s, uint16_t *fit_in)
{
    for (unsigned b = 0; b < STANDALONE_BINS; b++) {
        bool usable = s->lit[b] && !s->saturated[b];
        float i_b = word_f32(s, b, TRIMETER_STANDALONE_WORD_BLACK) / s->diffuse[b];
        float i_w = word_f32(s, b, TRIMETER_STANDALONE_WORD_WHITE) / s->diffuse[b];
        float i_c = word_f32(s, b, TRIMETER_STANDALONE_WORD_OPEN) / s->collimated[b];
        uint16_t *in = &fit_in[b * TRIMETER_FIT_INPUT_WORD_STRIDE];
        regmap_put_f32(&in[TRIMETER_FIT_INPUT_WORD_I_B], usable ? i_b : NAN);
        regmap_put_f32(&in[TRIMETER_FIT_INPUT_WORD_I_W], usable ? i_w : NAN);
        regmap_put_f32(&in[TRIMETER_FIT_INPUT_WORD_I_C], usable ? i_c : NAN);
        regmap_put_f32(&in[TRIMETER_FIT_INPUT_WORD_RHO_B], usable ? s->rho_black[b] : NAN);
        regmap_put_f32(&in[TRIMETER_FIT_INPUT_WORD_RHO_W], s->rho_white);
        put_bin(s, b, s->saturated[b] || s->calibration_saturated[b], !s->lit[b] && !s->calibration_saturated[b]);
    }
    return STANDALONE_BINS;
}

void standalone_take_fit(standalone_t *s, const uint16_t *fit_out, uint16_t n)
{
    static const unsigned out_word[3] = {TRIMETER_FIT_OUTPUT_WORD_ALPHA, TRIMETER_FIT_OUTPUT_WORD_SIGMA_T,
                                         TRIMETER_FIT_OUTPUT_WORD_G};
    uint16_t flagged = 0;
    for (unsigned b = 0; b < n && b < STANDALONE_BINS; b++) {
        const uint16_t *o = &fit_out[b * TRIMETER_FIT_OUTPUT_WORD_STRIDE];
        for (unsigned k = 0; k < 3; k++) put_f32(s, b, TRIMETER_STANDALONE_WORD_ALPHA + 2u * k, regmap_get_f32(&o[out_word[k]]));
        uint16_t flags = o[TRIMETER_FIT_OUTPUT_WORD_FLAGS];
        s->words[b * STRIDE + TRIMETER_STANDALONE_WORD_FIT_FLAGS] = flags;
        if (s->calibration_saturated[b] || (s->lit[b] && (flags || s->saturated[b]))) flagged++;
    }
    bool lamp_changed = false;
    for (int l = 0; l < HAL_LED_COUNT; l++) {
        bool seen = s->lamp_span[l] >= STANDALONE_LAMP_MIN_SPAN_COUNTS;
        s->lamp_level[l] = seen ? lamp_light(s, l) / s->lamp_span[l] : NAN;
        if (seen && fabsf(s->lamp_level[l] - 1.0f) > STANDALONE_LAMP_TOLERANCE) lamp_changed = true;
    }
    s->flagged_bins = flagged;
    s->status = lamp_changed ? TRIMETER_STANDALONE_STATUS_LAMP_CHANGED
                : flagged    ? TRIMETER_STANDALONE_STATUS_FLAGGED
                             : TRIMETER_STANDALONE_STATUS_DONE;
}

trimeter_status_pattern_t standalone_pattern(trimeter_standalone_status_t status)
{
    switch (status) {
    case TRIMETER_STANDALONE_STATUS_NONE: return TRIMETER_STATUS_PATTERN_OFF;
    case TRIMETER_STANDALONE_STATUS_BUSY: return TRIMETER_STATUS_PATTERN_SLOW_BLINK;
    case TRIMETER_STANDALONE_STATUS_DONE:
    case TRIMETER_STANDALONE_STATUS_CALIBRATED: return TRIMETER_STATUS_PATTERN_ON;
    case TRIMETER_STANDALONE_STATUS_FLAGGED:
    case TRIMETER_STANDALONE_STATUS_LAMP_CHANGED: return TRIMETER_STATUS_PATTERN_DOUBLE_BLINK;
    default: return TRIMETER_STATUS_PATTERN_FAST_BLINK;
    }
}

bool standalone_is_file(uint16_t file) { return file == TRIMETER_STANDALONE_FILE_RESULT; }

uint8_t standalone_read_records(const standalone_t *s, uint16_t file, uint16_t record, uint16_t n, uint16_t *out)
{
    uint32_t limit = (uint32_t)s->bins * STRIDE;
    if (file != TRIMETER_STANDALONE_FILE_RESULT || n == 0 || record > limit || n > limit - record)
        return MB_EX_ILLEGAL_DATA_ADDRESS;
    if (s->status == TRIMETER_STANDALONE_STATUS_BUSY) return MB_EX_SERVER_DEVICE_BUSY;
    memcpy(out, &s->words[record], n * sizeof *out);
    return MB_OK;
}
