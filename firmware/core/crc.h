/* CRC helpers shared by the Modbus slave (CRC-16/MODBUS) and storage (CRC-32/IEEE, as zlib). */
#ifndef TRIMETER_CRC_H
#define TRIMETER_CRC_H

#include <stddef.h>
#include <stdint.h>

/* CRC-16/MODBUS: poly 0xA001 reflected, init 0xFFFF; sent low byte first.
 * Start with crc16_modbus_update(0xFFFF, ...); over data + its CRC the result is 0. */
uint16_t crc16_modbus_update(uint16_t crc, const void *data, size_t n);
uint16_t crc16_modbus(const void *data, size_t n);

/* CRC-32/IEEE (zlib.crc32, Ethernet): poly 0xEDB88320 reflected, init and final XOR 0xFFFFFFFF.
 * Chainable like zlib: crc = crc32_update(0, a, na); crc = crc32_update(crc, b, nb). */
uint32_t crc32_update(uint32_t crc, const void *data, size_t n);

#endif
