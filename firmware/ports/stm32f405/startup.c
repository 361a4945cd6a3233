/* Reset handler and vector table (Cortex-M4F, STM32F405: 16 system + 82 interrupt vectors).
 *
 * The table in flash only boots the chip: reset_handler copies it to RAM and points VTOR there,
 * because the NVIC fetches a vector from the table on every interrupt, and a fetch from flash
 * stalls while the flash erases or programs (see flash.c). */
#include <stdint.h>

#include "regs.h"

#define VECTORS (16 + 82)

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack, _siramfunc, _sramfunc, _eramfunc;
extern int main(void);
void reset_handler(void);
void default_handler(void);
void SysTick_Handler(void);
void USART1_IRQHandler(void);
void TIM5_IRQHandler(void);
void TIM2_IRQHandler(void);
void EXTI15_10_IRQHandler(void);

static void (*const vector_table[VECTORS])(void);
/* VTOR wants the table aligned to its size rounded up to a power of two: 98 × 4 B → 512 B. */
__attribute__((aligned(512))) static void (*ram_vector_table[VECTORS])(void);

void default_handler(void)
{
    /* An unexpected interrupt or fault: stop here; the watchdog resets the board. */
    for (;;) {
    }
}

void reset_handler(void)
{
    /* The FPU first: -mfloat-abi=hard code may use it from the very first C statement. */
    SCB_CPACR |= 0xFu << 20;
    __asm__ volatile("dsb\n isb");
    uint32_t *src = &_sidata, *dst = &_sdata;
    while (dst < &_edata) *dst++ = *src++;
    for (src = &_siramfunc, dst = &_sramfunc; dst < &_eramfunc;) *dst++ = *src++;
    for (dst = &_sbss; dst < &_ebss;) *dst++ = 0;
    for (unsigned i = 0; i < VECTORS; i++) ram_vector_table[i] = vector_table[i];
    SCB_VTOR = (uint32_t)ram_vector_table;
    __asm__ volatile("dsb\n isb" ::: "memory");
    main();
    for (;;) {
    }
}

/* Ranges fill every slot with the default handler, then the used ones are overridden. */
#pragma GCC diagnostic ignored "-Woverride-init"
__attribute__((section(".isr_vector"), used)) static void (*const vector_table[VECTORS])(void) = {
    [0] = (void (*)(void))(&_estack),
    [1] = reset_handler,
    [2 ... 14] = default_handler,
    [15] = SysTick_Handler,
    [16 ... VECTORS - 1] = default_handler,
    [16 + IRQ_USART1] = USART1_IRQHandler,
    [16 + IRQ_TIM5] = TIM5_IRQHandler,
    [16 + IRQ_TIM2] = TIM2_IRQHandler,
    [16 + IRQ_EXTI15_10] = EXTI15_10_IRQHandler,
};
