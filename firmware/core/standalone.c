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
    for (unsigned b = 0; b < STANDALONE_BINS; b++) s->diffuse[b] = s->collimated[b] = s->rho_black[b] = NAN;
    s->check_value = NAN;
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

/* The median of v[0..n), reordering it (insertion sort: n is at most the bin count); NaN when n is 0. */
static float median(float *v, unsigned n)
{
    if (!n) return NAN;
    for (unsigned i = 1; i < n; i++) {
        float x = v[i];
        unsigned j = i;
        for (; j > 0 && v[j - 1] > x; j--) v[j] = v[j - 1];
        v[j] = x;
    }
    return n % 2u ? v[n / 2u] : 0.5f * (v[n / 2u - 1u] + v[n / 2u]);
}

#define HOLDER_BOUND(name) ((float)TRIMETER_STANDALONE_HOLDER_##name##_PERMILLE / 1000.0f)

/* This press's references as a calibration candidate (the reduced rates in the words). */
typedef struct {
    float rho_white, max_diffuse, max_collimated;
} candidate_t;

static float candidate_diffuse(const standalone_t *s, const candidate_t *c, unsigned b)
{
    return word_f32(s, b, TRIMETER_STANDALONE_WORD_WHITE) / c->rho_white;
}

static bool candidate_lit(const standalone_t *s, const candidate_t *c, unsigned b)
{
    return !s->saturated[b] && c->max_diffuse > 0.0f && c->max_collimated > 0.0f &&
           candidate_diffuse(s, c, b) >= STANDALONE_LIT_FRACTION * c->max_diffuse &&
           word_f32(s, b, TRIMETER_STANDALONE_WORD_OPEN) >= STANDALONE_LIT_FRACTION * c->max_collimated;
}

static float candidate_rho_black(const standalone_t *s, const candidate_t *c, unsigned b)
{
    return word_f32(s, b, TRIMETER_STANDALONE_WORD_BLACK) / candidate_diffuse(s, c, b);
}

/* The checks of standalone.h, in the order a person would look: light, slots, holder, then agreement. */
static trimeter_standalone_check_t holder_check(const standalone_t *s, const candidate_t *c, bool against_kept,
                                                float *value)
{
    float v[STANDALONE_BINS];
    unsigned n = 0;
    for (unsigned b = 0; b < STANDALONE_BINS; b++)
        if (candidate_lit(s, c, b)) v[n++] = candidate_rho_black(s, c, b);
    if ((float)n < HOLDER_BOUND(MIN_LIT) * (float)STANDALONE_BINS) {
        *value = (float)n / (float)STANDALONE_BINS;
        return TRIMETER_STANDALONE_CHECK_LITTLE_LIGHT;
    }
    float rho = *value = median(v, n);
    if (!(rho < c->rho_white)) return TRIMETER_STANDALONE_CHECK_SLOTS_SWAPPED;
    if (rho > HOLDER_BOUND(RHO_BLACK_MAX)) return TRIMETER_STANDALONE_CHECK_HOLDER_NOT_EMPTY;
    if (!against_kept || !s->calibrated) return TRIMETER_STANDALONE_CHECK_NONE;

    n = 0;
    for (unsigned b = 0; b < STANDALONE_BINS; b++)
        if (candidate_lit(s, c, b) && s->lit[b]) v[n++] = fabsf(candidate_rho_black(s, c, b) - s->rho_black[b]);
    if (!n) return TRIMETER_STANDALONE_CHECK_NONE; /* no bin lit in both: nothing to compare */
    float change = median(v, n);
    if (change > HOLDER_BOUND(RHO_BLACK_AGREEMENT)) {
        *value = change;
        return TRIMETER_STANDALONE_CHECK_RHO_BLACK_CHANGED;
    }
    n = 0;
    for (unsigned b = 0; b < STANDALONE_BINS; b++)
        if (candidate_lit(s, c, b) && s->lit[b]) v[n++] = word_f32(s, b, TRIMETER_STANDALONE_WORD_OPEN) / s->collimated[b];
    float beam = median(v, n);
    /* per the LED's own light on its photodiode, so an LED that aged or was dimmed is no sample in the beam */
    float now = lamp_light(s, HAL_LED_COLLIMATED), then = s->lamp_span[HAL_LED_COLLIMATED];
    if (now >= STANDALONE_LAMP_MIN_SPAN_COUNTS && then >= STANDALONE_LAMP_MIN_SPAN_COUNTS) beam /= now / then;
    if (!(fabsf(beam - 1.0f) <= HOLDER_BOUND(BEAM_AGREEMENT))) {
        *value = beam;
        return TRIMETER_STANDALONE_CHECK_BEAM_CHANGED;
    }
    return TRIMETER_STANDALONE_CHECK_NONE;
}

bool standalone_calibrate(standalone_t *s, float rho_white, bool against_kept)
{
    candidate_t c = {rho_white, 0.0f, 0.0f};
    for (unsigned b = 0; b < STANDALONE_BINS; b++) {
        float diffuse = candidate_diffuse(s, &c, b), collimated = word_f32(s, b, TRIMETER_STANDALONE_WORD_OPEN);
        if (diffuse > c.max_diffuse) c.max_diffuse = diffuse;
        if (collimated > c.max_collimated) c.max_collimated = collimated;
    }
    s->check = holder_check(s, &c, against_kept, &s->check_value);
    s->flagged_bins = 0;
    if (s->check != TRIMETER_STANDALONE_CHECK_NONE) {
        /* the file shows this press's rates beside the calibration still in force (NaN: none) */
        for (unsigned b = 0; b < STANDALONE_BINS; b++) put_bin(s, b, s->saturated[b], !s->lit[b] && !s->saturated[b]);
        s->status = TRIMETER_STANDALONE_STATUS_CALIBRATION_REFUSED;
        return false;
    }
    for (unsigned b = 0; b < STANDALONE_BINS; b++) {
        s->calibration_saturated[b] = s->saturated[b];
        s->lit[b] = candidate_lit(s, &c, b);
        s->diffuse[b] = candidate_diffuse(s, &c, b);
        s->collimated[b] = word_f32(s, b, TRIMETER_STANDALONE_WORD_OPEN);
        s->rho_black[b] = s->lit[b] ? candidate_rho_black(s, &c, b) : NAN;
        put_bin(s, b, s->saturated[b], !s->lit[b] && !s->saturated[b]);
    }
    for (int l = 0; l < HAL_LED_COUNT; l++) {
        s->lamp_span[l] = lamp_light(s, l);
        s->lamp_level[l] = NAN;
    }
    s->rho_white = rho_white;
    s->calibrated = true;
    s->status = TRIMETER_STANDALONE_STATUS_CALIBRATED;
    return true;
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
    /* as `trimeter serve` asks for an empty holder */
    case TRIMETER_STANDALONE_STATUS_CALIBRATION_REFUSED: return TRIMETER_STATUS_PATTERN_TRIPLE_BLINK;
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
