/* Minimal unit-test harness for the firmware's host-side C tests.
 * Each test binary ends with CHECK_SUMMARY(), which prints the plain closing line
 * "N passed, N failed" and returns non-zero on any failure. Header-only, no dependencies. */
#ifndef TRIMETER_CHECK_H
#define TRIMETER_CHECK_H

#include <stdio.h>
#include <string.h>

static int check_passed_, check_failed_;

#define CHECK(cond)                                                                      \
    do {                                                                                 \
        if (cond) {                                                                      \
            check_passed_++;                                                             \
        } else {                                                                         \
            check_failed_++;                                                             \
            fprintf(stderr, "%s:%d: CHECK failed: %s\n", __FILE__, __LINE__, #cond);     \
        }                                                                                \
    } while (0)

#define CHECK_EQ_INT(a, b)                                                               \
    do {                                                                                 \
        long long check_a_ = (long long)(a), check_b_ = (long long)(b);                  \
        if (check_a_ == check_b_) {                                                      \
            check_passed_++;                                                             \
        } else {                                                                         \
            check_failed_++;                                                             \
            fprintf(stderr, "%s:%d: CHECK_EQ_INT failed: %s == %s (%lld != %lld)\n",     \
                    __FILE__, __LINE__, #a, #b, check_a_, check_b_);                     \
        }                                                                                \
    } while (0)

#define CHECK_MEM(a, b, n) CHECK(memcmp((a), (b), (n)) == 0)

#define RUN_TEST(fn)                                                                     \
    do {                                                                                 \
        int check_before_ = check_failed_;                                               \
        fn();                                                                            \
        if (check_failed_ != check_before_) fprintf(stderr, "  in test %s\n", #fn);      \
    } while (0)

#define CHECK_SUMMARY()                                                                  \
    (printf("%d passed, %d failed\n", check_passed_, check_failed_), check_failed_ ? 1 : 0)

#endif
