/* The point sensor's Gaussian sums, one sample at a time (torchmcmcpf.models.sensors._points_native
 * states the maths and the contract; paper 001's association-free likelihood, DESIGN.md).
 *
 * Plain C99 (with OpenMP where the compiler has it), float64 throughout, built with the radar's
 * loop (torchmcmcpf._native). Every term is exp(c - |p - w_m|^2 / 2) for a whitened, centred
 * position p and point w_m: the loops over the points are written so that the compiler
 * vectorises them, with the exponential below (no calls); a log only where a point's
 * intensity changes.
 */
#include <math.h>
#include <stdint.h>

#include "split.h"
#include "vecmath.h"

/* positions a block in points_near: one vector of doubles on AVX-512, two on AVX2 */
#define LANES 8

/* Adds sign * exp(c - |p - w_m|^2 / 2) to acc[m], m < M; w0, w1 the points' whitened axes */
static inline void add_terms(int64_t M, const double *w0, const double *w1, const double *p, double c, double sign,
                             double *acc) {
    const double p0 = p[0], p1 = p[1];
#pragma omp simd
    for (int64_t m = 0; m < M; ++m) {
        const double d0 = p0 - w0[m], d1 = p1 - w1[m];
        acc[m] += sign * exp_flushed(c - 0.5 * (d0 * d0 + d1 * d1));
    }
}

/* out[r] = the sum over the valid points (valid (M)) of log lam_rm for R consecutive rows of M.
 * The logs of all R M numbers in one flat loop, a block of CHUNK at a time, then the masked
 * sums row by row: a vectorised log loop per row of 41 points cost 4.6 ns a point against 1.0
 * here (its prologue and scalar remainder per row, measured). */
#define CHUNK 4096
static void sum_logs(int64_t R, int64_t M, const double *lam, const uint8_t *valid, double *out) {
    double buf[CHUNK];
    const int64_t rows = M > 0 && M <= CHUNK ? CHUNK / M : 1;
    for (int64_t r0 = 0; r0 < R; r0 += rows) {
        const int64_t nr = R - r0 < rows ? R - r0 : rows;
        for (int64_t r = 0; r < nr; ++r) out[r0 + r] = 0.0;
        for (int64_t e0 = 0; e0 < nr * M; e0 += CHUNK) { /* one row of more than CHUNK points in parts */
            const int64_t ne = nr * M - e0 < CHUNK ? nr * M - e0 : CHUNK;
            const double *l = lam + r0 * M + e0;
#pragma omp simd
            for (int64_t e = 0; e < ne; ++e) buf[e] = log_vec(l[e]);
            const int64_t first = e0 / M;
            for (int64_t e = 0, r = first, m = e0 - first * M; e < ne; ++r, m = 0) { /* row by row */
                const int64_t n = ne - e < M - m ? ne - e : M - m;
                double acc = 0.0;
                for (int64_t k = 0; k < n; ++k) acc += valid[m + k] ? buf[e + k] : 0.0;
                out[r0 + r] += acc;
                e += n;
            }
        }
    }
}

/* points_intensity: lam (n, M) = clutter + sum_k exp(c[i, k] - |p[i, k] - w_m|^2 / 2) for the
 * n = B * P samples (sample i of run i / P): p (n, K, 2), c (n, K) (-inf: an inactive slot,
 * skipped), w (B, 2, M) the runs' points by axis. */
static void intensity_range(int64_t i0, int64_t i1, int64_t P, int64_t K, int64_t M, const double *p,
                            const double *c, const double *w, double clutter, double *lam) {
    for (int64_t i = i0; i < i1; ++i) {
        const double *w0 = w + (i / P) * 2 * M, *w1 = w0 + M;
        double *acc = lam + i * M;
        for (int64_t m = 0; m < M; ++m) acc[m] = 0.0;
        for (int64_t k = 0; k < K; ++k)
            if (c[i * K + k] != -INFINITY) add_terms(M, w0, w1, p + (i * K + k) * 2, c[i * K + k], 1.0, acc);
        for (int64_t m = 0; m < M; ++m) acc[m] += clutter;
    }
}

/* points_delta: a move of V slots read from the samples' intensities cache (n, M): p (n, 2V, 2)
 * and c (n, 2V) the old then the new terms' positions and constants; change (n, M) = the new
 * terms minus the old, delta (n) = sum over the valid points (mask (B, M)) of
 * log((cache + change) / cache), a log only where the change is not 0 (or the cache NaN). */
static void delta_range(int64_t i0, int64_t i1, int64_t P, int64_t V, int64_t M, const double *p, const double *c,
                        const double *w, const uint8_t *mask, const double *cache, double *delta, double *change) {
    for (int64_t i = i0; i < i1; ++i) {
        const int64_t b = i / P;
        const double *w0 = w + b * 2 * M, *w1 = w0 + M;
        double *ch = change + i * M;
        for (int64_t m = 0; m < M; ++m) ch[m] = 0.0;
        for (int64_t j = 0; j < 2 * V; ++j)
            if (c[i * 2 * V + j] != -INFINITY)
                add_terms(M, w0, w1, p + (i * 2 * V + j) * 2, c[i * 2 * V + j], j < V ? -1.0 : 1.0, ch);
    }
    for (int64_t i = i0; i < i1; ++i) { /* a log where a point's intensity changes: about 8 % of them */
        const double *lam = cache + i * M, *ch = change + i * M;
        const uint8_t *valid = mask + (i / P) * M;
        double acc = 0.0;
        for (int64_t m = 0; m < M; ++m)
            if (valid[m] && (ch[m] != 0.0 || lam[m] != lam[m])) acc += log((lam[m] + ch[m]) / lam[m]);
        delta[i] = acc;
    }
}

