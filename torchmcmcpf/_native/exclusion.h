/* The exclusion factor's log phi and its change when one slot moves, shared by exclusion.c (the
 * factor's own calls) and exchange.c (the exchange move's one-call iteration): static functions,
 * one copy in each object. */
#ifndef TORCHMCMCPF_EXCLUSION_H
#define TORCHMCMCPF_EXCLUSION_H
#include <math.h>
#include <stddef.h>
#include <stdint.h>

#include "vecmath.h"

/* log phi of n values x = max(d2 / (2 s^2), xmin) (xmin = e^LOG_PHI_FLOOR; scaled() below) into
 * out: log(-expm1(-x)), below x = 1/2 by the series of -expm1(-x) in nested form to x^18
 * (truncation below 1e-22 relative), above it 1 - e^-x (no cancellation there); NaN kept.
 * Vectorised over the values: 1 - e^-x and the log over the whole buffer, the series only
 * where x < 1/2 (slots are mostly farther apart than that). */
static void log_phi_buffer(int64_t n, const double *restrict x, double *restrict out) {
    int small = 0;
    for (int64_t m = 0; m < n; ++m) {
        out[m] = 1.0 - exp_flushed(-x[m]);
        small |= x[m] < 0.5;
    }
    if (small)
        for (int64_t m = 0; m < n; ++m) {
            if (!(x[m] < 0.5)) continue;
            double s = 1.0;
            for (int k = 18; k >= 2; --k) s = 1.0 - x[m] / (double)k * s;
            out[m] = x[m] * s;
        }
    for (int64_t m = 0; m < n; ++m) out[m] = log_vec(out[m]);
}

static inline double scaled(double d2, double inv2s2, double xmin) {
    const double x = d2 * inv2s2;
    return x < xmin ? xmin : x;
}

/* The loops below gather the live pairs' values of a block of samples in order into one buffer
 * (at most BUFFER), log_phi them at once, then sum them sample by sample in the same order as
 * a loop over the live pairs one at a time: the same sums to the bit, the transcendental
 * functions vectorised (2.2-4.5x; tests/models/test_exclusion_native.py) */
#define BUFFER 2048

/* exclusion_change: out (n) = sum over the live slots k != slot_i of e_new log phi(|u_n - u_k|^2)
 * - e_old log phi(|u_old - u_k|^2), u (n, K, r), u_n (n, r), slot (n), alive (n, K) and
 * alive_n (n) uint8 (NULL: all live; alive_n NULL: the slot's current flag) */
static void change_range(int64_t i0, int64_t i1, int64_t K, int64_t r, const double *u, const double *u_n,
                         const int64_t *slot, const uint8_t *alive, const uint8_t *alive_n, double inv2s2, double xmin,
                         double *out) {
    double buf[BUFFER], lp[BUFFER];
    int64_t start[BUFFER + 1];
    const int64_t block = BUFFER / (2 * K) > 0 ? BUFFER / (2 * K) : 1;
    for (int64_t b0 = i0; b0 < i1; b0 += block) {
        const int64_t b1 = b0 + block < i1 ? b0 + block : i1;
        int64_t m = 0;
        for (int64_t i = b0; i < b1; ++i) { /* each live slot k != slot_i: its new and old x */
            const double *ui = u + i * K * r, *un = u_n + i * r, *uo = ui + slot[i] * r;
            start[i - b0] = m;
            for (int64_t k = 0; k < K; ++k) {
                if (k == slot[i] || (alive != NULL && !alive[i * K + k])) continue;
                double d_old = 0.0, d_new = 0.0;
                for (int64_t c = 0; c < r; ++c) {
                    const double a = uo[c] - ui[k * r + c], b = un[c] - ui[k * r + c];
                    d_old += a * a;
                    d_new += b * b;
                }
                buf[m++] = scaled(d_new, inv2s2, xmin);
                buf[m++] = scaled(d_old, inv2s2, xmin);
            }
        }
        start[b1 - b0] = m;
        log_phi_buffer(m, buf, lp);
        for (int64_t i = b0; i < b1; ++i) { /* the sample's live slots, in the order gathered */
            const int e_old = alive == NULL ? 1 : alive[i * K + slot[i]];
            const int e_new = alive_n == NULL ? e_old : alive_n[i];
            double acc = 0.0;
            for (int64_t q = start[i - b0]; q < start[i - b0 + 1]; q += 2)
                acc += (e_new ? lp[q] : 0.0) - (e_old ? lp[q + 1] : 0.0);
            out[i] = acc;
        }
    }
}

#endif
