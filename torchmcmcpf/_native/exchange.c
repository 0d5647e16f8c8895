/* The exchange move's iteration after its likelihood change, in one call (torchmcmcpf.kernels._exchange_native):
 * for each chain of a move of M slots (paper 000 Alg. 2, eq. 12) the log acceptance ratio from the
 * likelihood's change, the exclusion factors' change and the slots' re-capture ratios, the MH
 * decision, every chain field written (the slots' new rows where accepted) and the amplitude
 * cache advanced in place: the arithmetic of kernels.exchange.exchange_iteration's tensor ops,
 * operation by operation in the same float32 order (the same bits, tested), in place of the
 * forty-odd ATen calls an iteration made on tensors of a few hundred numbers.
 */
#include <stdint.h>
#include <string.h>

#include "exclusion.h"
#include "split.h"

/* the widest resolution coordinate and the most moved slots the block buffers hold */
#define MAX_R 4
#define MAX_M 4

/* Chains [p0, p1) of n, each moving M distinct slots:
 *   log_lik, delta, log_u (n) float32, valid (n) uint8 or NULL, slot (n, M) int64;
 *   src_term (n) float32 or NULL: the pair's source term (exchange.pair_source_log_ratio's change);
 *   coords (n, K, r) float32 or NULL (no exclusion), coords_new (n, M, r) float32, inv2s2, xmin;
 *   log_r (n, K) float32 or NULL (no re-capture), r_new (n, M) float32, r_old (n, M) float32 (each
 *   moved slot's cached ratio, converted to this move's epsilon) or NULL (M = 1: read from log_r);
 *   nf fields: src[f] (n, K, width[f] bytes) copied to dst[f], row[f] (n, M, width[f] bytes) at
 *   the slots where accepted;
 *   cache (n * G) float32, cells (n, RV) int64 (flat indices into cache), change (n, RV) float32;
 *   out: ll_out (n) float32, accepted (n) uint8.
 * log alpha is summed as exchange_iteration sums it: (cur - ll) + (((0 + src_term) + excl_0 +
 * r_new_0 - r_old_0) + excl_1 + ...), each slot's exclusion change seeing the earlier slots moved;
 * the exclusion's change is change_range's over a block of chains (their coordinates widened to
 * float64, exactly), so its sums are Exclusion.log_change's C loop's to the bit. */
static void commit_range(int64_t p0, int64_t p1, int64_t K, int64_t M, const float *log_lik, const float *delta,
                         const float *log_u, const uint8_t *valid, const int64_t *slot, const float *src_term,
                         const float *coords, const float *coords_new, int64_t r, double inv2s2, double xmin,
                         const float *log_r, const float *r_new, const float *r_old, int64_t nf,
                         const void *const *src, void *const *dst, const void *const *row, const int64_t *width,
                         float *cache, const int64_t *cells, const float *change, int64_t RV, float *ll_out,
                         uint8_t *accepted) {
    double u[BUFFER / 2 * MAX_R], un[BUFFER / 2 * MAX_R], excl[MAX_M][BUFFER / 2];
    int64_t sl[BUFFER / 2];
    const int64_t block = BUFFER / (2 * K) > 0 ? BUFFER / (2 * K) : 1;
    for (int64_t b0 = p0; b0 < p1; b0 += block) {
        const int64_t b1 = b0 + block < p1 ? b0 + block : p1, nb = b1 - b0;
        if (coords != NULL) {
            for (int64_t i = 0; i < nb * K * r; ++i) u[i] = (double)coords[b0 * K * r + i];
            for (int64_t j = 0; j < M; ++j) {
                for (int64_t i = 0; i < nb; ++i) {
                    sl[i] = slot[(b0 + i) * M + j];
                    for (int64_t c = 0; c < r; ++c) un[i * r + c] = (double)coords_new[((b0 + i) * M + j) * r + c];
                }
                change_range(0, nb, K, r, u, un, sl, NULL, NULL, inv2s2, xmin, excl[j]);
                if (j + 1 < M) /* the next slot's factors see this one moved */
                    for (int64_t i = 0; i < nb; ++i)
                        for (int64_t c = 0; c < r; ++c) u[(i * K + sl[i]) * r + c] = un[i * r + c];
            }
        }
        for (int64_t q = b0; q < b1; ++q) {
            const int64_t *sq = slot + q * M;
            const float ll = log_lik[q], cur = ll + delta[q];
            float lp = 0.0f;
            if (src_term != NULL) lp = lp + src_term[q];
            for (int64_t j = 0; j < M; ++j) {
                if (coords != NULL) lp = lp + (float)excl[j][q - b0];
                if (log_r != NULL) {
                    const float old = r_old != NULL ? r_old[q * M + j] : log_r[q * K + sq[j]];
                    lp = lp + r_new[q * M + j];
                    lp = lp - old;
                }
            }
            const float la = (cur - ll) + lp;
            const int acc = log_u[q] < la && (valid == NULL || valid[q]);
            accepted[q] = (uint8_t)acc;
            ll_out[q] = acc ? cur : ll;
            for (int64_t f = 0; f < nf; ++f) {
                const int64_t w = width[f];
                if (dst[f] != src[f]) /* in place in a segment (exchange_segment) */
                    memcpy((char *)dst[f] + q * K * w, (const char *)src[f] + q * K * w, (size_t)(K * w));
                if (acc)
                    for (int64_t j = 0; j < M; ++j)
                        memcpy((char *)dst[f] + (q * K + sq[j]) * w, (const char *)row[f] + (q * M + j) * w, (size_t)w);
            }
            if (acc) /* every cell of the move's boxes, in order (index_add_'s adds) */
                for (int64_t c = 0; c < RV; ++c) cache[cells[q * RV + c]] += change[q * RV + c];
        }
    }
}

