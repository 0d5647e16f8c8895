/* The windowed Rician log-likelihood of a three-axis grid sensor, one particle at a time
 * (torchmcmcpf.models.sensors.grid.native states the maths and the contract).
 *
 * Plain C99 (with OpenMP where the compiler has it), no headers of Python or torch: built once per machine by the host's C compiler
 * (-O3 -march=native) and called through ctypes with the tensors' data pointers. The cell
 * loops are written so that the compiler vectorises them (no calls, selects instead of
 * branches); log is the Cephes single-precision polynomial, exp is libm's (per profile value,
 * 21 per target, not per cell).
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "split.h"

/* Abramowitz and Stegun 9.8.1 and 9.8.2, as torchmcmcpf.models.sensors.radar.log_i0_approx */
#define P_S0 1.0f
#define P_S1 3.5156229f
#define P_S2 3.0899424f
#define P_S3 1.2067492f
#define P_S4 0.2659732f
#define P_S5 0.0360768f
#define P_S6 0.0045813f
#define P_L0 0.39894228f
#define P_L1 0.01328592f
#define P_L2 0.00225319f
#define P_L3 (-0.00157565f)
#define P_L4 0.00916281f
#define P_L5 (-0.02057706f)
#define P_L6 0.02635537f
#define P_L7 (-0.01647633f)
#define P_L8 0.00392377f

/* natural log of a positive normal float: Cephes logf (relative error about 1e-7) */
static inline float log_pos(float x) {
    union { float f; int32_t i; } v = { x };
    int32_t e = ((v.i >> 23) & 0xff) - 126;
    v.i = (v.i & 0x007fffff) | 0x3f000000; /* mantissa in [0.5, 1) */
    float m = v.f;
    int lo = m < 0.70710678118654752f;
    e -= lo;
    m = (lo ? m + m : m) - 1.0f;
    float z = m * m;
    float y = 7.0376836292e-2f;
    y = y * m - 1.1514610310e-1f;
    y = y * m + 1.1676998740e-1f;
    y = y * m - 1.2420140846e-1f;
    y = y * m + 1.4249322787e-1f;
    y = y * m - 1.6668057665e-1f;
    y = y * m + 2.0000714765e-1f;
    y = y * m - 2.4999993993e-1f;
    y = y * m + 3.3333331174e-1f;
    y = y * m * z;
    float fe = (float)e;
    y += -2.12194440e-4f * fe;
    y += -0.5f * z;
    return m + y + 0.693359375f * fe;
}

/* log I0(v) - a^2 * half_inv_var for one cell; NaN in, NaN out (the (v - v) term) */
static inline float cell_ratio(float a, float zc, float half_inv_var) {
    float v = a * zc;
    float av = fabsf(v);
    int small = av < 3.75f;
    float t = (small ? av : 3.75f) * (1.0f / 3.75f); /* selects, not fminf: NaN comes through (v - v) */
    t = t * t;
    float ps = ((((((P_S6 * t + P_S5) * t + P_S4) * t + P_S3) * t + P_S2) * t + P_S1) * t + P_S0);
    float big = small ? 3.75f : av;
    float r = 3.75f / big;
    float pl = (((((((P_L8 * r + P_L7) * r + P_L6) * r + P_L5) * r + P_L4) * r + P_L3) * r + P_L2) * r + P_L1) * r
               + P_L0;
    /* one log for both branches: log(pl) - log(big) / 2 = log(pl / sqrt(big)) */
    float li0 = log_pos(small ? ps : pl / sqrtf(big)) + (small ? 0.0f : big);
    return li0 - a * a * half_inv_var + (v - v);
}

#define MAX_K 64
#define MAX_W 16 /* per box axis: buffers of 16^3 cells on the stack (48 KB), fine for any thread */

