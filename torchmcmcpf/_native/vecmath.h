/* Vectorisable float64 exp and log for the C loops (no calls: the compiler vectorises the loops
 * that use them), each within 2 ulps of libm's (tested through points_exp and points_log). */
#ifndef TORCHMCMCPF_VECMATH_H
#define TORCHMCMCPF_VECMATH_H
#include <math.h>
#include <stdint.h>

/* points.FLUSH: a term below e^FLUSH is exactly 0 (below half an ulp of any intensity's clutter
 * floor above 1e-288 and of a shifted logsumexp's 1) */
#define FLUSH (-700.0)

/* e^t, exactly 0 below FLUSH (points._exp_), NaN kept; t above 709 gives e^709 (no term of a
 * Gaussian density of a physical noise comes near). n = round(t / ln 2) by the 1.5 * 2^52
 * shift (its low bits hold n), r = t - n ln 2 in two parts (Cody and Waite), e^r by its Taylor
 * series to r^13 (|r| <= ln 2 / 2: truncation below 2e-17 relative), scaled by 2^n written
 * into the exponent bits. Relative error a few ulps, against libm's exp (tested). */
static inline double exp_flushed(double t) {
    const double shift = 6755399441055744.0; /* 1.5 * 2^52 */
    const int keep = !(t < FLUSH);           /* NaN kept */
    double u = t < FLUSH ? FLUSH : t;
    u = u > 709.0 ? 709.0 : u;
    const double kd = u * 1.4426950408889634 + shift;
    union { double d; int64_t i; } bits = { kd }, scale;
    const double n = kd - shift;
    const double r = (u - n * 6.93145751953125e-1) - n * 1.42860682030941723212e-6;
    double y = 1.0 / 6227020800.0; /* 1/13! */
    y = y * r + 1.0 / 479001600.0;
    y = y * r + 1.0 / 39916800.0;
    y = y * r + 1.0 / 3628800.0;
    y = y * r + 1.0 / 362880.0;
    y = y * r + 1.0 / 40320.0;
    y = y * r + 1.0 / 5040.0;
    y = y * r + 1.0 / 720.0;
    y = y * r + 1.0 / 120.0;
    y = y * r + 1.0 / 24.0;
    y = y * r + 1.0 / 6.0;
    y = y * r + 0.5;
    y = y * r + 1.0;
    y = y * r + 1.0;
    scale.i = (bits.i + 1023) << 52; /* 2^n: n + 1023 in the exponent's 11 bits */
    return keep ? y * scale.d : 0.0;
}

/* log x in float64, vectorisable: x = m 2^e with m in [sqrt(1/2), sqrt(2)), s = (m - 1) / (m + 1),
 * log m = 2 atanh(s) by its series to s^21 (|s| <= 0.172: truncation below 1e-18 relative), e ln 2
 * in two parts (fdlibm's split); subnormals scaled by 2^54 first; 0, negatives, inf and NaN as
 * libm. Error about 2 ulps of the result (tested against torch.log). */
static inline double log_vec(double x) {
    const int tiny = x < 2.2250738585072014e-308;
    union { double d; int64_t i; } v = { tiny ? x * 18014398509481984.0 : x }; /* 2^54 */
    int64_t e = ((v.i >> 52) & 0x7ff) - 1023 - (tiny ? 54 : 0);
    v.i = (v.i & 0x000fffffffffffffLL) | 0x3ff0000000000000LL; /* m in [1, 2) */
    const int high = v.d > 1.4142135623730951;
    const double m = high ? 0.5 * v.d : v.d;
    e += high;
    const double s = (m - 1.0) / (m + 1.0), z = s * s;
    double y = 1.0 / 21.0;
    y = y * z + 1.0 / 19.0;
    y = y * z + 1.0 / 17.0;
    y = y * z + 1.0 / 15.0;
    y = y * z + 1.0 / 13.0;
    y = y * z + 1.0 / 11.0;
    y = y * z + 1.0 / 9.0;
    y = y * z + 1.0 / 7.0;
    y = y * z + 1.0 / 5.0;
    y = y * z + 1.0 / 3.0;
    const double fe = (double)e;
    const double r = fe * 6.93147180369123816490e-01 + (fe * 1.90821492927058770002e-10 + (2.0 * s + 2.0 * s * z * y));
    /* the special values, by selects (NaN kept through the last one) */
    const double special = x == 0.0 ? -INFINITY : (x < 0.0 ? NAN : x);
    return x > 0.0 && x < INFINITY ? r : special;
}

#endif
