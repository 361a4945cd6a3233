/* The micro-spectrometer driver; see c12880.h. */
#include "c12880.h"

#include <math.h>
#include <string.h>

#include "modbus.h"

void c12880_init(c12880_t *s)
{
    memset(s, 0, sizeof *s);
    s->status = TRIMETER_SPECTRO_STATUS_IDLE;
}

bool c12880_clock_ok(uint32_t clock_hz) { return clock_hz >= C12880_CLOCK_HZ_MIN && clock_hz <= C12880_CLOCK_HZ_MAX; }

bool c12880_plan(uint32_t clock_hz, uint32_t integration_us, uint16_t gain, hal_spectro_timing_t *t)
{
    if (!c12880_clock_ok(clock_hz)) return false;
    uint64_t clocks = ((uint64_t)integration_us * clock_hz + 500000u) / 1000000u;
    if (clocks < (uint64_t)C12880_ST_HIGH_MIN_CLOCKS + C12880_INTEGRATION_EXTRA_CLOCKS || clocks > UINT32_MAX)
        return false;
    t->st_high_clocks = (uint32_t)clocks - C12880_INTEGRATION_EXTRA_CLOCKS;
    /* ST stays low until EOS has been seen: the whole readout, and never less than the datasheet's minimum */
    t->st_low_clocks = C12880_EOS_CLOCK + 1u > C12880_ST_LOW_MIN_CLOCKS ? C12880_EOS_CLOCK + 1u : C12880_ST_LOW_MIN_CLOCKS;
    t->first_video_clock = C12880_FIRST_VIDEO_CLOCK;
    t->pixels = C12880_PIXELS;
    t->eos_clock = C12880_EOS_CLOCK;
    t->gain = gain;
    return true;
}

uint32_t c12880_frame_us(uint32_t clock_hz, const hal_spectro_timing_t *t)
{
    uint64_t clocks = (uint64_t)t->st_high_clocks + t->st_low_clocks;
    return (uint32_t)((clocks * 1000000u + clock_hz - 1u) / clock_hz);
}

float c12880_wavelength_nm(const float coeff[C12880_WL_COEFFS], unsigned pixel)
{
    float p = (float)pixel, lam = 0.0f;
    for (int i = C12880_WL_COEFFS - 1; i >= 0; i--) lam = lam * p + coeff[i]; /* Horner */
    return lam;
}

bool c12880_wavelengths_valid(const float coeff[C12880_WL_COEFFS])
{
    float previous = -INFINITY;
    for (unsigned p = 1; p <= C12880_PIXELS; p++) {
        float lam = c12880_wavelength_nm(coeff, p);
        if (!isfinite(lam) || !(lam > previous) || lam < C12880_WL_MIN_NM || lam > C12880_WL_MAX_NM) return false;
        previous = lam;
    }
    return true;
}

static uint32_t clock_hz(const hal_t *hal) { return hal->spectro_clock_hz ? hal->spectro_clock_hz(hal->ctx) : 0u; }

uint8_t c12880_start(c12880_t *s, const hal_t *hal, bool dark, uint16_t frames, uint32_t integration_us,
                     uint16_t gain, uint32_t now_us)
{
    uint32_t hz = clock_hz(hal);
    if (hz == 0 || !hal->spectro_start || !hal->spectro_read) {
        s->status = TRIMETER_SPECTRO_STATUS_ERROR_NO_SENSOR;
        return MB_EX_ILLEGAL_FUNCTION;
    }
    if (s->running) return MB_EX_SERVER_DEVICE_BUSY;
    hal_spectro_timing_t t;
    if (frames < 1 || !c12880_plan(hz, integration_us, gain, &t)) return MB_EX_ILLEGAL_DATA_VALUE;
    s->timing = t;
    s->frame_us = c12880_frame_us(hz, &t);
    s->frames = frames;
    s->frames_done = 0;
    s->dark_capture = dark;
    s->saturated = false;
    s->frame_started = false;
    s->running = true;
    s->start_us = now_us;
    memset(s->sum, 0, sizeof s->sum);
    if (dark) s->dark_valid = false;
    else s->light_valid = false;
    s->status = TRIMETER_SPECTRO_STATUS_BUSY;
    return MB_OK;
}