/* The grid and its boxes: cells per axis N, box sizes W, a box's cells V = W0 W1 W2 laid out
 * as W0 rows of V12 = W1 W2 (the last two axes merged, as GridGeometry.box_cells), the frame's
 * G = N0 N1 N2 cells, and per axis the origin c0, cell size dc and 1 / (sqrt(2) width) sc. */
typedef struct {
    int64_t N[3], W[3], V12, V, G12, G, window;
    float c0[3], dc[3], sc[3];
} Grid;

/* 0, or 1 when a box is larger than the static buffers */
static int grid_of(Grid *g, const int64_t *shape, const double *geo, int64_t window) {
    for (int a = 0; a < 3; ++a) {
        g->N[a] = shape[a];
        g->W[a] = shape[3 + a];
        g->c0[a] = (float)geo[3 * a];
        g->dc[a] = (float)geo[3 * a + 1];
        g->sc[a] = (float)geo[3 * a + 2];
        if (g->W[a] > MAX_W) return 1;
    }
    g->V12 = g->W[1] * g->W[2];
    g->V = g->W[0] * g->V12;
    g->G12 = g->N[1] * g->N[2];
    g->G = g->N[0] * g->G12;
    g->window = window;
    return 0;
}

/* Each of K spreads' box (first cell per axis: the nearest cell minus the window, shifted into
 * the grid, as GridGeometry.box_first) and its per-axis profile over the box (eq. 20, as
 * spread.neighbour_profiles computes it); uk (K, 3) measurement coordinates. A non-finite
 * coordinate gives a box at the grid's edge and NaN profiles, never a cell outside the grid. */
static void boxes_of(const Grid *g, const float *uk, int64_t K, int64_t first[][3], float prof[][3][MAX_W]) {
    for (int64_t k = 0; k < K; ++k)
        for (int a = 0; a < 3; ++a) {
            const float ua = uk[3 * k + a];
            float f = nearbyintf((ua - g->c0[a]) / g->dc[a]) - (float)g->window;
            const float hi = (float)(g->N[a] - g->W[a]);
            f = f >= 0.0f ? f : 0.0f; /* NaN -> 0 */
            f = f <= hi ? f : hi;
            first[k][a] = (int64_t)f;
            const float us = ua * g->sc[a];
            for (int64_t t = 0; t < g->W[a]; ++t) {
                const float d = (g->c0[a] + g->dc[a] * (f + (float)t)) * g->sc[a] - us;
                prof[k][a][t] = expf(-(d * d));
            }
        }
}

/* Whether box j is box k of an earlier index in `among` (or any earlier one, among = NULL):
 * every cell of such a box is held by that earlier box, so its masked terms are all exactly 0
 * (A and A' agree there) and the box adds nothing to the sum; NaN cells are the earlier box's. */
static int repeats_box(const int64_t first[][3], int64_t j, const uint8_t *among) {
    for (int64_t k = 0; k < j; ++k)
        if ((among == NULL || among[k]) && first[k][0] == first[j][0] && first[k][1] == first[j][1]
            && first[k][2] == first[j][2])
            return 1;
    return 0;
}

/* Adds spread k (amplitude sk, box fk, profiles pk) to the cells of box fj (acc, V cells; none
 * when NULL) over the two boxes' intersection only, as blocks of the V12 cells of a row: Q
 * holds the product of k's last two profiles inside the intersection and 0 outside. With
 * `mask`, the intersection's cells are also set to 0 there (an earlier box holds them). */
