/* The micro-spectrometer on the STM32F405, register-level, from RM0090 (not run on hardware yet, and QEMU
 * emulates none of TIM1/TIM2 slaving, ADC triggers or DMA: this file is compiled and linked, not tested).
 *
 *   CLK  TIM1_CH1 PWM at SPECTRO_CLOCK_HZ, free-running from init; its update event is TRGO.
 *   ST   TIM2_CH1, TIM2 clocked by TIM1's TRGO (external clock mode 1, ITR0): it counts CLK periods, so the
 *        ST pulse is exactly st_high_clocks long. One-pulse mode, PWM mode 1: high while CNT < CCR1 =
 *        st_high_clocks, then low until the update at ARR + 1 = st_high + st_low clocks stops the timer.
 *   TRG  EXTI line 11 (PB11), ADC2's external regular trigger (rising edge): one conversion of the video
 *        (ADC123_IN13, PC3) per TRG, moved by DMA2 stream 2 channel 1 into `samples`. The trigger is enabled
 *        in TIM2's CC1 interrupt, i.e. as ST falls, so sample k is the video at the (k+1)-th CLK after it;
 *        the pixels are samples first_video_clock-1 .. +pixels-1.
 *   EOS  EXTI line 12 (PB12), rising edge interrupt: records how many samples the DMA had taken, which must be
 *        eos_clock - 1 (EOS rises at that CLK, before its TRG converts) — else the frame has no valid EOS.
 * The frame is complete when TIM2 has stopped (ST low for st_low_clocks) and the DMA took eos_clock samples. */
#include "c12880_port.h"

#include <stdbool.h>
#include <string.h>

#include "c12880.h"
#include "pinout_gen.h"
#include "regs.h"

#define SPECTRO_CLOCK_HZ 500000u /* ADC2 at 21 MHz, 15 + 12 cycles: 1.3 µs per conversion, inside a 2 µs CLK */
#define SAMPLES (C12880_EOS_CLOCK + 2u)

static uint16_t samples[SAMPLES];
static uint32_t clock_hz;
static hal_spectro_timing_t timing;
static volatile bool running, eos_seen;
static volatile uint32_t samples_at_eos;

static uint32_t samples_taken(void) { return SAMPLES - DMA2_S2NDTR; }

void spectro_init(uint32_t apb2_timer_hz)
{
    RCC_APB2ENR |= RCC_APB2ENR_TIM1 | RCC_APB2ENR_ADC2 | RCC_APB2ENR_SYSCFG;
    RCC_APB1ENR |= RCC_APB1ENR_TIM2;
    RCC_AHB1ENR |= RCC_AHB1ENR_DMA2;
    /* CLK: 50 % PWM; on the HSI fallback (16 MHz) the rate is lower but still within the chip's range */
    uint32_t period = apb2_timer_hz / SPECTRO_CLOCK_HZ;
    clock_hz = apb2_timer_hz / period;
    TIM_CR1(TIM1_BASE) = 0;
    TIM_PSC(TIM1_BASE) = 0;
    TIM_ARR(TIM1_BASE) = period - 1u;
    TIM_CCR(TIM1_BASE, 1) = period / 2u;
    TIM_CCMR1(TIM1_BASE) = (TIM_OCMODE_PWM1 << 4) | (1u << 3);
    TIM_CCER(TIM1_BASE) = 1u << 0;
    TIM_CR2(TIM1_BASE) = TIM_CR2_MMS_UPDATE;
    TIM_BDTR(TIM1_BASE) = TIM_BDTR_MOE; /* an advanced timer's outputs need the main output enable */
    TIM_EGR(TIM1_BASE) = TIM_EGR_UG;
    TIM_CR1(TIM1_BASE) = TIM_CR1_ARPE | TIM_CR1_CEN;
    /* ST: TIM2 counts CLK periods; output low until a frame starts */
    TIM_CR1(TIM2_BASE) = TIM_CR1_OPM;
    TIM_SMCR(TIM2_BASE) = TIM_SMCR_ECM1_ITR0;
    TIM_CCMR1(TIM2_BASE) = TIM_OCMODE_PWM1 << 4;
    TIM_CCER(TIM2_BASE) = 1u << 0;
    TIM_CCR(TIM2_BASE, 1) = 0;
    TIM_DIER(TIM2_BASE) = TIM_DIER_CC1IE;
    NVIC_IPR8(IRQ_TIM2) = 0x10;
    NVIC_ISER(IRQ_TIM2 / 32u) = 1u << (IRQ_TIM2 % 32u);
    /* TRG (PB11) and EOS (PB12) on EXTI lines 11 and 12, rising edges; only EOS interrupts */
    SYSCFG_EXTICR(2) = (SYSCFG_EXTICR(2) & ~(0xFu << 12)) | (1u << 12); /* EXTI11 ← port B */
    SYSCFG_EXTICR(3) = (SYSCFG_EXTICR(3) & ~0xFu) | 1u;                 /* EXTI12 ← port B */
    EXTI_RTSR |= (1u << 11) | (1u << 12);
    EXTI_IMR |= 1u << 12;
    NVIC_IPR8(IRQ_EXTI15_10) = 0x10;
    NVIC_ISER(IRQ_EXTI15_10 / 32u) = 1u << (IRQ_EXTI15_10 % 32u);
    /* ADC2: 12 bits, one conversion of the video per trigger, DMA requests kept coming (DDS) */
    ADC2_CR1 = 0;
    ADC2_SQR1 = 0;
    ADC2_SQR3 = PIN_SPECTRO_VIDEO_CHANNEL;
    ADC2_SMPR1 = ADC_SMP_15_CYCLES << (3u * (PIN_SPECTRO_VIDEO_CHANNEL - 10u));
    ADC2_CR2 = ADC_CR2_ADON;
}

