/* The STM32F405 port: clocks, pins (from hardware/pinout.toml), USART1, SysTick time base, the
 * TIM5 step timer, TIM3/TIM4 PWM for servos and LEDs, flash storage, IWDG — and the HAL that hands
 * them to the core. Register level, no vendor library.
 *
 * Clock: HSE 8 MHz → PLL 168 MHz when the crystal starts; every ready-wait has a timeout and falls
 * back to HSI 16 MHz (QEMU reads RCC as 0, so it runs on the fallback). The actual bus clocks are
 * kept in variables and every divider is computed from them.
 *
 * The step timer's ISR, the other ISRs and the HAL hooks the step timer calls are RAMFUNC, and the
 * hal_t they are reached through is in RAM: they keep running while the flash programs (flash.c). */
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "app.h"
#include "c12880_port.h"
#include "flash.h"
#include "pinout_gen.h"
#include "ramfunc.h"
#include "regs.h"
#include "timebase.h"

#define READY_TIMEOUT 200000u /* loop turns: ~10 ms at 16 MHz; generous for HSE and PLL */
#define SERVO_PERIOD_US 20000u
#define UART_BUF 512u         /* ≥ one Modbus ADU (256) each way */

static uint32_t sysclk_hz = 16000000u, apb1_timer_hz = 16000000u, apb2_hz = 16000000u;
static volatile uint32_t ms_ticks;

/* ---------------------------------------------------------------- clocks */

static bool wait_set(volatile uint32_t *reg, uint32_t mask, uint32_t value)
{
    for (uint32_t i = 0; i < READY_TIMEOUT; i++)
        if ((*reg & mask) == value) return true;
    return false;
}

static void clock_init(void)
{
    RCC_CR |= RCC_CR_HSEON;
    if (!wait_set(&RCC_CR, RCC_CR_HSERDY, RCC_CR_HSERDY)) return; /* stay on HSI 16 MHz */
    /* PLL: 8 MHz / M=8 * N=336 / P=2 = 168 MHz, Q=7 (48 MHz USB) */
    RCC_PLLCFGR = 8u | (336u << 6) | (0u << 16) | (1u << 22) | (7u << 24);
    RCC_CR |= RCC_CR_PLLON;
    if (!wait_set(&RCC_CR, RCC_CR_PLLRDY, RCC_CR_PLLRDY)) return;
    FLASH_ACR = FLASH_ACR_PRFTEN | FLASH_ACR_ICEN | FLASH_ACR_DCEN | 5u; /* 5 wait states at 168 MHz, 3.3 V */
    RCC_CFGR = (5u << 10) | (4u << 13) | RCC_CFGR_SW_PLL; /* APB1 /4 = 42 MHz, APB2 /2 = 84 MHz */
    if (!wait_set(&RCC_CFGR, RCC_CFGR_SWS_MASK, RCC_CFGR_SWS_PLL)) {
        RCC_CFGR = 0; /* back to HSI, undivided */
        return;
    }
    sysclk_hz = 168000000u;
    apb1_timer_hz = 84000000u; /* APB1 prescaler ≠ 1: timers run at twice the bus clock */
    apb2_hz = 84000000u;
}

/* ---------------------------------------------------------------- GPIO */

enum { MODE_INPUT = 0, MODE_OUTPUT = 1, MODE_AF = 2, MODE_ANALOG = 3 };

static void pin_mode(uint32_t port, uint32_t pin, uint32_t mode, int af, uint32_t pull)
{
    GPIO_MODER(port) = (GPIO_MODER(port) & ~(3u << (2 * pin))) | (mode << (2 * pin));
    GPIO_PUPDR(port) = (GPIO_PUPDR(port) & ~(3u << (2 * pin))) | (pull << (2 * pin));
    GPIO_OSPEEDR(port) |= 2u << (2 * pin);
    if (af >= 0) {
        uint32_t shift = 4 * (pin % 8);
        GPIO_AFR(port, pin) = (GPIO_AFR(port, pin) & ~(0xFu << shift)) | ((uint32_t)af << shift);
    }
}

/* Always inlined: the RAM hooks use them, and a copy in flash would stall them. */
#define ALWAYS_INLINE inline __attribute__((always_inline))
static ALWAYS_INLINE void pin_write(uint32_t port, uint32_t pin, bool high)
{
    GPIO_BSRR(port) = high ? 1u << pin : 1u << (pin + 16);
}
static ALWAYS_INLINE bool pin_read(uint32_t port, uint32_t pin) { return (GPIO_IDR(port) >> pin) & 1u; }

