#include "app_fixture.h"

#include "../core/app.h"
#include "../core/crc.h"
#include "../core/regmap.h"

#define RECORDS_PER_WRITE 100u

static int write_reg(uint16_t addr, uint16_t v) { return app_write_regs(NULL, addr, 1, &v) == MB_OK; }

int fixture_activate_table(const uint8_t *table, uint32_t length)
{
    uint16_t params[7];
    regmap_put_u32(&params[0], length);
    regmap_put_u32(&params[2], crc32_update(0, table, length));
    params[4] = 1;
    params[5] = 0;
    params[6] = TRIMETER_MAP_COMMAND_BEGIN_WRITE;
    if (!write_reg(REG_HR_UNLOCK, TRIMETER_UNLOCK_KEY)) return 1;
    if (app_write_regs(NULL, REG_HR_MAP_EXPECTED_LENGTH, 7, params) != MB_OK) return 2;
    for (uint32_t rec = 0; rec < length / 2; rec += RECORDS_PER_WRITE) {
        uint16_t words[RECORDS_PER_WRITE];
        uint32_t n = length / 2 - rec < RECORDS_PER_WRITE ? length / 2 - rec : RECORDS_PER_WRITE;
        for (uint32_t i = 0; i < n; i++)
            words[i] = (uint16_t)(table[2 * (rec + i)] << 8 | table[2 * (rec + i) + 1]);
        if (app_write_file(NULL, 1, (uint16_t)rec, (uint16_t)n, words) != MB_OK) return 3;
    }
    if (!write_reg(REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_VERIFY)) return 4;
    if (!write_reg(REG_HR_UNLOCK, TRIMETER_UNLOCK_KEY)) return 5;
    if (!write_reg(REG_HR_MAP_COMMAND, TRIMETER_MAP_COMMAND_ACTIVATE)) return 6;
    uint16_t status = 0;
    if (app_read_regs(NULL, MB_TABLE_INPUT_REGISTERS, REG_IR_MAP_OP_STATUS, 1, &status) != MB_OK) return 7;
    return status == TRIMETER_MAP_OP_STATUS_ACTIVATED ? 0 : 8;
}
