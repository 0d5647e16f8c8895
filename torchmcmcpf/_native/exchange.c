/* The exchange move's iteration after its likelihood change, in one call (torchmcmcpf.kernels._exchange_native):
 * for each chain of a one-slot move (paper 000 Alg. 2, eq. 12) the log acceptance ratio from the
 * likelihood's change, the exclusion factors' change and the slot's re-capture ratio, the MH
 * decision, every chain field written (the slot's new row where accepted) and the amplitude
 * cache advanced in place: the arithmetic of kernels.exchange.exchange_iteration's tensor ops,
 * operation by operation in the same float32 order (the same bits, tested), in place of the
 * forty-odd ATen calls an iteration made on tensors of a few hundred numbers.
 */
#include <stdint.h>
#include <string.h>

#include "exclusion.h"
#include "split.h"

/* the widest resolution coordinate the exclusion's block buffer holds */
#define MAX_R 4

/* Chains [p0, p1) of n:
 *   log_lik, delta, log_u (n) float32, valid (n) uint8 or NULL, slot (n) int64;
 *   coords (n, K, r) float32 or NULL (no exclusion), coords_new (n, r) float32, inv2s2, xmin;
 *   log_r (n, K) float32 or NULL (no re-capture), r_new (n) float32;
 *   nf fields: src[f] (n, K, width[f] bytes) copied to dst[f], row[f] (n, width[f] bytes) at
 *   slot where accepted;
 *   cache (n * G) float32 or NULL, cells (n, RV) int64 (flat indices into cache), change (n, RV);
 *   out: ll_out (n) float32, accepted (n) uint8.
 * The exclusion's change is change_range's over a block of chains (their coordinates widened
 * to float64, exactly), so its sums are Exclusion.log_change's C loop's to the bit. */
static void commit_range(int64_t p0, int64_t p1, int64_t K, const float *log_lik, const float *delta,
                         const float *log_u, const uint8_t *valid, const int64_t *slot, const float *coords,
                         const float *coords_new, int64_t r, double inv2s2, double xmin, const float *log_r,
                         const float *r_new, int64_t nf, const void *const *src, void *const *dst,
                         const void *const *row, const int64_t *width, float *cache, const int64_t *cells,
                         const float *change, int64_t RV, float *ll_out, uint8_t *accepted) {
    double u[BUFFER / 2 * MAX_R], un[BUFFER / 2 * MAX_R], excl[BUFFER / 2];
    const int64_t block = BUFFER / (2 * K) > 0 ? BUFFER / (2 * K) : 1;
    for (int64_t b0 = p0; b0 < p1; b0 += block) {
        const int64_t b1 = b0 + block < p1 ? b0 + block : p1;
        if (coords != NULL) {
            for (int64_t i = 0; i < (b1 - b0) * K * r; ++i) u[i] = (double)coords[b0 * K * r + i];
            for (int64_t i = 0; i < (b1 - b0) * r; ++i) un[i] = (double)coords_new[b0 * r + i];
            change_range(0, b1 - b0, K, r, u, un, slot + b0, NULL, NULL, inv2s2, xmin, excl);
        }
        for (int64_t q = b0; q < b1; ++q) {
            const int64_t n = slot[q];
            const float ll = log_lik[q], cur = ll + delta[q];
            float lp = 0.0f;
            if (coords != NULL) lp = lp + (float)excl[q - b0];
            if (log_r != NULL) {
                lp = lp + r_new[q];
                lp = lp - log_r[q * K + n];
            }
            const float la = (cur - ll) + lp;
            const int acc = log_u[q] < la && (valid == NULL || valid[q]);
            accepted[q] = (uint8_t)acc;
            ll_out[q] = acc ? cur : ll;
            for (int64_t f = 0; f < nf; ++f) {
                const int64_t w = width[f];
                memcpy((char *)dst[f] + q * K * w, (const char *)src[f] + q * K * w, (size_t)(K * w));
                if (acc) memcpy((char *)dst[f] + (q * K + n) * w, (const char *)row[f] + q * w, (size_t)w);
            }
            if (acc && cache != NULL) /* every cell of the move's boxes, in order (index_add_'s adds) */
                for (int64_t c = 0; c < RV; ++c) cache[cells[q * RV + c]] += change[q * RV + c];
        }
    }
}

int exchange_commit(int64_t n, int64_t threads, int64_t K, const float *log_lik, const float *delta,
                    const float *log_u, const uint8_t *valid, const int64_t *slot, const float *coords,
                    const float *coords_new, int64_t r, double inv2s2, double xmin, const float *log_r,
                    const float *r_new, int64_t nf, const void *const *src, void *const *dst, const void *const *row,
                    const int64_t *width, float *cache, const int64_t *cells, const float *change, int64_t RV,
                    float *ll_out, uint8_t *accepted) {
    if (coords != NULL && (r > MAX_R || K > BUFFER / 2)) return 1;
    SPLIT(n, threads, commit_range(lo, hi, K, log_lik, delta, log_u, valid, slot, coords, coords_new, r, inv2s2, xmin,
                                   log_r, r_new, nf, src, dst, row, width, cache, cells, change, RV, ll_out,
                                   accepted))
    return 0;
}
