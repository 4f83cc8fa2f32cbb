/*
 * param_check_harness.c - the device's parameter checks (ib_core_check_params) as a filter,
 * for tests/firmware/test_param_limits_agree.py: each input line is one packed parameter block in
 * hexadecimal (IB_PARAMS_SIZE bytes, wire layout); each output line is the error code the
 * device gives it (0 = accepted). Built for the host from the same core.c as the firmware.
 */
#include <stdio.h>
#include <string.h>

#include "core.h"
#include "protocol_gen.h"

static int hexval(int ch)
{
    if (ch >= '0' && ch <= '9') {
        return ch - '0';
    }
    if (ch >= 'a' && ch <= 'f') {
        return ch - 'a' + 10;
    }
    if (ch >= 'A' && ch <= 'F') {
        return ch - 'A' + 10;
    }
    return -1;
}

int main(void)
{
    static char line[4 * IB_PARAMS_SIZE];
    while (fgets(line, sizeof line, stdin) != NULL) {
        uint8_t blob[IB_PARAMS_SIZE];
        size_t n = strcspn(line, "\r\n");
        if (n != 2u * IB_PARAMS_SIZE) {
            fprintf(stderr, "line of %zu hex digits, want %u\n", n, 2u * IB_PARAMS_SIZE);
            return 2;
        }
        for (size_t i = 0; i < IB_PARAMS_SIZE; i++) {
            int hi = hexval(line[2 * i]), lo = hexval(line[2 * i + 1]);
            if (hi < 0 || lo < 0) {
                fprintf(stderr, "not hexadecimal\n");
                return 2;
            }
            blob[i] = (uint8_t)(hi << 4 | lo);
        }
        ib_params_t p;
        ib_params_unpack(blob, &p);
        printf("%u\n", (unsigned)ib_core_check_params(&p, NULL, NULL));
    }
    return 0;
}
