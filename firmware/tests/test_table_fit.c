/* The inverse core the firmware links (tr_fit_bins, fit_core.h; fit_core/table_fit.c at the root)
 * under the sanitizers, in single precision as on the MCU: a format-2 table is taken, any float input is a
 * flagged bin (NaN outputs where unusable) and never a fault, and a table the core cannot use — a defect
 * anywhere in its header, bytes changed anywhere else, a short or misaligned buffer — is refused or fitted
 * without a fault. How well it fits is the host tests' (tests/inversion/test_table_fit.py, the twin). */
#include <math.h>
#include <string.h>

#include "fit_core.h"
#include "table_fit.h"
#include "check.h"
#include "table_fixture.h"

#define FLAGS_UNUSABLE (TM_FLAG_NONFINITE_INPUT | TM_FLAG_NEGATIVE_INPUT | TM_FLAG_ABOVE_ONE | TM_FLAG_BAD_BACKGROUND)
/* the bits the core may set: FitFlag up to UNDERDETERMINED, never THICKNESS_DISAGREE (several thicknesses)
 * or STD_APPROXIMATE (it returns no stds) */
#define FLAGS_KNOWN 0x6FFu

static _Alignas(8) uint8_t table[8192];
static _Alignas(8) uint8_t copy[sizeof table + 8];
static uint32_t length;

static uint32_t rng_state = 12345u;
static uint32_t next_random(void)
{
    rng_state = rng_state * 1664525u + 1013904223u;
    return rng_state >> 8;
}

/* Every output of n fitted bins is a number or NaN, NaN exactly where the bin is unusable, and only
 * known flag bits are set. */
static void check_outputs(const float *out, const uint16_t *flags, size_t n)
{
    for (size_t i = 0; i < n; i++) {
        CHECK((flags[i] & ~FLAGS_KNOWN) == 0);
        const float *o = &out[i * TR_FIT_OUT_PER_BIN];
        if (flags[i] & FLAGS_UNUSABLE) {
            CHECK(isnan(o[TR_FIT_OUT_ALPHA]) && isnan(o[TR_FIT_OUT_SIGMA_T]) && isnan(o[TR_FIT_OUT_G]));
        } else {
            CHECK(!isinf(o[TR_FIT_OUT_ALPHA]) && !isinf(o[TR_FIT_OUT_G]));
            CHECK(isnan(o[TR_FIT_OUT_ALPHA]) || (o[TR_FIT_OUT_ALPHA] >= 0.0f && o[TR_FIT_OUT_ALPHA] <= 1.0f));
            CHECK(isnan(o[TR_FIT_OUT_G]) || (o[TR_FIT_OUT_G] >= -1.0f && o[TR_FIT_OUT_G] <= 1.0f));
            CHECK(isnan(o[TR_FIT_OUT_SIGMA_T]) || o[TR_FIT_OUT_SIGMA_T] >= 0.0f);
        }
    }
}

static const float ordinary[3][TR_FIT_IN_PER_BIN] = {
    {0.10f, 0.30f, 0.05f, 0.02f, 0.95f}, {0.40f, 0.70f, 0.40f, 0.02f, 0.95f}, {0.02f, 0.05f, 0.001f, 0.02f, 0.95f}};

static void test_a_format_2_table_is_taken_and_ordinary_bins_fitted(void)
{
    length = fixture_table_v2(table, sizeof table, 5);
    CHECK(length > 0);
    CHECK_EQ_INT(tr_fit_bins(table, length, NULL, 0, NULL, NULL), TR_FIT_OK);
    float out[3 * TR_FIT_OUT_PER_BIN];
    uint16_t flags[3];
    CHECK_EQ_INT(tr_fit_bins(table, length, &ordinary[0][0], 3, out, flags), TR_FIT_OK);
    check_outputs(out, flags, 3);
    for (int i = 0; i < 3; i++) CHECK(!(flags[i] & FLAGS_UNUSABLE) && isfinite(out[i * TR_FIT_OUT_PER_BIN]));
}

static void test_any_float_input_is_a_flagged_bin_never_a_fault(void)
{
    length = fixture_table_v2(table, sizeof table, 5);
    const float specials[] = {0.0f, -0.0f, 1.0f, 0.5f, 1e-3f, -1e-4f, -0.5f, 1.0005f, 2.0f, 1e30f, -1e30f, 1e-40f,
                              INFINITY, -INFINITY, NAN};
    const size_t ns = sizeof specials / sizeof specials[0];
    float in[TR_FIT_IN_PER_BIN], out[TR_FIT_OUT_PER_BIN];
    uint16_t flags;
    /* each input alone through every special value, the others ordinary */
    for (int k = 0; k < TR_FIT_IN_PER_BIN; k++)
        for (size_t s = 0; s < ns; s++) {
            memcpy(in, ordinary[1], sizeof in);
            in[k] = specials[s];
            CHECK_EQ_INT(tr_fit_bins(table, length, in, 1, out, &flags), TR_FIT_OK);
            check_outputs(out, &flags, 1);
            if (!isfinite(specials[s])) CHECK(flags & TM_FLAG_NONFINITE_INPUT);
        }
    /* and random mixes of them */
    for (int trial = 0; trial < 3000; trial++) {
        for (int k = 0; k < TR_FIT_IN_PER_BIN; k++) in[k] = specials[next_random() % ns];
        CHECK_EQ_INT(tr_fit_bins(table, length, in, 1, out, &flags), TR_FIT_OK);
        check_outputs(out, &flags, 1);
    }
    const float dark[TR_FIT_IN_PER_BIN] = {0.1f, 0.3f, 0.0f, 0.02f, 0.95f};
    CHECK_EQ_INT(tr_fit_bins(table, length, dark, 1, out, &flags), TR_FIT_OK);
    CHECK(flags & TM_FLAG_IC_BELOW_FLOOR);
    CHECK(isfinite(out[TR_FIT_OUT_SIGMA_T])); /* a lower bound */
}