static void add_spread(const Grid *g, const int64_t fj[3], const int64_t fk[3], const float pk[3][MAX_W], float sk,
                       float *acc, float *mask) {
    int64_t lo[3], hi[3], lag[3];
    for (int a = 0; a < 3; ++a) { /* box k's cells in box j's local coordinates */
        lag[a] = fj[a] - fk[a];
        lo[a] = lag[a] < 0 ? -lag[a] : 0;
        hi[a] = g->W[a] - (lag[a] > 0 ? lag[a] : 0);
        if (lo[a] >= hi[a]) return; /* the boxes do not meet */
    }
    float Q[MAX_W * MAX_W], keep[MAX_W * MAX_W];
    for (int64_t c = 0; c < g->V12; ++c) { Q[c] = 0.0f; keep[c] = 1.0f; }
    const float *p0 = pk[0] + lag[0], *p1 = pk[1] + lag[1], *p2 = pk[2] + lag[2];
    for (int64_t m = lo[1]; m < hi[1]; ++m)
        for (int64_t l = lo[2]; l < hi[2]; ++l) {
            Q[m * g->W[2] + l] = p1[m] * p2[l];
            keep[m * g->W[2] + l] = 0.0f;
        }
    for (int64_t i = lo[0]; i < hi[0]; ++i) {
        if (acc != NULL) {
            const float si = sk * p0[i];
            float *ai = acc + i * g->V12;
            for (int64_t c = 0; c < g->V12; ++c) ai[c] += si * Q[c];
        }
        if (mask != NULL) {
            float *mi = mask + i * g->V12;
            for (int64_t c = 0; c < g->V12; ++c) mi[c] *= keep[c];
        }
    }
}

/* The frame's cells of box fj into Z (V cells; rows copied 8 floats at a time from the padded
 * frame zq, so Z has 8 floats to spare; none when Z is NULL), with `cache` its cells too (A),
 * and with `cells` their flat index (base + the cell). */
static void box_cells_of(const Grid *g, const float *zq, const int64_t fj[3], float *Z, const float *cache,
                         float *A, int64_t base, int64_t *cells) {
    for (int64_t i = 0; i < g->W[0]; ++i)
        for (int64_t m = 0; m < g->W[1]; ++m) {
            const int64_t row = (fj[0] + i) * g->G12 + (fj[1] + m) * g->N[2] + fj[2], at = i * g->V12 + m * g->W[2];
            if (Z != NULL)
                for (int64_t l = 0; l < g->W[2]; l += 8) memcpy(Z + at + l, zq + row + l, 8 * sizeof(float));
            if (cache != NULL)
                for (int64_t l = 0; l < g->W[2]; ++l) A[at + l] = cache[row + l];
            if (cells != NULL)
                for (int64_t l = 0; l < g->W[2]; ++l) cells[at + l] = base + row + l;
        }
}

/* Windowed log-likelihood of particles [p0, p1) of B x P.
 *   u      (B*P, K, 3) measurement coordinates     s    (B*P, K) amplitudes (times existence)
 *   live   (B*P, K) uint8                          zc   (B, N0*N1*N2 + 8) prepared frames, each
 *                                                       padded by 8 floats (rows are copied 8 at a time)
 *   out    (B*P) float
 * Box j sums the live spreads over its intersections with their boxes, masks the cells an
 * earlier live box holds (each cell of the union counted once), and adds its cells' ratios.
 */
static void window_range(const Grid *g, int64_t p0, int64_t p1, int64_t P, int64_t K, const float *u,
                         const float *s, const uint8_t *live, const float *zc, float half_inv_var, float *out) {
    float prof[MAX_K][3][MAX_W];
    int64_t first[MAX_K][3];
    float A[MAX_W * MAX_W * MAX_W], Z[MAX_W * MAX_W * MAX_W + 8], own[MAX_W * MAX_W * MAX_W];
    for (int64_t q = p0; q < p1; ++q) {
        const float *sq = s + q * K;
        const uint8_t *lq = live + q * K;
        boxes_of(g, u + q * K * 3, K, first, prof);
        double total = 0.0;
        for (int64_t j = 0; j < K; ++j) {
            if (!lq[j] || repeats_box(first, j, lq)) continue;
            for (int64_t c = 0; c < g->V; ++c) { A[c] = 0.0f; own[c] = 1.0f; }
            for (int64_t k = 0; k < K; ++k)
                if (lq[k]) add_spread(g, first[j], first[k], prof[k], sq[k], A, k < j ? own : NULL);
            box_cells_of(g, zc + (q / P) * (g->G + 8), first[j], Z, NULL, NULL, 0, NULL);
            float acc = 0.0f;
#pragma omp simd reduction(+ : acc)
            for (int64_t c = 0; c < g->V; ++c) {
                const float r = cell_ratio(A[c], Z[c], half_inv_var);
                acc += own[c] != 0.0f ? r : 0.0f;
            }
            total += (double)acc;
        }
        out[q] = (float)total;
    }
}