void c12880_abort(c12880_t *s)
{
    if (!s->running) return;
    s->running = false;
    s->status = TRIMETER_SPECTRO_STATUS_ABORTED;
}

bool c12880_busy(const c12880_t *s) { return s->running; }

static void finish(c12880_t *s, uint32_t now_us)
{
    uint16_t *out = s->dark_capture ? s->dark : s->light;
    uint16_t peak = 0;
    for (unsigned p = 0; p < C12880_PIXELS; p++) {
        uint64_t v = ((uint64_t)s->sum[p] * C12880_RECORD_SCALE + s->frames / 2u) / s->frames;
        out[p] = (uint16_t)(v > 0xFFFFu ? 0xFFFFu : v);
        uint16_t counts = (uint16_t)(s->sum[p] / s->frames);
        if (counts > peak) peak = counts;
    }
    s->peak = peak;
    if (s->dark_capture) s->dark_valid = true;
    else s->light_valid = true;
    s->running = false;
    s->capture_us = now_us - s->start_us;
    s->sequence++;
    s->status = s->saturated ? TRIMETER_SPECTRO_STATUS_SATURATED : TRIMETER_SPECTRO_STATUS_DONE;
}

void c12880_poll(c12880_t *s, const hal_t *hal, bool shutters_settled, uint32_t now_us)
{
    if (!s->running) return;
    if (!s->frame_started) {
        if (s->dark_capture && !shutters_settled) return;
        if (hal->spectro_start(hal->ctx, &s->timing) != 0) return; /* the port is still finishing a frame */
        s->frame_started = true;
        s->frame_start_us = now_us;
        return;
    }
    enum hal_spectro_result r = hal->spectro_read(hal->ctx, s->video, C12880_PIXELS);
    if (r == HAL_SPECTRO_PENDING) {
        if (now_us - s->frame_start_us <= s->frame_us + C12880_FRAME_TIMEOUT_US) return;
        r = HAL_SPECTRO_NO_EOS; /* the chip never finished the frame */
    }
    if (r != HAL_SPECTRO_OK) {
        s->running = false;
        s->capture_us = now_us - s->start_us;
        s->status = TRIMETER_SPECTRO_STATUS_ERROR_NO_EOS;
        return;
    }
    for (unsigned p = 0; p < C12880_PIXELS; p++) {
        uint16_t v = s->video[p] > C12880_ADC_FULL_SCALE ? C12880_ADC_FULL_SCALE : s->video[p];
        if (v >= C12880_ADC_FULL_SCALE) s->saturated = true;
        s->sum[p] += v;
    }
    s->frame_started = false;
    if (++s->frames_done >= s->frames) finish(s, now_us);
}

bool c12880_is_file(uint16_t file)
{
    return file == TRIMETER_SPECTRO_FILE_LIGHT || file == TRIMETER_SPECTRO_FILE_DARK;
}

uint8_t c12880_read_records(const c12880_t *s, uint16_t file, uint16_t record, uint16_t n, uint16_t *out)
{
    bool dark = file == TRIMETER_SPECTRO_FILE_DARK;
    if (record >= C12880_PIXELS || n > C12880_PIXELS - record) return MB_EX_ILLEGAL_DATA_ADDRESS;
    if (s->running && s->dark_capture == dark) return MB_EX_SERVER_DEVICE_BUSY;
    if (!(dark ? s->dark_valid : s->light_valid))
        return s->status == TRIMETER_SPECTRO_STATUS_ERROR_NO_EOS ? MB_EX_SERVER_DEVICE_FAILURE : MB_EX_ILLEGAL_FUNCTION;
    memcpy(out, (dark ? s->dark : s->light) + record, n * sizeof *out);
    return MB_OK;
}
