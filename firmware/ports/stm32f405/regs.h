/* The few STM32F405 registers this port touches (RM0090, PM0214), written out so the build needs
 * no vendor package. Only what is used is declared. */
#ifndef TRIMETER_STM32F405_REGS_H
#define TRIMETER_STM32F405_REGS_H

#include <stdint.h>

#define REG32(addr) (*(volatile uint32_t *)(addr))

/* ---- RCC */
#define RCC_BASE 0x40023800u
#define RCC_CR REG32(RCC_BASE + 0x00)
#define RCC_PLLCFGR REG32(RCC_BASE + 0x04)
#define RCC_CFGR REG32(RCC_BASE + 0x08)
#define RCC_AHB1ENR REG32(RCC_BASE + 0x30)
#define RCC_APB1ENR REG32(RCC_BASE + 0x40)
#define RCC_APB2ENR REG32(RCC_BASE + 0x44)
#define RCC_CSR REG32(RCC_BASE + 0x74)
#define RCC_CR_HSEON (1u << 16)
#define RCC_CR_HSERDY (1u << 17)
#define RCC_CR_PLLON (1u << 24)
#define RCC_CR_PLLRDY (1u << 25)
#define RCC_CFGR_SW_PLL 2u
#define RCC_CFGR_SWS_MASK (3u << 2)
#define RCC_CFGR_SWS_PLL (2u << 2)
#define RCC_APB1ENR_TIM3 (1u << 1)
#define RCC_APB1ENR_TIM4 (1u << 2)
#define RCC_APB1ENR_TIM5 (1u << 3)
#define RCC_APB2ENR_USART1 (1u << 4)
#define RCC_APB2ENR_ADC1 (1u << 8)

/* ---- FLASH interface */
#define FLASH_BASE_R 0x40023C00u
#define FLASH_ACR REG32(FLASH_BASE_R + 0x00)
#define FLASH_KEYR REG32(FLASH_BASE_R + 0x04)
#define FLASH_SR REG32(FLASH_BASE_R + 0x0C)
#define FLASH_CR REG32(FLASH_BASE_R + 0x10)
#define FLASH_ACR_LATENCY_MASK 0xFu
#define FLASH_ACR_PRFTEN (1u << 8)
#define FLASH_ACR_ICEN (1u << 9)
#define FLASH_ACR_DCEN (1u << 10)
#define FLASH_ACR_ICRST (1u << 11)
#define FLASH_ACR_DCRST (1u << 12)
#define FLASH_KEY1 0x45670123u
#define FLASH_KEY2 0xCDEF89ABu
#define FLASH_SR_BSY (1u << 16)
#define FLASH_SR_ERRORS 0xF2u /* OPERR, WRPERR, PGAERR, PGPERR, PGSERR */
#define FLASH_CR_PG (1u << 0)
#define FLASH_CR_SER (1u << 1)
#define FLASH_CR_SNB_SHIFT 3
#define FLASH_CR_SNB_MASK (0xFu << FLASH_CR_SNB_SHIFT)
#define FLASH_CR_PSIZE_MASK (3u << 8)
#define FLASH_CR_PSIZE_X8 (0u << 8)
#define FLASH_CR_PSIZE_X32 (2u << 8)
#define FLASH_CR_STRT (1u << 16)
#define FLASH_CR_LOCK (1u << 31)

/* ---- GPIO */
#define GPIO_BASE(port) (0x40020000u + 0x400u * (port))
#define GPIO_MODER(port) REG32(GPIO_BASE(port) + 0x00)
#define GPIO_OSPEEDR(port) REG32(GPIO_BASE(port) + 0x08)
#define GPIO_PUPDR(port) REG32(GPIO_BASE(port) + 0x0C)
#define GPIO_IDR(port) REG32(GPIO_BASE(port) + 0x10)
#define GPIO_BSRR(port) REG32(GPIO_BASE(port) + 0x18)
#define GPIO_AFR(port, pin) REG32(GPIO_BASE(port) + 0x20 + 4u * ((pin) / 8u))

