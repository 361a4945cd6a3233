/* What the app's tests share: a map table flashed through the app's Modbus callbacks as `trimeter map
 * flash` does. Tests only. check.h counts per test binary, so this reports instead of checking. */
#ifndef TRIMETER_APP_FIXTURE_H
#define TRIMETER_APP_FIXTURE_H

#include <stdint.h>

/* Uploads `table` (`length` bytes, even) into slot A, verifies and activates it; 0 when every step was
 * accepted and the slot reports activated, else the 1-based number of the first step that was not. */
int fixture_activate_table(const uint8_t *table, uint32_t length);

#endif
