/* The exclusion factor and its change when one slot moves (torchmcmcpf.models.multitarget.Exclusion,
 * Khan, Balch and Dellaert 2005: phi(d) = 1 - exp(-d^2 / (2 s^2)), log phi floored): the K - 1
 * pairs of the moved slot before and after (or a state's K (K - 1) / 2 pairs), in float64, with
 * no (S, 2, K) tensor and none of the thirty small ATen calls a move made on tensors; the pairs
 * of a block of samples gathered, their log phi vectorised, each sample's summed in order.
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>

#include "exclusion.h"
#include "split.h"

int exclusion_change(int64_t n, int64_t threads, int64_t K, int64_t r, const double *u, const double *u_n,
                     const int64_t *slot, const uint8_t *alive, const uint8_t *alive_n, double inv2s2, double xmin,
                     double *out) {
    SPLIT(n, threads, change_range(lo, hi, K, r, u, u_n, slot, alive, alive_n, inv2s2, xmin, out))
    return 0;
}

/* exclusion_factor: out (n) = sum over the pairs k < l of live slots of log phi(|u_k - u_l|^2),
 * u (n, K, r), alive (n, K) uint8 (NULL: all live) */
static void factor_range(int64_t i0, int64_t i1, int64_t K, int64_t r, const double *u, const uint8_t *alive,
                         double inv2s2, double xmin, double *out) {
    double buf[BUFFER], lp[BUFFER];
    int64_t start[BUFFER + 1];
    const int64_t pairs = K * (K - 1) / 2;
    const int64_t block = pairs > 0 && BUFFER / pairs > 0 ? BUFFER / pairs : 1;
    for (int64_t b0 = i0; b0 < i1; b0 += block) {
        const int64_t b1 = b0 + block < i1 ? b0 + block : i1;
        int64_t m = 0;
        for (int64_t i = b0; i < b1; ++i) {
            const double *ui = u + i * K * r;
            start[i - b0] = m;
            for (int64_t k = 0; k < K; ++k) {
                if (alive != NULL && !alive[i * K + k]) continue;
                for (int64_t l = k + 1; l < K; ++l) {
                    if (alive != NULL && !alive[i * K + l]) continue;
                    double d2 = 0.0;
                    for (int64_t c = 0; c < r; ++c) {
                        const double a = ui[k * r + c] - ui[l * r + c];
                        d2 += a * a;
                    }
                    buf[m++] = scaled(d2, inv2s2, xmin);
                }
            }
        }
        start[b1 - b0] = m;
        log_phi_buffer(m, buf, lp);
        for (int64_t i = b0; i < b1; ++i) { /* the sample's live pairs, in the order gathered */
            double acc = 0.0;
            for (int64_t q = start[i - b0]; q < start[i - b0 + 1]; ++q) acc += lp[q];
            out[i] = acc;
        }
    }
}

int exclusion_factor(int64_t n, int64_t threads, int64_t K, int64_t r, const double *u, const uint8_t *alive,
                     double inv2s2, double xmin, double *out) {
    SPLIT(n, threads, factor_range(lo, hi, K, r, u, alive, inv2s2, xmin, out))
    return 0;
}

/* log phi on n squared distances (the loops' own log_phi_buffer), for its test */
void exclusion_log_phi(int64_t n, const double *d2, double inv2s2, double xmin, double *out) {
    double x[BUFFER];
    for (int64_t i0 = 0; i0 < n; i0 += BUFFER) {
        const int64_t m = n - i0 < BUFFER ? n - i0 : BUFFER;
        for (int64_t i = 0; i < m; ++i) x[i] = scaled(d2[i0 + i], inv2s2, xmin);
        log_phi_buffer(m, x, out + i0);
    }
}
