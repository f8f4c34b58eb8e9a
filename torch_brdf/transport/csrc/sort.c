/* Stable sorts of packed keys with their arrival index (kernel.h: item, item64): an LSD radix
 * sort by 11-bit digits and a merge of sorted runs, both stable, so equal keys keep their arrival
 * order and the per-key sums that follow add their entries in that order (as torch's index_add_). */
#include "kernel.h"

/* stable LSD radix sort of x (n items, keys of `total` bits) by 11-bit digits, y scratch;
 * the sorted items end in *out (x or y) */
#define RADIX_SORT(ITEM, x, y, n, total, cnt, out)                                  \
    do {                                                                            \
        for (int shift = 0; shift < (total); shift += 11) {                         \
            memset(cnt, 0, sizeof(int64_t) * 2048);                                 \
            for (int64_t i = 0; i < n; i++) cnt[(uint64_t)(x[i].k >> shift) & 2047]++; \
            if (cnt[(uint64_t)(x[0].k >> shift) & 2047] == n) continue;             \
            for (int64_t d = 0, sum = 0; d < 2048; d++) {                           \
                int64_t c = cnt[d];                                                 \
                cnt[d] = sum, sum += c;                                             \
            }                                                                       \
            for (int64_t i = 0; i < n; i++) y[cnt[(uint64_t)(x[i].k >> shift) & 2047]++] = x[i]; \
            ITEM *t = x;                                                            \
            x = y, y = t;                                                           \
        }                                                                           \
        out = x;                                                                    \
    } while (0)

/* stable merge of the sorted runs at[0..runs) (the last ends at n) of x into sorted order, y scratch (pairs
 * of adjacent runs, left first on equal keys, until one run is left); the result in *out */
#define RUN_MERGE(ITEM, x, y, n, at, runs, out)                                              \
    do {                                                                                  \
        int64_t nr = (runs);                                                              \
        while (nr > 1) {                                                                  \
            int64_t w = 0;                                                                \
            for (int64_t r = 0; r < nr; r += 2) {                                         \
                int64_t a0 = at[r], a1 = r + 1 < nr ? at[r + 1] : (n), b1 = r + 2 < nr ? at[r + 2] : (n); \
                int64_t i = a0, j = a1, mo = a0;                                          \
                while (i < a1 && j < b1) y[mo++] = x[j].k < x[i].k ? x[j++] : x[i++];     \
                while (i < a1) y[mo++] = x[i++];                                          \
                while (j < b1) y[mo++] = x[j++];                                          \
                at[w++] = a0;                                                             \
            }                                                                             \
            nr = w;                                                                       \
            ITEM *t = x;                                                                  \
            x = y, y = t;                                                                 \
        }                                                                                 \
        out = x;                                                                          \
    } while (0)

/* the sorts and merges as functions: one copy of each loop per item type (a smaller, faster build) */
item64 *sort64(item64 *x, item64 *y, int64_t n, int total, int64_t *cnt) {
    item64 *out;
    RADIX_SORT(item64, x, y, n, total, cnt, out);
    return out;
}
item *sort128(item *x, item *y, int64_t n, int total, int64_t *cnt) {
    item *out;
    RADIX_SORT(item, x, y, n, total, cnt, out);
    return out;
}
item64 *merge64(item64 *x, item64 *y, int64_t n, int64_t *at, int64_t runs) {
    item64 *out;
    RUN_MERGE(item64, x, y, n, at, runs, out);
    return out;
}
item *merge128(item *x, item *y, int64_t n, int64_t *at, int64_t runs) {
    item *out;
    RUN_MERGE(item, x, y, n, at, runs, out);
    return out;
}