uint32_t spectro_clock_hz(void *ctx)
{
    (void)ctx;
    return clock_hz;
}

int spectro_start(void *ctx, const hal_spectro_timing_t *t)
{
    (void)ctx;
    if (running || (TIM_CR1(TIM2_BASE) & TIM_CR1_CEN)) return -1;
    timing = *t;
    eos_seen = false;
    samples_at_eos = 0;
    /* the DMA waits for the ADC; the ADC's trigger is enabled only as ST falls (TIM2's CC1 interrupt) */
    DMA2_S2CR = 0;
    DMA2_LIFCR = DMA2_LIFCR_STREAM2;
    DMA2_S2PAR = ADC2_DR_ADDR;
    DMA2_S2M0AR = (uint32_t)samples;
    DMA2_S2NDTR = SAMPLES;
    DMA2_S2CR = DMA_SXCR_CHSEL(1) | DMA_SXCR_MSIZE_16 | DMA_SXCR_PSIZE_16 | DMA_SXCR_MINC | DMA_SXCR_EN;
    ADC2_CR2 = ADC_CR2_ADON | ADC_CR2_DMA;
    TIM_CNT(TIM2_BASE) = 0;
    TIM_CCR(TIM2_BASE, 1) = t->st_high_clocks;
    TIM_ARR(TIM2_BASE) = t->st_high_clocks + t->st_low_clocks - 1u;
    TIM_SR(TIM2_BASE) = 0;
    running = true;
    TIM_CR1(TIM2_BASE) = TIM_CR1_OPM | TIM_CR1_CEN; /* ST rises at the next CLK */
    return 0;
}

/* ST falls: from the next CLK on, every TRG converts one sample. */
void TIM2_IRQHandler(void)
{
    TIM_SR(TIM2_BASE) = ~TIM_SR_CC1IF;
    if (running) ADC2_CR2 = ADC_CR2_ADON | ADC_CR2_DMA | ADC_CR2_EXTSEL_EXTI11 | ADC_CR2_EXTEN_RISING;
}

void EXTI15_10_IRQHandler(void)
{
    if (EXTI_PR & (1u << 12)) {
        EXTI_PR = 1u << 12;
        if (running && !eos_seen) {
            eos_seen = true;
            samples_at_eos = samples_taken();
        }
    }
}

enum hal_spectro_result spectro_read(void *ctx, uint16_t *video, size_t pixels)
{
    (void)ctx;
    if (!running) return HAL_SPECTRO_NO_EOS;
    if ((TIM_CR1(TIM2_BASE) & TIM_CR1_CEN) || samples_taken() < timing.eos_clock) return HAL_SPECTRO_PENDING;
    ADC2_CR2 = ADC_CR2_ADON; /* trigger off: TRG keeps coming with CLK */
    DMA2_S2CR = 0;
    running = false;
    size_t first = timing.first_video_clock - 1u;
    if (!eos_seen || samples_at_eos != timing.eos_clock - 1u || pixels != timing.pixels || first + pixels > SAMPLES)
        return HAL_SPECTRO_NO_EOS;
    memcpy(video, &samples[first], pixels * sizeof *video);
    return HAL_SPECTRO_OK;
}
