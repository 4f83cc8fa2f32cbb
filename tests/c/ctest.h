/*
 * ctest.h - the smallest possible C test harness for the host-built firmware tests.
 *
 *   static void test_something(void) { CHECK(x == 1); CHECK_EQ_INT(a, b); }
 *   int main(void) { RUN(test_something); return ctest_summary(); }
 *
 * Every CHECK counts; a failing check prints file:line and the expression. main()
 * returns non-zero when anything failed, and the last line is "N passed, N failed".
 * tests/firmware/test_c_units.py builds and runs every tests/c/test_*.c.
 */
#ifndef CTEST_H
#define CTEST_H

#include <inttypes.h>
#include <math.h>
#include <stdio.h>

static int ctest_checks_failed;
static int ctest_tests_passed;
static int ctest_tests_failed;

#define CHECK(cond)                                                                \
    do {                                                                           \
        if (!(cond)) {                                                             \
            ctest_checks_failed++;                                                 \
            printf("  FAIL %s:%d: %s\n", __FILE__, __LINE__, #cond);               \
        }                                                                          \
    } while (0)

#define CHECK_EQ_INT(a, b)                                                         \
    do {                                                                           \
        long long ctest_a_ = (long long)(a), ctest_b_ = (long long)(b);            \
        if (ctest_a_ != ctest_b_) {                                                \
            ctest_checks_failed++;                                                 \
            printf("  FAIL %s:%d: %s == %s (%lld != %lld, 0x%llx != 0x%llx)\n",    \
                   __FILE__, __LINE__, #a, #b, ctest_a_, ctest_b_,                 \
                   (unsigned long long)ctest_a_, (unsigned long long)ctest_b_);    \
        }                                                                          \
    } while (0)

#define CHECK_NEAR(a, b, tol)                                                      \
    do {                                                                           \
        double ctest_a_ = (double)(a), ctest_b_ = (double)(b);                     \
        if (!(fabs(ctest_a_ - ctest_b_) <= (double)(tol))) {                       \
            ctest_checks_failed++;                                                 \
            printf("  FAIL %s:%d: %s ~ %s (%.9g vs %.9g, tol %.3g)\n", __FILE__,   \
                   __LINE__, #a, #b, ctest_a_, ctest_b_, (double)(tol));           \
        }                                                                          \
    } while (0)

#define RUN(fn)                                                                    \
    do {                                                                           \
        int ctest_before_ = ctest_checks_failed;                                   \
        fn();                                                                      \
        if (ctest_checks_failed == ctest_before_) {                                \
            ctest_tests_passed++;                                                  \
            printf("ok   %s\n", #fn);                                              \
        } else {                                                                   \
            ctest_tests_failed++;                                                  \
            printf("FAIL %s\n", #fn);                                              \
        }                                                                          \
    } while (0)

static inline int ctest_summary(void)
{
    printf("%d passed, %d failed\n", ctest_tests_passed, ctest_tests_failed);
    return ctest_tests_failed != 0;
}

#endif