/* The arithmetic floor of the windowed radar step (torchmcmcpf.bench.peers.radar_floor):
 * boxes x V cells, each one amplitude times a profile value and the Rician log ratio there,
 * summed; inputs of a few KB (amp (boxes), prof (V), zc (V)), so no memory traffic but the loop's.
 */
static double floor_range(int64_t boxes, int64_t V, const float *amp, const float *prof, const float *zc,
                    double half_inv_var_d) {
    const float half_inv_var = (float)half_inv_var_d;
    double total = 0.0;
    for (int64_t b = 0; b < boxes; ++b) {
        const float ab = amp[b];
        float acc = 0.0f;
#pragma omp simd reduction(+ : acc)
        for (int64_t c = 0; c < V; ++c) acc += cell_ratio(ab * prof[c], zc[c], half_inv_var);
        total += (double)acc;
    }
    return total;
}

/* A move's change of the windowed Rician log-likelihood read from the chains' amplitude cache
 * (torchmcmcpf.models.sensors.grid.amplitudes.log_likelihood_delta_cached, box form), chains
 * [p0, p1) of B x P. The move's R = 2M spreads (slot 0 before, after, slot 1 before, ...):
 *   u      (B*P, R, 3) measurement coordinates     s      (B*P, R) signed amplitudes (- old, + new)
 *   cache  (B*P, G) each chain's amplitude per cell
 *   zc as window_range
 * Writes delta (B*P), and per box r of the R boxes its cells' flat index into the cache
 * (cells (B*P, R, V) int64, q * G + the cell) and the change there (change (B*P, R, V); 0
 * at the cells an earlier box of the move holds, so each cell changes once). Each cell's
 * term is ratio(max(A + change, 0)) - ratio(max(A, 0)).
 */
/* The cached move's change of sample q (rician_delta_cached below): uq (R, 3), sq (R) its
 * spreads; writes its cells and change, cq and hq (R, V), and returns the sum. */