int exchange_commit(int64_t n, int64_t threads, int64_t K, int64_t M, const float *log_lik, const float *delta,
                    const float *log_u, const uint8_t *valid, const int64_t *slot, const float *src_term,
                    const float *coords, const float *coords_new, int64_t r, double inv2s2, double xmin,
                    const float *log_r, const float *r_new, const float *r_old, int64_t nf, const void *const *src,
                    void *const *dst, const void *const *row, const int64_t *width, float *cache,
                    const int64_t *cells, const float *change, int64_t RV, float *ll_out, uint8_t *accepted) {
    if (M > MAX_M || (coords != NULL && (r > MAX_R || K > BUFFER / 2))) return 1;
    SPLIT(n, threads, commit_range(lo, hi, K, M, log_lik, delta, log_u, valid, slot, src_term, coords, coords_new, r,
                                   inv2s2, xmin, log_r, r_new, r_old, nf, src, dst, row, width, cache, cells, change,
                                   RV, ll_out, accepted))
    return 0;
}

/* A sensor's change of one chain's move read from its rows (kernels.exchange.exchange_iteration's
 * log_likelihood_delta_rows, for sample q): rician_rows_one of rician_window.c is one. */
typedef float (*rows_delta)(const void *ctx, int64_t q, int64_t M, const float *terms_q, const int64_t *slot_q,
                            const float *terms_new_q, const float *cache, int64_t *cq, float *hq);

#define MAX_F 16 /* chain fields */

/* L iterations of M-slot moves of chains [p0, p1), chain by chain, iteration after iteration:
 * the sensor's change (fn) and commit_range on the chains' own fields, in place; after
 * iteration t >= record, each recorded field's rows (trace[f] non-NULL, (L - record, n, K,
 * width[f] bytes)) and log_lik (ll_trace, (L - record, n)) copied out; count (n) += the
 * acceptances. The per-iteration inputs have leading (L, n): log_u, valid, slot (L, n, M),
 * src_term (or NULL), coords_new (L, n, M, r), r_new (L, n, M) at the move's epsilon, row[f]
 * (L, n, M, width[f] bytes), terms_new (L, n, M, 4). With conv (3 floats, by the slots' kind
 * int8 (n, K): FIXED, MOTION, RELOCATED) each moved slot's cached ratio is converted to the
 * move's epsilon as kernels.exchange's convert does, log_r + conv[kind] in float32, into
 * r_old (n, M); without, read as it is. delta (n), cells and change (n, RV), accepted (n):
 * scratch. Each chain's arithmetic is exchange_commit's and the sensor's call's for that
 * chain, in the iterations' order: the same bits as L calls of the two. */