/* points_near: out (n) = log sum over the valid points of exp(c - |q_i - w_m|^2 / 2), q (n, 2);
 * -inf for a run without valid points, NaN for a NaN position. Positions in blocks of LANES of
 * one run, the points in turn (one vector of terms a point). One pass shifted by c (no term
 * exceeds e^c): where a sum is above 1e-260 (e^-599), the terms it flushed (each below e^-700) are
 * below 1e-40 of it; below, a second pass for that position shifted by its largest term. */
static void near_range(int64_t i0, int64_t i1, int64_t P, int64_t M, const double *q, const double *w,
                       const uint8_t *mask, double c, double *out) {
    for (int64_t i = i0; i < i1;) {
        const int64_t b = i / P, end = (b + 1) * P < i1 ? (b + 1) * P : i1;
        const int64_t L = end - i < LANES ? end - i : LANES;
        const double *w0 = w + b * 2 * M, *w1 = w0 + M;
        const uint8_t *valid = mask + b * M;
        double q0[LANES], q1[LANES], sum[LANES];
        for (int64_t j = 0; j < LANES; ++j) {
            q0[j] = q[2 * (i + (j < L ? j : 0))];
            q1[j] = q[2 * (i + (j < L ? j : 0)) + 1];
            sum[j] = 0.0;
        }
        for (int64_t m = 0; m < M; ++m) {
            if (!valid[m]) continue;
            const double a = w0[m], e = w1[m];
#pragma omp simd
            for (int64_t j = 0; j < LANES; ++j) {
                const double d0 = q0[j] - a, d1 = q1[j] - e;
                sum[j] += exp_flushed(-0.5 * (d0 * d0 + d1 * d1));
            }
        }
        for (int64_t j = 0; j < L; ++j) {
            double total = sum[j], shift = c;
            if (!(total > 1e-260)) { /* far from every point (or none, or NaN) */
                double top = -INFINITY;
                for (int64_t m = 0; m < M; ++m) {
                    const double d0 = q0[j] - w0[m], d1 = q1[j] - w1[m], t = c - 0.5 * (d0 * d0 + d1 * d1);
                    top = valid[m] && t > top ? t : top;
                }
                if (q0[j] != q0[j] || q1[j] != q1[j] || top == -INFINITY) {
                    out[i + j] = q0[j] != q0[j] || q1[j] != q1[j] ? NAN : -INFINITY;
                    continue;
                }
                total = 0.0;
                for (int64_t m = 0; m < M; ++m) {
                    const double d0 = q0[j] - w0[m], d1 = q1[j] - w1[m];
                    total += valid[m] ? exp_flushed(c - 0.5 * (d0 * d0 + d1 * d1) - top) : 0.0;
                }
                shift = top;
            }
            out[i + j] = shift + log(total);
        }
        i += L;
    }
}

/* points_log_sum: out (n) = sum over the valid points (mask (B, M)) of log lam[i, m], lam (n, M) */
static void log_sum_range(int64_t i0, int64_t i1, int64_t P, int64_t M, const double *lam, const uint8_t *mask,
                          double *out) {
    for (int64_t i = i0; i < i1;) { /* run by run (each its own mask) */
        const int64_t b = i / P, end = (b + 1) * P < i1 ? (b + 1) * P : i1;
        sum_logs(end - i, M, lam + i * M, mask + b * M, out + i);
        i = end;
    }
}

int points_log_sum(int64_t n, int64_t threads, int64_t P, int64_t M, const double *lam, const uint8_t *mask,
                   double *out) {
    SPLIT(n, threads, log_sum_range(lo, hi, P, M, lam, mask, out))
    return 0;
}

int points_intensity(int64_t n, int64_t threads, int64_t P, int64_t K, int64_t M, const double *p, const double *c,
                     const double *w, double clutter, double *lam) {
    SPLIT(n, threads, intensity_range(lo, hi, P, K, M, p, c, w, clutter, lam))
    return 0;
}

int points_delta(int64_t n, int64_t threads, int64_t P, int64_t V, int64_t M, const double *p, const double *c,
                 const double *w, const uint8_t *mask, const double *cache, double *delta, double *change) {
    SPLIT(n, threads, delta_range(lo, hi, P, V, M, p, c, w, mask, cache, delta, change))
    return 0;
}

int points_near(int64_t n, int64_t threads, int64_t P, int64_t M, const double *q, const double *w,
                const uint8_t *mask, double c, double *out) {
    SPLIT(n, threads, near_range(lo, hi, P, M, q, w, mask, c, out))
    return 0;
}

/* exp_flushed and log_vec on n numbers, for their tests against libm */
void points_exp(int64_t n, const double *t, double *out) {
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) out[i] = exp_flushed(t[i]);
}

void points_log(int64_t n, const double *t, double *out) {
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) out[i] = log_vec(t[i]);
}