static float delta_sample(const Grid *g, int64_t q, int64_t P, int64_t R, const float *uq, const float *sq,
                          const float *cache, const float *zc, float half_inv_var, int64_t *cq, float *hq) {
    float prof[MAX_K][3][MAX_W];
    int64_t first[MAX_K][3];
    float A[MAX_W * MAX_W * MAX_W], Z[MAX_W * MAX_W * MAX_W + 8], once[MAX_W * MAX_W * MAX_W];
    const int64_t V = g->V;
    boxes_of(g, uq, R, first, prof);
    /* the boxes' rows of the cache and the frame requested now, read after the spreads: a
     * chain's cache (245 kB on bench's grid) is rarely in the core's caches */
    for (int64_t j = 0; j < R; ++j)
        for (int64_t i = 0; i < g->W[0]; ++i)
            for (int64_t m = 0; m < g->W[1]; ++m) {
                const int64_t row = (first[j][0] + i) * g->G12 + (first[j][1] + m) * g->N[2] + first[j][2];
                const float *a = cache + q * g->G + row, *z = zc + (q / P) * (g->G + 8) + row;
                __builtin_prefetch(a); /* a row's first and last cells: one or two lines */
                __builtin_prefetch(a + g->W[2] - 1);
                __builtin_prefetch(z);
                __builtin_prefetch(z + g->W[2] - 1);
            }
    double total = 0.0;
    for (int64_t j = 0; j < R; ++j) {
        float *ch = hq + j * V;
        if (repeats_box(first, j, NULL)) { /* no change here: an earlier box holds every cell */
            memset(ch, 0, (size_t)V * sizeof(float));
            box_cells_of(g, NULL, first[j], NULL, NULL, NULL, q * g->G, cq + j * V);
            continue;
        }
        for (int64_t c = 0; c < V; ++c) { ch[c] = 0.0f; once[c] = 1.0f; }
        for (int64_t k = 0; k < R; ++k) add_spread(g, first[j], first[k], prof[k], sq[k], ch, k < j ? once : NULL);
        box_cells_of(g, zc + (q / P) * (g->G + 8), first[j], Z, cache + q * g->G, A, q * g->G, cq + j * V);
        float acc = 0.0f;
#pragma omp simd reduction(+ : acc)
        for (int64_t c = 0; c < V; ++c) {
            const float d = ch[c] * once[c];
            ch[c] = d;
            const float a0 = A[c] < 0.0f ? 0.0f : A[c], a1 = A[c] + d < 0.0f ? 0.0f : A[c] + d;
            acc += cell_ratio(a1, Z[c], half_inv_var) - cell_ratio(a0, Z[c], half_inv_var);
        }
        total += (double)acc;
    }
    return (float)total;
}

static void delta_range(const Grid *g, int64_t p0, int64_t p1, int64_t P, int64_t R, const float *u, const float *s,
                        const float *cache, const float *zc, float half_inv_var, float *delta, int64_t *cells,
                        float *change) {
    for (int64_t q = p0; q < p1; ++q)
        delta[q] = delta_sample(g, q, P, R, u + q * R * 3, s + q * R, cache, zc, half_inv_var, cells + q * R * g->V,
                                change + q * R * g->V);
}

/* delta_range for moves of M distinct slots read from rows (torchmcmcpf.models.sensors.grid.native.delta_rows):
 * terms (B*P, K, 4) each slot's measurement coordinates and amplitude (times existence), slot
 * (B*P, M) int64 the moved slots, terms_new (B*P, M, 4) their rows after the move: the spreads
 * of delta_range with R = 2M, each slot's before, then after (amplitudes._moved_terms' order),
 * the amplitude before negated (exact, as amplitudes._signed makes it). rows_sample is one
 * sample's: terms_q (K, 4), slot_q (M), terms_new_q (M, 4), cells and change cq, hq (2M, V). */
static float rows_sample(const Grid *g, int64_t q, int64_t P, int64_t M, const float *terms_q, const int64_t *slot_q,
                         const float *terms_new_q, const float *cache, const float *zc, float half_inv_var,
                         int64_t *cq, float *hq) {
    float u[MAX_K * 3], s[MAX_K];
    for (int64_t j = 0; j < M; ++j) {
        const float *old = terms_q + slot_q[j] * 4, *now = terms_new_q + j * 4;
        for (int c = 0; c < 3; ++c) {
            u[6 * j + c] = old[c];
            u[6 * j + 3 + c] = now[c];
        }
        s[2 * j] = old[3] * -1.0f;
        s[2 * j + 1] = now[3];
    }
    return delta_sample(g, q, P, 2 * M, u, s, cache, zc, half_inv_var, cq, hq);
}

static void rows_range(const Grid *g, int64_t p0, int64_t p1, int64_t P, int64_t K, int64_t M, const float *terms,
                       const int64_t *slot, const float *terms_new, const float *cache, const float *zc,
                       float half_inv_var, float *delta, int64_t *cells, float *change) {
    const int64_t RV = 2 * M * g->V;
    for (int64_t q = p0; q < p1; ++q)
        delta[q] = rows_sample(g, q, P, M, terms + q * K * 4, slot + q * M, terms_new + q * M * 4, cache, zc,
                               half_inv_var, cells + q * RV, change + q * RV);
}

