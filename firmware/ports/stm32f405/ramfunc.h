/* Code that must keep running while the flash is busy erasing or programming: the CPU stalls on any
 * flash fetch until the operation ends (one bank), so such code is linked into RAM (.ramfunc, copied
 * there at reset with .data). tests/firmware/test_stm32_image.py checks that nothing placed there
 * branches to or loads from flash. */
#ifndef TRIMETER_STM32F405_RAMFUNC_H
#define TRIMETER_STM32F405_RAMFUNC_H

#define RAMFUNC __attribute__((section(".ramfunc"), noinline))

#endif