static void test_bad_arguments_and_buffers_are_refused(void)
{
    length = fixture_table_v2(table, sizeof table, 5);
    float out[TR_FIT_OUT_PER_BIN];
    uint16_t flags;
    CHECK_EQ_INT(tr_fit_bins(NULL, length, NULL, 0, NULL, NULL), TR_FIT_ERR_TABLE);
    CHECK_EQ_INT(tr_fit_bins(table, length, NULL, 1, out, &flags), TR_FIT_ERR_ARGS);
    CHECK_EQ_INT(tr_fit_bins(table, length, ordinary[0], 1, NULL, &flags), TR_FIT_ERR_ARGS);
    CHECK_EQ_INT(tr_fit_bins(table, length, ordinary[0], 1, out, NULL), TR_FIT_ERR_ARGS);
    for (uint32_t len = 0; len < length; len += 37) CHECK_EQ_INT(tr_fit_bins(table, len, NULL, 0, NULL, NULL), TR_FIT_ERR_TABLE);
    CHECK_EQ_INT(tr_fit_bins(table, length + 8, NULL, 0, NULL, NULL), TR_FIT_ERR_TABLE);
    memcpy(copy + 2, table, length); /* the same bytes, not 4-byte aligned: the floats are read in place */
    CHECK_EQ_INT(tr_fit_bins(copy + 2, length, NULL, 0, NULL, NULL), TR_FIT_ERR_TABLE);
    memcpy(copy, table, length);
    CHECK_EQ_INT(tr_fit_bins(copy, length, NULL, 0, NULL, NULL), TR_FIT_OK);
}

/* One damaged copy: refused, or fitted without a fault */
static void fit_damaged(void)
{
    float out[3 * TR_FIT_OUT_PER_BIN];
    uint16_t flags[3];
    int rc = tr_fit_bins(copy, length, &ordinary[0][0], 3, out, flags);
    CHECK(rc == TR_FIT_OK || rc == TR_FIT_ERR_TABLE);
    if (rc == TR_FIT_OK) check_outputs(out, flags, 3);
}

static void test_a_damaged_table_is_refused_or_fitted_never_a_fault(void)
{
    length = fixture_table_v2(table, sizeof table, 5);
    const uint8_t patterns[] = {0x01, 0x80, 0xFF, 0x7F};
    int refused = 0;
    for (uint32_t at = 0; at < 256; at++) /* every header byte */
        for (size_t p = 0; p < sizeof patterns; p++) {
            memcpy(copy, table, length);
            copy[at] ^= patterns[p];
            fit_damaged();
            refused += tr_fit_bins(copy, length, NULL, 0, NULL, NULL) == TR_FIT_ERR_TABLE;
        }
    CHECK(refused > 256); /* most header bytes matter */
    for (int trial = 0; trial < 2000; trial++) { /* random bytes anywhere, a few at a time */
        memcpy(copy, table, length);
        for (int k = 0; k < 4; k++) copy[next_random() % (length - 4)] = (uint8_t)next_random();
        fit_damaged();
    }
    /* floats the reader takes that overflow the arithmetic: A's and B's steps, a frame's m00 (the fixture's
     * sections: axes at 256, 272, 288; scales at 304; spline 352; model_std 640; inscatter 832; frames 848) */
    static const uint32_t huge_at[] = {304 + 4, 304 + 12, 848 + 8};
    for (size_t i = 0; i < sizeof huge_at / sizeof huge_at[0]; i++) {
        memcpy(copy, table, length);
        const float huge = 3e38f;
        memcpy(copy + huge_at[i], &huge, sizeof huge);
        fit_damaged();
    }
}

int main(void)
{
    RUN_TEST(test_a_format_2_table_is_taken_and_ordinary_bins_fitted);
    RUN_TEST(test_any_float_input_is_a_flagged_bin_never_a_fault);
    RUN_TEST(test_bad_arguments_and_buffers_are_refused);
    RUN_TEST(test_a_damaged_table_is_refused_or_fitted_never_a_fault);
    return CHECK_SUMMARY();
}