/* The change of the windowed Rician log-likelihood when slot n of each of particles [p0, p1)
 * moves, without a cache (grid.delta.log_likelihood_delta: the MCMC filters' per-target
 * sweeps on the radar): u, s, live as window_range (K slots); slot (B*P) int64 the moved
 * slot; u_new (B*P, 3), s_new (B*P) its new coordinates and amplitude (times existence).
 * Over the old and the new box of slot n: A the other live slots' spreads plus slot n's old
 * spread, A' the same with its new one, each cell's ratio(A') - ratio(A); the new box's cells
 * inside the old box counted once (in the old box). Writes delta (B*P). */
static void move_range(const Grid *g, int64_t p0, int64_t p1, int64_t P, int64_t K, const float *u, const float *s,
                       const uint8_t *live, const int64_t *slot, const float *u_new, const float *s_new,
                       const float *zc, float half_inv_var, float *delta) {
    float prof[MAX_K + 1][3][MAX_W];
    int64_t first[MAX_K + 1][3];
    float cur[MAX_W * MAX_W * MAX_W], prop[MAX_W * MAX_W * MAX_W], Z[MAX_W * MAX_W * MAX_W + 8];
    float once[MAX_W * MAX_W * MAX_W];
    const int64_t V = g->V;
    for (int64_t q = p0; q < p1; ++q) {
        const float *sq = s + q * K;
        const uint8_t *lq = live + q * K;
        const int64_t n = slot[q];
        boxes_of(g, u + q * K * 3, K, first, prof);
        boxes_of(g, u_new + q * 3, 1, first + K, prof + K); /* the new state: index K */
        double total = 0.0;
        const int same = first[n][0] == first[K][0] && first[n][1] == first[K][1] && first[n][2] == first[K][2];
        for (int r = 0; r < 2 - same; ++r) { /* the new box, when it is the old one, adds nothing */
            const int64_t *fj = first[r == 0 ? n : K];
            for (int64_t c = 0; c < V; ++c) { cur[c] = 0.0f; once[c] = 1.0f; }
            for (int64_t k = 0; k < K; ++k)
                if (k != n && lq[k]) add_spread(g, fj, first[k], prof[k], sq[k], cur, NULL);
            memcpy(prop, cur, (size_t)V * sizeof(float));
            add_spread(g, fj, first[n], prof[n], sq[n], cur, r == 1 ? once : NULL);
            add_spread(g, fj, first[K], prof[K], s_new[q], prop, NULL);
            box_cells_of(g, zc + (q / P) * (g->G + 8), fj, Z, NULL, NULL, 0, NULL);
            float acc = 0.0f;
#pragma omp simd reduction(+ : acc)
            for (int64_t c = 0; c < V; ++c) {
                const float d = cell_ratio(prop[c], Z[c], half_inv_var) - cell_ratio(cur[c], Z[c], half_inv_var);
                acc += once[c] != 0.0f ? d : 0.0f;
            }
            total += (double)acc;
        }
        delta[q] = (float)total;
    }
}

/* rician_window_loglik, rician_delta_cached: window_range, delta_range over n = B*P samples;
 * shape N0 N1 N2 W0 W1 W2, geo the axes' (origin, cell size, 1/(sqrt2 width)), window the
 * box half-width, half_inv_var 1 / (2 sigma^2). Return 0, or 1 when K (R) or a box exceeds
 * the static buffers (the caller checks first). */
int rician_window_loglik(int64_t n, int64_t threads, int64_t P, int64_t K, const float *u, const float *s,
                         const uint8_t *live, const float *zc, const int64_t *shape, const double *geo,
                         int64_t window, double half_inv_var, float *out) {
    Grid g;
    if (K > MAX_K || grid_of(&g, shape, geo, window)) return 1;
    SPLIT(n, threads, window_range(&g, lo, hi, P, K, u, s, live, zc, (float)half_inv_var, out))
    return 0;
}