static void segment_range(int64_t p0, int64_t p1, int64_t n, int64_t L, int64_t K, int64_t M, float *log_lik,
                          const float *log_u, const uint8_t *valid, const int64_t *slot, const float *src_term,
                          float *coords, const float *coords_new, int64_t r, double inv2s2, double xmin, float *log_r,
                          const float *r_new, const int8_t *kind, const float *conv, float *r_old, int64_t nf,
                          void *const *field, const void *const *row, const int64_t *width, const float *terms,
                          const float *terms_new, float *cache, rows_delta fn, const void *ctx, int64_t RV,
                          float *delta, int64_t *cells, float *change, uint8_t *accepted, int64_t record,
                          void *const *trace, float *ll_trace, float *count) {
    const void *rows_t[MAX_F];
    /* one chain at a time through all L iterations: its cache rows near its slots stay in the
     * core's caches between its moves (blocks of 64 chains measured the same or 5 % slower) */
    const int64_t block = 1;
    for (int64_t b0 = p0; b0 < p1; b0 += block) {
        const int64_t b1 = b0 + block < p1 ? b0 + block : p1;
        for (int64_t t = 0; t < L; ++t) {
            const int64_t *st = slot + t * n * M;
            for (int64_t q = b0; q < b1; ++q)
                delta[q] = fn(ctx, q, M, terms + q * K * 4, st + q * M, terms_new + (t * n + q) * M * 4, cache,
                              cells + q * RV, change + q * RV);
            if (conv != NULL)
                for (int64_t q = b0; q < b1; ++q)
                    for (int64_t j = 0; j < M; ++j) {
                        const int64_t at = q * K + st[q * M + j];
                        const float c = kind[at] == 1 ? conv[1] : kind[at] == 2 ? conv[2] : conv[0];
                        r_old[q * M + j] = log_r[at] + c;
                    }
            for (int64_t f = 0; f < nf; ++f) rows_t[f] = (const char *)row[f] + t * n * M * width[f];
            commit_range(b0, b1, K, M, log_lik, delta, log_u + t * n, valid == NULL ? NULL : valid + t * n, st,
                         src_term == NULL ? NULL : src_term + t * n, coords,
                         coords == NULL ? NULL : coords_new + t * n * M * r, r, inv2s2, xmin, log_r,
                         log_r == NULL ? NULL : r_new + t * n * M, conv == NULL ? NULL : r_old, nf,
                         (const void *const *)field, field, rows_t, width, cache, cells, change, RV, log_lik, accepted);
            for (int64_t q = b0; q < b1; ++q) count[q] += (float)accepted[q];
            if (t < record) continue;
            for (int64_t f = 0; f < nf; ++f) {
                if (trace[f] == NULL) continue;
                const int64_t w = K * width[f];
                memcpy((char *)trace[f] + ((t - record) * n + b0) * w, (const char *)field[f] + b0 * w,
                       (size_t)((b1 - b0) * w));
            }
            if (ll_trace != NULL)
                memcpy(ll_trace + (t - record) * n + b0, log_lik + b0, (size_t)(b1 - b0) * sizeof(float));
        }
    }
}

int exchange_segment(int64_t n, int64_t threads, int64_t L, int64_t K, int64_t M, float *log_lik, const float *log_u,
                     const uint8_t *valid, const int64_t *slot, const float *src_term, float *coords,
                     const float *coords_new, int64_t r, double inv2s2, double xmin, float *log_r, const float *r_new,
                     const int8_t *kind, const float *conv, float *r_old, int64_t nf, void *const *field,
                     const void *const *row, const int64_t *width, const float *terms, const float *terms_new,
                     float *cache, rows_delta fn, const void *ctx, int64_t RV, float *delta, int64_t *cells,
                     float *change, uint8_t *accepted, int64_t record, void *const *trace, float *ll_trace,
                     float *count) {
    if (nf > MAX_F || M > MAX_M || (coords != NULL && (r > MAX_R || K > BUFFER / 2))
        || (conv != NULL && (kind == NULL || log_r == NULL)))
        return 1;
    SPLIT(n, threads, segment_range(lo, hi, n, L, K, M, log_lik, log_u, valid, slot, src_term, coords, coords_new, r,
                                    inv2s2, xmin, log_r, r_new, kind, conv, r_old, nf, field, row, width, terms,
                                    terms_new, cache, fn, ctx, RV, delta, cells, change, accepted, record, trace,
                                    ll_trace, count))
    return 0;
}