/* ---- USART1 */
#define USART1_BASE 0x40011000u
#define USART1_SR REG32(USART1_BASE + 0x00)
#define USART1_DR REG32(USART1_BASE + 0x04)
#define USART1_BRR REG32(USART1_BASE + 0x08)
#define USART1_CR1 REG32(USART1_BASE + 0x0C)
#define USART_SR_ORE (1u << 3)
#define USART_SR_RXNE (1u << 5)
#define USART_SR_TXE (1u << 7)
#define USART_CR1_RE (1u << 2)
#define USART_CR1_TE (1u << 3)
#define USART_CR1_RXNEIE (1u << 5)
#define USART_CR1_TXEIE (1u << 7)
#define USART_CR1_UE (1u << 13)

/* ---- general-purpose timers TIM3/4/5 */
#define TIM3_BASE 0x40000400u
#define TIM4_BASE 0x40000800u
#define TIM5_BASE 0x40000C00u
#define TIM_CR1(t) REG32((t) + 0x00)
#define TIM_DIER(t) REG32((t) + 0x0C)
#define TIM_SR(t) REG32((t) + 0x10)
#define TIM_EGR(t) REG32((t) + 0x14)
#define TIM_CCMR1(t) REG32((t) + 0x18)
#define TIM_CCMR2(t) REG32((t) + 0x1C)
#define TIM_CCER(t) REG32((t) + 0x20)
#define TIM_CNT(t) REG32((t) + 0x24)
#define TIM_PSC(t) REG32((t) + 0x28)
#define TIM_ARR(t) REG32((t) + 0x2C)
#define TIM_CCR(t, ch) REG32((t) + 0x34 + 4u * ((ch) - 1u))
#define TIM_CR1_CEN (1u << 0)
#define TIM_CR1_ARPE (1u << 7)
#define TIM_DIER_UIE (1u << 0)
#define TIM_SR_UIF (1u << 0)
#define TIM_EGR_UG (1u << 0)
#define TIM_OCMODE_PWM1 6u

/* ---- ADC1 (regular group, software-started single conversions) */
#define ADC1_BASE 0x40012000u
#define ADC1_SR REG32(ADC1_BASE + 0x00)
#define ADC1_CR1 REG32(ADC1_BASE + 0x04)
#define ADC1_CR2 REG32(ADC1_BASE + 0x08)
#define ADC1_SMPR2 REG32(ADC1_BASE + 0x10)
#define ADC1_SQR1 REG32(ADC1_BASE + 0x2C)
#define ADC1_SQR3 REG32(ADC1_BASE + 0x34)
#define ADC1_DR REG32(ADC1_BASE + 0x4C)
#define ADC_CCR REG32(0x40012300u + 0x04)
#define ADC_SR_EOC (1u << 1)
#define ADC_CR2_ADON (1u << 0)
#define ADC_CR2_SWSTART (1u << 30)
#define ADC_CCR_ADCPRE_DIV4 (1u << 16)
#define ADC_SMP_144_CYCLES 6u

/* ---- IWDG */
#define IWDG_BASE 0x40003000u
#define IWDG_KR REG32(IWDG_BASE + 0x00)
#define IWDG_PR REG32(IWDG_BASE + 0x04)
#define IWDG_RLR REG32(IWDG_BASE + 0x08)

/* ---- Cortex-M4 core */
#define SYST_CSR REG32(0xE000E010u)
#define SYST_RVR REG32(0xE000E014u)
#define SYST_CVR REG32(0xE000E018u)
#define SYST_CSR_COUNTFLAG (1u << 16)
#define NVIC_ISER(n) REG32(0xE000E100u + 4u * (n))
#define NVIC_IPR8(irq) (*(volatile uint8_t *)(0xE000E400u + (irq)))
#define SCB_SHPR3 REG32(0xE000ED20u)
#define SCB_CPACR REG32(0xE000ED88u)
#define SCB_AIRCR REG32(0xE000ED0Cu)
#define SCB_ICSR REG32(0xE000ED04u)
#define SCB_ICSR_PENDSTSET (1u << 26)
#define SCB_VTOR REG32(0xE000ED08u)