int rician_delta_cached(int64_t n, int64_t threads, int64_t P, int64_t R, const float *u, const float *s,
                        const float *cache, const float *zc, const int64_t *shape, const double *geo,
                        int64_t window, double half_inv_var, float *delta, int64_t *cells, float *change) {
    Grid g;
    if (R > MAX_K || grid_of(&g, shape, geo, window)) return 1;
    SPLIT(n, threads, delta_range(&g, lo, hi, P, R, u, s, cache, zc, (float)half_inv_var, delta, cells, change))
    return 0;
}

int rician_delta_rows(int64_t n, int64_t threads, int64_t P, int64_t K, int64_t M, const float *terms,
                      const int64_t *slot, const float *terms_new, const float *cache, const float *zc,
                      const int64_t *shape, const double *geo, int64_t window, double half_inv_var, float *delta,
                      int64_t *cells, float *change) {
    Grid g;
    if (2 * M > MAX_K || grid_of(&g, shape, geo, window)) return 1;
    SPLIT(n, threads, rows_range(&g, lo, hi, P, K, M, terms, slot, terms_new, cache, zc, (float)half_inv_var, delta,
                                 cells, change))
    return 0;
}

int rician_move(int64_t n, int64_t threads, int64_t P, int64_t K, const float *u, const float *s, const uint8_t *live,
                const int64_t *slot, const float *u_new, const float *s_new, const float *zc, const int64_t *shape,
                const double *geo, int64_t window, double half_inv_var, float *delta) {
    Grid g;
    if (K > MAX_K || grid_of(&g, shape, geo, window)) return 1;
    SPLIT(n, threads, move_range(&g, lo, hi, P, K, u, s, live, slot, u_new, s_new, zc, (float)half_inv_var, delta))
    return 0;
}

/* the floor's boxes split likewise; returns the sum (in each part's order, added in part order) */
double rician_floor(int64_t boxes, int64_t threads, int64_t V, const float *amp, const float *prof, const float *zc,
                    double half_inv_var) {
    double parts[256] = { 0.0 };
    const int64_t T = threads < 1 ? 1 : (threads > 256 ? 256 : threads);
    SPLIT(boxes, T, parts[part] = floor_range(hi - lo, V, amp + lo, prof, zc, half_inv_var))
    double total = 0.0;
    for (int64_t t = 0; t < T; ++t) total += parts[t];
    return total;
}

/* rows_sample for a caller's own loop (the exchange segment's, exchange.c): a context made
 * once per frame by rician_rows_context (the grid, P samples a frame, the prepared frames zc,
 * 1 / (2 sigma^2); rician_rows_context_size bytes) and the call for sample q, whose result is
 * rician_delta_rows' for that sample to the bit. */
typedef struct {
    Grid g;
    int64_t P;
    const float *zc;
    float half_inv_var;
} RowsContext;

int64_t rician_rows_context_size(void) { return (int64_t)sizeof(RowsContext); }

int rician_rows_context(void *ctx, int64_t P, const float *zc, const int64_t *shape, const double *geo,
                        int64_t window, double half_inv_var) {
    RowsContext *c = (RowsContext *)ctx;
    if (grid_of(&c->g, shape, geo, window)) return 1;
    c->P = P;
    c->zc = zc;
    c->half_inv_var = (float)half_inv_var;
    return 0;
}

float rician_rows_one(const void *ctx, int64_t q, int64_t M, const float *terms_q, const int64_t *slot_q,
                      const float *terms_new_q, const float *cache, int64_t *cq, float *hq) {
    const RowsContext *c = (const RowsContext *)ctx;
    return rows_sample(&c->g, q, c->P, M, terms_q, slot_q, terms_new_q, cache, c->zc, c->half_inv_var, cq, hq);
}