#define PIN_INIT(name, mode) \
    pin_mode(PIN_##name##_PORT, PIN_##name##_PIN, (mode), PIN_##name##_AF, PIN_##name##_PULL)
#define PIN_SET(name, asserted) pin_write(PIN_##name##_PORT, PIN_##name##_PIN, (asserted) != PIN_##name##_ACTIVE_LOW)
#define PIN_ASSERTED(name) (pin_read(PIN_##name##_PORT, PIN_##name##_PIN) != PIN_##name##_ACTIVE_LOW)

static void gpio_init(void)
{
    RCC_AHB1ENR |= 0x7u; /* GPIOA..C */
    PIN_INIT(MODBUS_TX, MODE_AF);
    PIN_INIT(MODBUS_RX, MODE_AF);
    PIN_SET(STEPPER_STEP, false);
    PIN_SET(STEPPER_ENABLE, false);
    PIN_INIT(STEPPER_STEP, MODE_OUTPUT);
    PIN_INIT(STEPPER_DIR, MODE_OUTPUT);
    PIN_INIT(STEPPER_ENABLE, MODE_OUTPUT);
    PIN_INIT(ENDSTOP, MODE_INPUT);
    PIN_INIT(STEPPER_DIAG, MODE_INPUT);
    PIN_INIT(BUTTON, MODE_INPUT);
    PIN_INIT(STATUS_LED, MODE_OUTPUT);
    PIN_INIT(SERVO_PANEL_LEFT, MODE_AF);
    PIN_INIT(SERVO_PANEL_RIGHT, MODE_AF);
    PIN_INIT(SERVO_COLLIMATED, MODE_AF);
    PIN_INIT(LED_PANEL_LEFT, MODE_AF);
    PIN_INIT(LED_PANEL_RIGHT, MODE_AF);
    PIN_INIT(LED_COLLIMATED, MODE_AF);
    PIN_INIT(MONITOR_PANEL_LEFT, MODE_ANALOG);
    PIN_INIT(MONITOR_PANEL_RIGHT, MODE_ANALOG);
    PIN_INIT(MONITOR_COLLIMATED, MODE_ANALOG);
    PIN_INIT(SPECTRO_CLK, MODE_AF);
    PIN_INIT(SPECTRO_ST, MODE_AF);
    PIN_INIT(SPECTRO_TRG, MODE_INPUT);
    PIN_INIT(SPECTRO_EOS, MODE_INPUT);
    PIN_INIT(SPECTRO_VIDEO, MODE_ANALOG);
}

/* ---------------------------------------------------------------- time base */

RAMFUNC void SysTick_Handler(void) { ms_ticks++; }

static void systick_init(void)
{
    SYST_RVR = sysclk_hz / 1000u - 1u;
    SYST_CVR = 0;
    SCB_SHPR3 = (SCB_SHPR3 & 0x00FFFFFFu) | (0x40u << 24); /* below the step timer */
    SYST_CSR = 7u;                                          /* core clock, interrupt, enable */
}

static uint32_t read_ms_ticks(void) { return ms_ticks; }
static uint32_t read_counter(void) { return SYST_CVR; }
static bool read_wrap_pending(void) { return (SCB_ICSR & SCB_ICSR_PENDSTSET) != 0; }

static uint32_t now_us(void)
{
    static const systick_source_t systick = {read_ms_ticks, read_counter, read_wrap_pending};
    return systick_now_us(&systick, SYST_RVR + 1u);
}

/* ---------------------------------------------------------------- USART1 (interrupt-driven rings) */

static volatile uint8_t rx_buf[UART_BUF], tx_buf[UART_BUF];
static volatile uint32_t rx_head, rx_tail, tx_head, tx_tail;

RAMFUNC void USART1_IRQHandler(void)
{
    uint32_t sr = USART1_SR;
    if (sr & (USART_SR_RXNE | USART_SR_ORE)) {
        uint8_t b = (uint8_t)USART1_DR; /* reading DR also clears ORE */
        uint32_t next = (rx_head + 1u) % UART_BUF;
        if (next != rx_tail) {
            rx_buf[rx_head] = b;
            rx_head = next;
        }
    }
    if ((USART1_CR1 & USART_CR1_TXEIE) && (sr & USART_SR_TXE)) {
        if (tx_tail == tx_head) {
            USART1_CR1 &= ~USART_CR1_TXEIE;
        } else {
            USART1_DR = tx_buf[tx_tail];
            tx_tail = (tx_tail + 1u) % UART_BUF;
        }
    }
}

/* Also push bytes from the main loop: QEMU's USART never raises the TXE interrupt (only RXNE), and
 * on the board this merely refills the data register early. IRQs off so the ISR can't pop too. */
static void uart_tx_pump(void)
{
    __asm__ volatile("cpsid i" ::: "memory");
    while (tx_tail != tx_head && (USART1_SR & USART_SR_TXE)) {
        USART1_DR = tx_buf[tx_tail];
        tx_tail = (tx_tail + 1u) % UART_BUF;
    }
    __asm__ volatile("cpsie i" ::: "memory");
}

static void uart_init(uint32_t baud)
{
    RCC_APB2ENR |= RCC_APB2ENR_USART1;
    USART1_CR1 = 0;
    USART1_BRR = (apb2_hz + baud / 2u) / baud; /* oversampling by 16: BRR = f / baud */
    USART1_CR1 = USART_CR1_UE | USART_CR1_TE | USART_CR1_RE | USART_CR1_RXNEIE;
    NVIC_IPR8(IRQ_USART1) = 0x20;
    NVIC_ISER(IRQ_USART1 / 32u) = 1u << (IRQ_USART1 % 32u);
}

static size_t h_uart_read(void *ctx, uint8_t *buf, size_t max)
{
    (void)ctx;
    size_t n = 0;
    while (n < max && rx_tail != rx_head) {
        buf[n++] = rx_buf[rx_tail];
        rx_tail = (rx_tail + 1u) % UART_BUF;
    }
    return n;
}

static size_t h_uart_write(void *ctx, const uint8_t *buf, size_t len)
{
    (void)ctx;
    size_t n = 0;
    while (n < len) {
        uint32_t next = (tx_head + 1u) % UART_BUF;
        if (next == tx_tail) break;
        tx_buf[tx_head] = buf[n++];
        tx_head = next;
    }
    USART1_CR1 |= USART_CR1_TXEIE;
    return n;
}

/* ---------------------------------------------------------------- step timer (TIM5, 32-bit, 1 MHz) */

RAMFUNC void TIM5_IRQHandler(void)
{
    TIM_SR(TIM5_BASE) = ~TIM_SR_UIF;
    uint32_t next = app_step_isr();
    if (next == 0) {
        TIM_CR1(TIM5_BASE) &= ~TIM_CR1_CEN;
    } else {
        /* The counter restarted at 0 on this update; ARR (not preloaded) applies to this period. */
        TIM_ARR(TIM5_BASE) = (next < 2u ? 2u : next) - 1u;
        /* Already past it (the ISR itself took longer than the interval)? Without this the
         * counter would run on to 2^32 µs: fire the update now instead. */
        if (TIM_CNT(TIM5_BASE) >= TIM_ARR(TIM5_BASE)) TIM_EGR(TIM5_BASE) = TIM_EGR_UG;
    }
}

static void step_timer_init(void)
{
    RCC_APB1ENR |= RCC_APB1ENR_TIM5;
    TIM_CR1(TIM5_BASE) = 0;
    TIM_PSC(TIM5_BASE) = apb1_timer_hz / 1000000u - 1u;
    TIM_EGR(TIM5_BASE) = TIM_EGR_UG; /* load the prescaler */
    TIM_SR(TIM5_BASE) = 0;
    TIM_DIER(TIM5_BASE) = TIM_DIER_UIE;
    NVIC_IPR8(IRQ_TIM5) = 0x00; /* highest: step timing beats everything else */
    NVIC_ISER(IRQ_TIM5 / 32u) = 1u << (IRQ_TIM5 % 32u);
}

static void h_timer_start(void *ctx, uint32_t first_us)
{
    (void)ctx;
    TIM_CR1(TIM5_BASE) &= ~TIM_CR1_CEN;
    TIM_CNT(TIM5_BASE) = 0;
    TIM_ARR(TIM5_BASE) = (first_us < 2u ? 2u : first_us) - 1u;
    TIM_SR(TIM5_BASE) = 0;
    TIM_CR1(TIM5_BASE) |= TIM_CR1_CEN;
}

static void h_timer_stop(void *ctx)
{
    (void)ctx;
    TIM_CR1(TIM5_BASE) &= ~TIM_CR1_CEN;
    TIM_SR(TIM5_BASE) = 0;
}

/* ---------------------------------------------------------------- PWM: TIM3 servos, TIM4 LEDs */

static void pwm_init(uint32_t tim, uint32_t tick_hz, uint32_t period_ticks)
{
    TIM_CR1(tim) = 0;
    TIM_PSC(tim) = apb1_timer_hz / tick_hz - 1u;
    TIM_ARR(tim) = period_ticks - 1u;
    /* channels 1-3: PWM mode 1 with preload, outputs enabled, duty 0 */
    TIM_CCMR1(tim) = (TIM_OCMODE_PWM1 << 4) | (1u << 3) | (TIM_OCMODE_PWM1 << 12) | (1u << 11);
    TIM_CCMR2(tim) = (TIM_OCMODE_PWM1 << 4) | (1u << 3);
    TIM_CCER(tim) = (1u << 0) | (1u << 4) | (1u << 8);
    for (uint32_t ch = 1; ch <= 3; ch++) TIM_CCR(tim, ch) = 0;
    TIM_EGR(tim) = TIM_EGR_UG;
    TIM_CR1(tim) = TIM_CR1_ARPE | TIM_CR1_CEN;
}

static uint32_t led_period_ticks = 1000u;

static void pwm_setup(uint16_t led_pwm_hz)
{
    RCC_APB1ENR |= RCC_APB1ENR_TIM3 | RCC_APB1ENR_TIM4;
    pwm_init(TIM3_BASE, 1000000u, SERVO_PERIOD_US); /* 1 µs ticks, 50 Hz */
    /* LEDs: as many ticks per period as the clock allows, ≤ 1000 (permille resolution). */
    led_period_ticks = apb1_timer_hz / led_pwm_hz;
    if (led_period_ticks > 1000u) led_period_ticks = 1000u;
    pwm_init(TIM4_BASE, led_pwm_hz * led_period_ticks, led_period_ticks);
}

static const uint8_t servo_channel[HAL_SHUTTER_COUNT] = {
    PIN_SERVO_PANEL_LEFT_CHANNEL, PIN_SERVO_PANEL_RIGHT_CHANNEL, PIN_SERVO_COLLIMATED_CHANNEL};
static const uint8_t led_channel[HAL_LED_COUNT] = {PIN_LED_PANEL_LEFT_CHANNEL, PIN_LED_PANEL_RIGHT_CHANNEL,
                                                   PIN_LED_COLLIMATED_CHANNEL};

static void h_servo(void *ctx, enum hal_shutter s, uint16_t pulse_us)
{
    (void)ctx;
    TIM_CCR(TIM3_BASE, servo_channel[s]) = pulse_us; /* 0 = no pulses */
}

static void h_led(void *ctx, enum hal_led l, uint16_t permille)
{
    (void)ctx;
    TIM_CCR(TIM4_BASE, led_channel[l]) = (uint32_t)permille * led_period_ticks / 1000u;
}

/* ---------------------------------------------------------------- lamp monitor (ADC1) */

#define ADC_TIMEOUT 2000u /* loop turns: a conversion takes ~7 µs; never hang on a dead ADC */

static const uint8_t monitor_channel[HAL_LED_COUNT] = {
    PIN_MONITOR_PANEL_LEFT_CHANNEL, PIN_MONITOR_PANEL_RIGHT_CHANNEL, PIN_MONITOR_COLLIMATED_CHANNEL};

static void adc_init(void)
{
    RCC_APB2ENR |= RCC_APB2ENR_ADC1;
    ADC_CCR = ADC_CCR_ADCPRE_DIV4; /* APB2 84 MHz / 4 = 21 MHz, within the 36 MHz limit */
    ADC1_CR1 = 0;                  /* 12 bits, no scan, no interrupts */
    ADC1_SQR1 = 0;                 /* one conversion per start */
    /* 144 cycles (~7 µs) of sampling; the 100 nF at each pin holds the 100 kΩ load's voltage meanwhile */
    for (int l = 0; l < HAL_LED_COUNT; l++)
        ADC1_SMPR2 |= ADC_SMP_144_CYCLES << (3u * monitor_channel[l]);
    ADC1_CR2 = ADC_CR2_ADON;
}

/* One regular conversion of the photodiode's channel; 0 if the ADC does not answer. */
static uint16_t h_lamp(void *ctx, enum hal_led l)
{
    (void)ctx;
    ADC1_SQR3 = monitor_channel[l];
    (void)ADC1_DR; /* clears a stale EOC */
    ADC1_CR2 = ADC_CR2_ADON | ADC_CR2_SWSTART;
    for (uint32_t i = 0; i < ADC_TIMEOUT; i++)
        if (ADC1_SR & ADC_SR_EOC) return (uint16_t)(ADC1_DR & 0xFFFu);
    return 0;
}

/* ---------------------------------------------------------------- the rest of the HAL */

static uint32_t h_now_us(void *ctx)
{
    (void)ctx;
    return now_us();
}

static RAMFUNC void h_enable(void *ctx, bool on) { (void)ctx; PIN_SET(STEPPER_ENABLE, on); }
static RAMFUNC void h_dir(void *ctx, bool positive) { (void)ctx; PIN_SET(STEPPER_DIR, positive); }

static RAMFUNC void h_step(void *ctx)
{
    (void)ctx;
    PIN_SET(STEPPER_STEP, true);
    /* ≥ 2 µs high for the driver at 168 MHz (longer on the HSI fallback); a counted loop because
     * the DWT cycle counter isn't there in QEMU. */
    for (volatile uint32_t i = 0; i < 80u; i++) {
    }
    PIN_SET(STEPPER_STEP, false);
}

static RAMFUNC bool h_endstop(void *ctx) { (void)ctx; return PIN_ASSERTED(ENDSTOP); }
static RAMFUNC bool h_stalled(void *ctx) { (void)ctx; return PIN_ASSERTED(STEPPER_DIAG); }
static bool h_button(void *ctx) { (void)ctx; return PIN_ASSERTED(BUTTON); }
static void h_status(void *ctx, bool on) { (void)ctx; PIN_SET(STATUS_LED, on); }
static void h_kick(void *ctx) { (void)ctx; IWDG_KR = 0xAAAAu; }

static void watchdog_init(void)
{
    IWDG_KR = 0x5555u; /* unlock PR/RLR */
    IWDG_PR = 4u;      /* LSI 32 kHz / 64 = 500 Hz */
    IWDG_RLR = 2000u;  /* 4 s: longer than a 128 KiB sector erase at x32 (1 s typ., 2 s max), during
                        * which the main loop waits in the flash driver and can't kick it */
    IWDG_KR = 0xAAAAu;
    IWDG_KR = 0xCCCCu; /* start; it can't be stopped again */
}

/* Not const: the step timer's ISR reads its hooks from here, and .rodata is in flash. */
static hal_t board_hal = {
    .ctx = NULL,
    .uart_read = h_uart_read,
    .uart_write = h_uart_write,
    .now_us = h_now_us,
    .stepper_enable = h_enable,
    .stepper_dir = h_dir,
    .stepper_step = h_step,
    .endstop_active = h_endstop,
    .stepper_stalled = h_stalled,
    .step_timer_start = h_timer_start,
    .step_timer_stop = h_timer_stop,
    .servo_pulse_us = h_servo,
    .led_level = h_led,
    .status_led = h_status,
    .button_pressed = h_button,
    .lamp_monitor = h_lamp,
    .spectro_clock_hz = spectro_clock_hz,
    .spectro_start = spectro_start,
    .spectro_read = spectro_read,
    .storage_read = flash_region_read,
    .storage_write = flash_region_write,
    .storage_erase = flash_region_erase,
    .storage_map_bytes = flash_region_map_bytes,
    .watchdog_kick = h_kick,
};

int main(void)
{
    clock_init();
    gpio_init();
    systick_init();
    step_timer_init();
    watchdog_init();
    adc_init();
    /* TIM1 runs at APB2 × 2 when APB2 is divided (the PLL set-up), else at APB2 (the HSI fallback) */
    spectro_init(apb2_hz == sysclk_hz ? apb2_hz : 2u * apb2_hz);
    app_init(&board_hal);
    const app_t *app = app_get();
    pwm_setup(app->cfg.led_pwm_hz);
    uart_init(app->cfg.modbus_baud);
    for (;;) {
        app_poll();
        uart_tx_pump();
    }
}