#define IRQ_USART1 37u
#define IRQ_TIM5 50u

/* ---- the micro-spectrometer (c12880_port.c): TIM1 CLK, TIM2 ST counted in CLK periods, ADC2 + DMA2 on TRG
 * (EXTI line 11), EXTI line 12 for EOS. RM0090 sections 17-18 (TIM1/TIM2), 13 (ADC), 10 (DMA), 12 (EXTI). */
#define TIM1_BASE 0x40010000u
#define TIM2_BASE 0x40000000u
#define TIM_CR2(t) REG32((t) + 0x04)
#define TIM_SMCR(t) REG32((t) + 0x08)
#define TIM_BDTR(t) REG32((t) + 0x44)
#define TIM_CR1_OPM (1u << 3)
#define TIM_DIER_CC1IE (1u << 1)
#define TIM_SR_CC1IF (1u << 1)
#define TIM_CR2_MMS_UPDATE (2u << 4)      /* TRGO on update: one per CLK period */
#define TIM_SMCR_ECM1_ITR0 (7u | (0u << 4)) /* external clock mode 1 from ITR0 (TIM2: TIM1's TRGO) */
#define TIM_BDTR_MOE (1u << 15)
#define RCC_APB1ENR_TIM2 (1u << 0)
#define RCC_APB2ENR_TIM1 (1u << 0)
#define RCC_APB2ENR_ADC2 (1u << 9)
#define RCC_APB2ENR_SYSCFG (1u << 14)
#define RCC_AHB1ENR_DMA2 (1u << 22)
#define ADC2_BASE 0x40012100u
#define ADC2_SR REG32(ADC2_BASE + 0x00)
#define ADC2_CR1 REG32(ADC2_BASE + 0x04)
#define ADC2_CR2 REG32(ADC2_BASE + 0x08)
#define ADC2_SMPR1 REG32(ADC2_BASE + 0x0C)
#define ADC2_SMPR2 REG32(ADC2_BASE + 0x10)
#define ADC2_SQR1 REG32(ADC2_BASE + 0x2C)
#define ADC2_SQR3 REG32(ADC2_BASE + 0x34)
#define ADC2_DR_ADDR (ADC2_BASE + 0x4C)
#define ADC_CR2_DMA (1u << 8)
#define ADC_CR2_EXTSEL_EXTI11 (15u << 24)
#define ADC_CR2_EXTEN_RISING (1u << 28)
#define ADC_SMP_15_CYCLES 1u
#define DMA2_BASE 0x40026400u
#define DMA2_LIFCR REG32(DMA2_BASE + 0x08)
#define DMA2_S2CR REG32(DMA2_BASE + 0x10 + 0x18 * 2)
#define DMA2_S2NDTR REG32(DMA2_BASE + 0x14 + 0x18 * 2)
#define DMA2_S2PAR REG32(DMA2_BASE + 0x18 + 0x18 * 2)
#define DMA2_S2M0AR REG32(DMA2_BASE + 0x1C + 0x18 * 2)
#define DMA_SXCR_EN (1u << 0)
#define DMA_SXCR_MINC (1u << 10)
#define DMA_SXCR_PSIZE_16 (1u << 11)
#define DMA_SXCR_MSIZE_16 (1u << 13)
#define DMA_SXCR_CHSEL(n) ((uint32_t)(n) << 25)
#define DMA2_LIFCR_STREAM2 (0x3Du << 16)
#define SYSCFG_EXTICR(n) REG32(0x40013800u + 0x08 + 4u * (n)) /* n = 0..3: EXTI 4n..4n+3 */
#define EXTI_IMR REG32(0x40013C00u + 0x00)
#define EXTI_EMR REG32(0x40013C00u + 0x04)
#define EXTI_RTSR REG32(0x40013C00u + 0x08)
#define EXTI_PR REG32(0x40013C00u + 0x14)
#define IRQ_TIM2 28u
#define IRQ_EXTI15_10 40u

#endif
