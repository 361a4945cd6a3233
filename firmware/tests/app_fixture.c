#include "app_fixture.h"

#include <string.h>

#include "../core/crc.h"

#define RECORDS_PER_WRITE 100u

static fake_hal_t *hal;
static void (*each_ms)(void);
static uint32_t loop_period_us = 1000;

fake_hal_t *fixture_fresh_hal(void)
{
    fixture_free_hal();
    hal = fake_hal_new();
    each_ms = NULL;
    loop_period_us = 1000;
    return hal;
}

void fixture_free_hal(void)
{
    if (hal) fake_hal_free(hal);
    hal = NULL;
}

void fixture_each_ms(void (*hook)(void)) { each_ms = hook; }

void fixture_loop_every_us(uint32_t period_us) { loop_period_us = period_us; }

uint32_t fixture_step_isr(void *ctx)
{
    (void)ctx;
    return app_step_isr();
}

void run_ms(uint32_t ms)
{
    for (uint32_t i = 0; i < ms; i++) {
        if (each_ms) each_ms();
        for (uint32_t turn = 0; turn < 1000 / loop_period_us; turn++) {
            fake_hal_run_until(hal, hal->now_us + loop_period_us, fixture_step_isr, NULL);
            app_poll();
        }
    }
}

void send_frame(const uint8_t *adu, size_t len)
{
    uint16_t crc = crc16_modbus(adu, len);
    memcpy(hal->rx, adu, len);
    hal->rx[len] = (uint8_t)crc;
    hal->rx[len + 1] = (uint8_t)(crc >> 8);
    hal->rx_len = len + 2;
    hal->rx_pos = 0;
    hal->tx_len = 0;
    run_ms(4);
}

void fixture_boot(void)
{
    app_init(&hal->hal);
    run_ms(1);
}

int fixture_activate_table(const uint8_t *table, uint32_t length)
{
    uint16_t params[7];
    regmap_put_u32(&params[0], length);
    regmap_put_u32(&params[2], crc32_update(0, table, length));
    params[4] = 1;
    params[5] = 0;
    params[6] = TRIMETER_MAP_COMMAND_BEGIN_WRITE;
    if (write_reg(REG_HR_UNLOCK, TRIMETER_UNLOCK_KEY) != MB_OK) return 1;
    if (app_write_regs(NULL, REG_HR_MAP_EXPECTED_LENGTH, 7, params) != MB_OK) return 2;
    for (uint32_t rec = 0; rec < length / 2; rec += RECORDS_PER_WRITE) {
        uint16_t words[RECORDS_PER_WRITE];
        uint32_t n = length / 2 - rec < RECORDS_PER_WRITE ? length / 2 - rec : RECORDS_PER_WRITE;
        for (uint32_t i = 0; i < n; i++)
            words[i] = (uint16_t)(table[2 * (rec + i)] << 8 | table[2 * (rec + i) + 1]);
        if (app_write_file(NULL, 1, (uint16_t)rec, (uint16_t)n, words) != MB_OK) return 3;
    }
    if (write_reg(REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_VERIFY) != MB_OK) return 4;
    if (write_reg(REG_HR_UNLOCK, TRIMETER_UNLOCK_KEY) != MB_OK) return 5;
    if (write_reg(REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_ACTIVATE) != MB_OK) return 6;
    uint16_t status = 0;
    if (app_read_regs(NULL, MB_TABLE_INPUT_REGISTERS, REG_IR_MAP_OP_STATUS, 1, &status) != MB_OK) return 7;
    return status == TRIMETER_MAP_OP_STATUS_ACTIVATED ? 0 : 8;
}
