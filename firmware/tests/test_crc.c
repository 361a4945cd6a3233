/* CRC-16/MODBUS and CRC-32/IEEE against published check values and Modbus spec frames. */
#include "../core/crc.h"
#include "check.h"

static void test_crc16_check_value(void) {
    /* The CRC catalogue's check value for CRC-16/MODBUS over "123456789". */
    CHECK_EQ_INT(crc16_modbus("123456789", 9), 0x4B37);
    CHECK_EQ_INT(crc16_modbus("", 0), 0xFFFF);
}

static void test_crc16_spec_frames(void) {
    /* Modbus over serial line spec / application protocol examples, CRC sent low byte first. */
    const uint8_t read_hr[] = {0x11, 0x03, 0x00, 0x6B, 0x00, 0x03, 0x76, 0x87};
    const uint8_t read_10[] = {0x01, 0x03, 0x00, 0x00, 0x00, 0x0A, 0xC5, 0xCD};
    const uint8_t write_coil[] = {0x01, 0x05, 0x00, 0xAC, 0xFF, 0x00, 0x4C, 0x1B};
    CHECK_EQ_INT(crc16_modbus(read_hr, 6), 0x8776);
    CHECK_EQ_INT(crc16_modbus(read_10, 6), 0xCDC5);
    CHECK_EQ_INT(crc16_modbus(write_coil, 6), 0x1B4C);
    /* Over data + CRC the remainder is zero: what the framer tests. */
    CHECK_EQ_INT(crc16_modbus(read_hr, 8), 0);
    CHECK_EQ_INT(crc16_modbus(read_10, 8), 0);
    uint8_t corrupt[8];
    memcpy(corrupt, read_hr, 8);
    corrupt[3] ^= 0x01;
    CHECK(crc16_modbus(corrupt, 8) != 0);
}

static void test_crc16_chaining(void) {
    uint16_t c = crc16_modbus_update(0xFFFF, "1234", 4);
    c = crc16_modbus_update(c, "56789", 5);
    CHECK_EQ_INT(c, 0x4B37);
}

static void test_crc32_check_values(void) {
    CHECK_EQ_INT(crc32_update(0, "123456789", 9), 0xCBF43926u);
    CHECK_EQ_INT(crc32_update(0, "", 0), 0);
    CHECK_EQ_INT(crc32_update(0, "The quick brown fox jumps over the lazy dog", 43), 0x414FA339u);
    /* Chained like zlib.crc32(b, zlib.crc32(a)). */
    uint32_t c = crc32_update(0, "12345", 5);
    CHECK_EQ_INT(crc32_update(c, "6789", 4), 0xCBF43926u);
}

static void test_crc32_long_buffer(void) {
    /* 1 MiB of 0xFF (erased flash), python: zlib.crc32(b"\xff" * (1 << 20)). */
    static uint8_t erased[1u << 20];
    memset(erased, 0xFF, sizeof erased);
    CHECK_EQ_INT(crc32_update(0, erased, sizeof erased), 0x956BAC74u);
}

int main(void) {
    RUN_TEST(test_crc16_check_value);
    RUN_TEST(test_crc16_spec_frames);
    RUN_TEST(test_crc16_chaining);
    RUN_TEST(test_crc32_check_values);
    RUN_TEST(test_crc32_long_buffer);
    return CHECK_SUMMARY();
}
