/* The STM32F405 side of the micro-spectrometer (hal.h spectro_*): see c12880_port.c. */
#ifndef TRIMETER_STM32_C12880_PORT_H
#define TRIMETER_STM32_C12880_PORT_H

#include <stddef.h>
#include <stdint.h>

#include "hal.h"

/* apb2_timer_hz: TIM1's clock (APB2 × 2 when APB2 is divided); the CLK is set from it. */
void spectro_init(uint32_t apb2_timer_hz);
uint32_t spectro_clock_hz(void *ctx);
int spectro_start(void *ctx, const hal_spectro_timing_t *t);
enum hal_spectro_result spectro_read(void *ctx, uint16_t *video, size_t pixels);

#endif
