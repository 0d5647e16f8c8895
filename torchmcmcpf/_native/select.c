/* Selects (torch.where) and the read-back of a packed block, one pass each.
 *
 * ATen's CPU where runs a scalar loop per element whatever the layout: 1.2-2.5 ns an element
 * on one core where a copy costs 0.08, and 2.3 ns when the condition is broadcast over an
 * inner dim (a chain's accept flag over its (K, D) state), which the MCMC moves do dozens of
 * times an iteration. Here a row's condition is a bit mask and the row is copied as
 * (a & m) | (b & ~m) on unsigned words of the element's size: the same bits as where (NaN,
 * -0.0 and all), vectorised by the compiler.
 *
 * Layout: `rows` rows of `w` elements of `size` bytes; the condition one byte a row; each
 * operand's row stride (in elements) `w` (a full operand) or 0 (one row repeated). */
#include <stdint.h>

#include "split.h"

#define FLAT(T, A, B)                                                                                       \
    for (int64_t r = lo; r < hi; ++r) {                                                                     \
        const T m = (T)0 - (T)(c[r] != 0);                                                                  \
        out[r] = ((A) & m) | ((B) & (T)~m);                                                                 \
    }

#define ROWS(T, W)                                                                                          \
    for (int64_t r = lo; r < hi; ++r) {                                                                     \
        const T m = (T)0 - (T)(c[r] != 0);                                                                  \
        const T *ar = a + r * ars, *br = b + r * brs;                                                       \
        T *o = out + r * (W);                                                                               \
        for (int64_t j = 0; j < (W); ++j) o[j] = (ar[j] & m) | (br[j] & (T)~m);                             \
    }

/* the run i / P counted, not divided; both sources read (place is 0, inside the block, where not
 * flagged) and combined by the mask: a select, not a mispredicted branch */
#define UNPACK(T, W_)                                                                                       \
    {                                                                                                       \
        int64_t end = (lo / P + 1) * P;                                                                     \
        const T *blk = block + (lo / P) * W * (W_);                                                         \
        for (int64_t i = lo; i < hi; ++i) {                                                                 \
            if (i == end) {                                                                                 \
                end += P;                                                                                   \
                blk += W * (W_);                                                                            \
            }                                                                                               \
            const T m = (T)0 - (T)(flag[i] != 0);                                                           \
            const T *s = blk + place[i] * (W_), *f = fill + i * frs;                                        \
            T *o = out + i * (W_);                                                                          \
            for (int64_t j = 0; j < (W_); ++j) o[j] = (s[j] & m) | (f[j] & (T)~m);                          \
        }                                                                                                   \
    }

#define SELECT_RANGE(T)                                                                                     \
    static void select_##T(int64_t lo, int64_t hi, int64_t w, const uint8_t *restrict c,                    \
                           const T *restrict a, int64_t ars, const T *restrict b, int64_t brs,              \
                           T *restrict out) {                                                               \
        if (w == 1) { /* one element a row: unit or zero strides, each loop vectorised */                  \
            if (ars && brs) FLAT(T, a[r], b[r])                                                             \
            else if (ars) FLAT(T, a[r], b[0])                                                               \
            else if (brs) FLAT(T, a[0], b[r])                                                               \
            else FLAT(T, a[0], b[0])                                                                        \
            return;                                                                                         \
        }                                                                                                   \
        switch (w) { /* a short row's length known to the compiler: its rows vectorised together */       \
        case 2: ROWS(T, 2) return;                                                                          \
        case 3: ROWS(T, 3) return;                                                                          \
        case 4: ROWS(T, 4) return;                                                                          \
        default: ROWS(T, w) return;                                                                         \
        }                                                                                                   \
    }                                                                                                       \
    /* unpack: out[i] = flag[i] ? block[i / P, place[i]] : fill[i * frs], rows of w elements;              \
     * block (B, W, w) */                                                                                   \
    static void unpack_##T(int64_t lo, int64_t hi, int64_t P, int64_t W, int64_t w,                          \
                           const uint8_t *restrict flag, const int64_t *restrict place,                     \
                           const T *restrict block, const T *restrict fill, int64_t frs, T *restrict out) { \
        switch (w) {                                                                                        \
        case 1: UNPACK(T, 1) return;                                                                        \
        case 2: UNPACK(T, 2) return;                                                                        \
        case 4: UNPACK(T, 4) return;                                                                        \
        default: UNPACK(T, w) return;                                                                       \
        }                                                                                                   \
    }

SELECT_RANGE(uint8_t)
SELECT_RANGE(uint16_t)
SELECT_RANGE(uint32_t)
SELECT_RANGE(uint64_t)

/* select_rows: out (rows, w) = c ? a : b row by row, elements of `size` bytes (1, 2, 4, 8);
 * 1 for another size */
int select_rows(int64_t rows, int64_t threads, int64_t w, int64_t size, const uint8_t *c, const void *a,
                int64_t ars, const void *b, int64_t brs, void *out) {
    switch (size) {
    case 1: SPLIT(rows, threads, select_uint8_t(lo, hi, w, c, a, ars, b, brs, out)) return 0;
    case 2: SPLIT(rows, threads, select_uint16_t(lo, hi, w, c, a, ars, b, brs, out)) return 0;
    case 4: SPLIT(rows, threads, select_uint32_t(lo, hi, w, c, a, ars, b, brs, out)) return 0;
    case 8: SPLIT(rows, threads, select_uint64_t(lo, hi, w, c, a, ars, b, brs, out)) return 0;
    default: return 1;
    }
}

/* unpack_rows: out (B * P, w) = flag ? block (B, W, w)[i / P, place] : fill (row stride frs, w or 0);
 * place within [0, W) everywhere (W > 0; packed_places gives 0 where not flagged); 1 for another size */
int unpack_rows(int64_t n, int64_t threads, int64_t P, int64_t W, int64_t w, int64_t size, const uint8_t *flag,
                const int64_t *place, const void *block, const void *fill, int64_t frs, void *out) {
    switch (size) {
    case 1: SPLIT(n, threads, unpack_uint8_t(lo, hi, P, W, w, flag, place, block, fill, frs, out)) return 0;
    case 2: SPLIT(n, threads, unpack_uint16_t(lo, hi, P, W, w, flag, place, block, fill, frs, out)) return 0;
    case 4: SPLIT(n, threads, unpack_uint32_t(lo, hi, P, W, w, flag, place, block, fill, frs, out)) return 0;
    case 8: SPLIT(n, threads, unpack_uint64_t(lo, hi, P, W, w, flag, place, block, fill, frs, out)) return 0;
    default: return 1;
    }
}
