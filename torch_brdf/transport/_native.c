/* The entries of the multibounce precomputation, made and summed per key (torch_brdf).
 *
 * The compiled twin of the tracer's _Tracer._emit + _Entries (tracer.py) and of reduce.py's
 * _reduce: each light sample at a vertex adds, per layer combination (a, b), one entry with
 * weight ((base * X[a]) * Y[b]) (float32, in that order, as the torch path multiplies) and key
 * (record, eye object, bounce, j, w, per-object counts, path); a pass group's entries are then
 * summed per key in float64 in the order they were made (as torch's index_add_ sums them).
 *
 * A key is packed into one 128-bit integer field by field (record most significant, path least;
 * the widths come from the caller), so integer order is reduce.py's radix-key order. The sums
 * come from a stable LSD radix sort of (key, arrival index) and one pass over the sorted keys,
 * so each key's sum adds its entries in arrival order: the output equals the torch path bit
 * for bit. The count digits are packed last object most significant, the order of
 * _multiset_ids' base-(max + 1) code; when that code would not fit in 62 bits, torch numbers
 * multisets with unique(dim=0) (first object first) and the keys are repacked before sorting.
 *
 * Built on first use by _native.py with the system C compiler (-O3 -ffp-contract=off: no fused
 * multiply-add, IEEE float32 products as in torch; -fno-math-errno -fno-trapping-math only let
 * sqrtf inline and selects replace branches, the values stay IEEE's) and called through ctypes.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* Loops of the sampling side written to vectorise (branch-free passes over arrays)
 * are built twice, for AVX2 and for the baseline x86-64 (SSE2), and the loader picks the copy
 * the CPU can run (GCC's target_clones: an ifunc resolved once). The two copies do the same
 * IEEE operations in the same order (no FMA: -ffp-contract=off), so they give the same bits:
 * the result does not depend on the CPU. Other compilers and CPUs: one plain copy. */
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__)
#define TB_SIMD __attribute__((target_clones("avx2", "default")))
#else
#define TB_SIMD
#endif

typedef unsigned __int128 u128;

enum { F_REC, F_OBJ, F_BOUNCE, F_J, F_W, NFIXED };

typedef struct {
    int M, V;                 /* objects (count digits), float64 values per entry */
    int bits[NFIXED], bc, bp; /* field widths: fixed fields, one count digit, path (0: none) */
    int total;                /* bits of a key (<= 127) */
    int64_t n, room;          /* entries, capacity */
    u128 *key;                /* room */
    double *val;              /* room * V */
    int max_count;
    /* sorted runs (tb_reduce_into appends one per call, in its key order): starts of nruns runs
     * (-1: the entries are not such runs), their order (forward) */
    int64_t *run_at;
    int nruns, run_room, run_fwd;
    void *scratch; /* the sorts' item arrays, kept for the next reduction (no fresh pages per call) */
    size_t scratch_bytes;
    void *samples; /* tb_emit's per-sample rows, kept for the next call (likewise) */
    int64_t samples_room;
} tb_acc;

static u128 field_mask(int b) { return (((u128)1) << b) - 1; }

/* bits: widths of rec, obj, bounce, j, w + 1, one count digit, path (0: no path field) */
tb_acc *tb_new(int M, int V, const int32_t *bits) {
    tb_acc *a = (tb_acc *)calloc(1, sizeof(tb_acc));
    if (!a) return NULL;
    a->M = M, a->V = V, a->bc = bits[NFIXED], a->bp = bits[NFIXED + 1];
    a->total = M * a->bc + a->bp;
    for (int f = 0; f < NFIXED; f++) a->bits[f] = bits[f], a->total += bits[f];
    a->room = 1 << 14;
    a->key = (u128 *)malloc(sizeof(u128) * a->room);
    a->val = (double *)malloc(sizeof(double) * a->room * V);
    if (a->total > 127 || !a->key || !a->val) {
        free(a->key), free(a->val), free(a);
        return NULL;
    }
    return a;
}

void tb_free(tb_acc *a) {
    if (!a) return;
    free(a->key), free(a->val), free(a->run_at), free(a->scratch), free(a->samples), free(a);
}

/* Empty the accumulator for reuse (its memory kept). */
void tb_clear(tb_acc *a) { a->n = 0, a->max_count = 0, a->nruns = 0; }

int64_t tb_size(const tb_acc *a) { return a->n; }
int tb_max_count(const tb_acc *a) { return a->max_count; }

static int reserve(tb_acc *a, int64_t more) {
    if (a->n + more <= a->room) return 0;
    int64_t room = a->room;
    while (room < a->n + more) room *= 2;
    u128 *k = (u128 *)realloc(a->key, sizeof(u128) * room);
    if (!k) return -1;
    a->key = k;
    double *v = (double *)realloc(a->val, sizeof(double) * room * a->V);
    if (!v) return -1;
    a->val = v, a->room = room;
    return 0;
}

/* the packed key; -1 into *bad when a field does not fit its width */
static u128 pack(tb_acc *a, const int64_t *f, const int8_t *cnt, int64_t inc, int64_t path, int *bad) {
    u128 k = 0;
    for (int d = 0; d < NFIXED; d++) {
        if (f[d] < 0 || ((uint64_t)f[d] >> a->bits[d])) *bad = 1;
        k = (k << a->bits[d]) | (u128)((uint64_t)f[d] & (uint64_t)field_mask(a->bits[d]));
    }
    for (int m = a->M - 1; m >= 0; m--) { /* last object most significant (the code's order) */
        int c = cnt[m] + (m == inc);
        if (c < 0 || ((unsigned)c >> a->bc)) *bad = 1;
        if (c > a->max_count) a->max_count = c;
        k = (k << a->bc) | (u128)((unsigned)c & (unsigned)field_mask(a->bc));
    }
    if (a->bp) {
        if (path < 0 || ((uint64_t)path >> a->bp)) *bad = 1;
        k = (k << a->bp) | (u128)((uint64_t)path & (uint64_t)field_mask(a->bp));
    }
    return k;
}

/* Add n rows of sums: keys rec, obj, bounce, j, w (n,) int64 and counts (n, M) int8 (no path),
 * values wd (n, V) float64. Returns 0; -1 out of memory; -2 a field does not fit its width. */
int tb_add_sums(tb_acc *a, int64_t n, const int64_t *rec, const int64_t *obj, const int64_t *bounce,
                const int64_t *j, const int64_t *w, const int8_t *counts, const double *wd) {
    int bad = 0;
    if (reserve(a, n)) return -1;
    if (n) a->nruns = -1;
    for (int64_t i = 0; i < n; i++) {
        int64_t f[NFIXED] = {rec[i], obj[i], bounce[i], j[i], w[i] + 1};
        a->key[a->n] = pack(a, f, counts + i * a->M, -1, 0, &bad);
        memcpy(a->val + a->n * a->V, wd + i * a->V, sizeof(double) * a->V);
        a->n++;
    }
    return bad ? -2 : 0;
}

/* The entries of n light samples at vertex `bounce` (the tracer's _emit), in its order: layer
 * combination (a, b) major, sample i minor. Per sample i (path row r = kk[i] of the path state):
 *   base = raw[r] * lw[i] (lw[i] when raw is NULL), then * f[i] when f, then * scale[e] when scale, e = sum(counts[r]);
 *   entry (a, b): weight (base * X[a]) * Y[b] with X[a] = xw[(r or i), a] (x_rows: rows r) and
 *   Y[b] = yw[(r or i), b] (y_rows), 1 when yw is NULL (then Lb = 1);
 *   key: rec = ray % p, path = ray / p with ray = rec[idx[r]]; obj = m1[r]; j = xi[., a];
 *   w = yi[., b] (-1 when yi is NULL); counts = counts[r] plus one at object ob[i] when ed[i].
 * Rows with a NaN or all-zero weight are dropped (as _Entries.add drops them).
 * Shapes: raw (N, 3), idx, m1 (N,), counts (N, M) int8, rec (rays,); kk, ob (n,) int64, ed (n,) uint8
 * (or NULL), lw, f (n, 3) float32; xi (., La) int64, xw (., La, 3); yi (., Lb), yw (., Lb, 3).
 * Returns 0; -1 out of memory; -2 a field does not fit its width. */
/* a field value masked to its width; *bad when it does not fit (as pack) */
static u128 fit(int64_t v, int b, int *bad) {
    if (v < 0 || ((uint64_t)v >> b)) *bad = 1;
    return (u128)((uint64_t)v & (uint64_t)field_mask(b));
}

int tb_emit(tb_acc *a, int64_t n, int64_t bounce, int64_t p, const int64_t *kk, const float *raw, const int64_t *idx,
            const int64_t *rec, const int64_t *m1, const int8_t *counts, const int64_t *ob, const uint8_t *ed, const float *lw,
            const float *f, const float *scale, int64_t nscale, int64_t La, const int64_t *xi, const float *xw,
            int x_rows, int64_t Lb, const int64_t *yi, const float *yw, int y_rows) {
    int M = a->M, bad = 0;
    /* per sample: its weight base, the key's fields above j (rec, obj, bounce) and below w
     * (counts, path), whether they fit and the largest count (pack's, once per sample) */
    typedef struct {
        u128 hi, lo;
        float base[3];
        int bad, maxc;
    } sample;
    if (a->samples_room < n) {
        free(a->samples);
        a->samples = malloc(sizeof(sample) * n), a->samples_room = a->samples ? n : 0;
    }
    sample *sm = (sample *)a->samples;
    if ((n && !sm) || reserve(a, n * La * Lb)) return -1;
    if (n) a->nruns = -1;
    const int low = M * a->bc + a->bp;
    for (int64_t i = 0; i < n; i++) {
        int64_t r = kk[i];
        sample *q = sm + i;
        for (int c = 0; c < 3; c++) {
            float v = raw ? raw[3 * r + c] * lw[3 * i + c] : lw[3 * i + c];
            if (f) v = v * f[3 * i + c];
            q->base[c] = v;
        }
        if (scale) {
            int64_t e = 0;
            for (int m = 0; m < M; m++) e += counts[r * M + m];
            if (e < 0 || e >= nscale) return -2;
            for (int c = 0; c < 3; c++) q->base[c] = q->base[c] * scale[e];
        }
        int64_t ray = rec[idx[r]];
        int b = 0, inc = (ed && ed[i]) ? (int)ob[i] : -1, mx = 0;
        q->hi = (((fit(ray % p, a->bits[F_REC], &b) << a->bits[F_OBJ]) | fit(m1[r], a->bits[F_OBJ], &b))
                 << a->bits[F_BOUNCE]) | fit(bounce, a->bits[F_BOUNCE], &b);
        u128 lo = 0;
        for (int m = M - 1; m >= 0; m--) { /* last object most significant (the code's order) */
            int c = counts[r * M + m] + (m == inc);
            if (c < 0 || ((unsigned)c >> a->bc)) b = 1;
            if (c > mx) mx = c;
            lo = (lo << a->bc) | (u128)((unsigned)c & (unsigned)field_mask(a->bc));
        }
        q->lo = a->bp ? (lo << a->bp) | fit(ray / p, a->bp, &b) : lo;
        q->bad = b, q->maxc = mx;
    }
    const int bj = a->bits[F_J], bw = a->bits[F_W];
    for (int64_t ia = 0; ia < La; ia++)
        for (int64_t ib = 0; ib < Lb; ib++)
            for (int64_t i = 0; i < n; i++) {
                int64_t r = kk[i], rx = x_rows ? r : i, ry = y_rows ? r : i;
                const float *x = xw + (rx * La + ia) * 3;
                const sample *q = sm + i;
                float w3[3];
                for (int c = 0; c < 3; c++) {
                    float v = q->base[c] * x[c];
                    w3[c] = yw ? v * yw[(ry * Lb + ib) * 3 + c] : v;
                }
                if (w3[0] != w3[0] || w3[1] != w3[1] || w3[2] != w3[2]) continue;
                if (!(w3[0] != 0.0f || w3[1] != 0.0f || w3[2] != 0.0f)) continue;
                u128 k = (q->hi << bj) | fit(xi[rx * La + ia], bj, &bad);
                k = (k << bw) | fit(yi ? yi[ry * Lb + ib] + 1 : 0, bw, &bad);
                a->key[a->n] = (k << low) | q->lo;
                bad |= q->bad;
                if (q->maxc > a->max_count) a->max_count = q->maxc;
                double *v = a->val + a->n * a->V;
                for (int c = 0; c < 3; c++) v[c] = (double)w3[c];
                a->n++;
            }
    return bad ? -2 : 0;
}

typedef struct {
    u128 k;
    int64_t s;
} item; /* a key and its arrival index */

typedef struct {
    uint64_t k;
    int64_t s;
} item64; /* the same for keys of at most 64 bits (half the bytes to move) */

/* the key with its count digits in the other order (first object most significant) */
static u128 forward_key(const tb_acc *a, u128 k) {
    int M = a->M, bc = a->bc, bp = a->bp;
    u128 path = bp ? k & field_mask(bp) : 0, out = k >> (bp + M * bc);
    for (int m = 0; m < M; m++) out = (out << bc) | ((k >> (bp + m * bc)) & field_mask(bc));
    return bp ? (out << bp) | path : out;
}

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
static item64 *sort64(item64 *x, item64 *y, int64_t n, int total, int64_t *cnt) {
    item64 *out;
    RADIX_SORT(item64, x, y, n, total, cnt, out);
    return out;
}
static item *sort128(item *x, item *y, int64_t n, int total, int64_t *cnt) {
    item *out;
    RADIX_SORT(item, x, y, n, total, cnt, out);
    return out;
}
static item64 *merge64(item64 *x, item64 *y, int64_t n, int64_t *at, int64_t runs) {
    item64 *out;
    RUN_MERGE(item64, x, y, n, at, runs, out);
    return out;
}
static item *merge128(item *x, item *y, int64_t n, int64_t *at, int64_t runs) {
    item *out;
    RUN_MERGE(item, x, y, n, at, runs, out);
    return out;
}

/* Sum the entries per key: *u distinct keys in ascending order (count digits compared last
 * object first, or first object first when forward) into fields_out (n, 5 + M) int64 (rec,
 * obj, bounce, j, w, counts) and sums_out (n, V) float64 (first *u rows; room for n). Each
 * sum adds its entries in arrival order, starting from 0.0. Returns 0 or -1 (out of memory). */
static int reduce_impl(tb_acc *a, int forward, int64_t *fields_out, double *sums_out, int64_t *u, tb_acc *into) {
    int64_t n = a->n, o = 0;
    if (into && (into->V != 2 * a->V || reserve(into, n))) return -1;
    if (into && into->nruns >= 0 && n) { /* this call's output is one more sorted run of into */
        if (into->nruns == into->run_room) {
            int room = into->run_room ? 2 * into->run_room : 16;
            int64_t *r = (int64_t *)realloc(into->run_at, sizeof(int64_t) * room);
            if (!r) return -1;
            into->run_at = r, into->run_room = room;
        }
        if (into->nruns && into->run_fwd != forward) into->nruns = -1;
        else into->run_at[into->nruns++] = into->n, into->run_fwd = forward;
    }
    int small = a->total <= 64;
    size_t isz = small ? sizeof(item64) : sizeof(item);
    size_t need = 2 * isz * (n ? n : 1);
    if (a->scratch_bytes < need) {
        free(a->scratch);
        a->scratch = malloc(need), a->scratch_bytes = a->scratch ? need : 0;
    }
    void *xv = a->scratch, *yv = xv ? (char *)xv + isz * (n ? n : 1) : NULL;
    int64_t cnt[2048];
    if (!xv) return -1;
    item *xw = (item *)xv, *yw = (item *)yv, *sw = NULL;
    item64 *xs = (item64 *)xv, *ys = (item64 *)yv, *ss = NULL;
    for (int64_t i = 0; i < n; i++) {
        u128 k = forward ? forward_key(a, a->key[i]) : a->key[i];
        if (small)
            xs[i].k = (uint64_t)k, xs[i].s = i;
        else
            xw[i].k = k, xw[i].s = i;
    }
    /* runs appended by tb_reduce_into in this order: merge them (the same stable order) */
    int64_t *starts = NULL;
    if (n && a->nruns > 0 && a->run_fwd == forward && (starts = (int64_t *)malloc(sizeof(int64_t) * a->nruns))) {
        memcpy(starts, a->run_at, sizeof(int64_t) * a->nruns);
        if (small)
            ss = merge64(xs, ys, n, starts, a->nruns);
        else
            sw = merge128(xw, yw, n, starts, a->nruns);
        free(starts);
    } else if (n && small)
        ss = sort64(xs, ys, n, a->total, cnt);
    else if (n)
        sw = sort128(xw, yw, n, a->total, cnt);
    int M = a->M, K = NFIXED + M, V = a->V, narrow = a->total - a->bp <= 64;
    int sh[NFIXED + 256];
    uint64_t mk[NFIXED + 256];
    for (int m = 0, at = 0; m < M; m++, at += a->bc) sh[NFIXED + m] = at, mk[NFIXED + m] = ((uint64_t)1 << a->bc) - 1;
    for (int d = NFIXED - 1, at = M * a->bc; d >= 0; at += a->bits[d], d--)
        sh[d] = at, mk[d] = a->bits[d] >= 64 ? ~(uint64_t)0 : ((uint64_t)1 << a->bits[d]) - 1;
    if (M > 256) narrow = 0;
    for (int64_t i = 0; i < n; i++) {
        int64_t si = small ? ss[i].s : sw[i].s;
        if (i + 16 < n) __builtin_prefetch(a->val + (small ? ss[i + 16].s : sw[i + 16].s) * V);
        int fresh = i == 0 || (small ? ss[i].k != ss[i - 1].k : sw[i].k != sw[i - 1].k);
        if (fresh && into) { /* the key without its path field, sums then squares */
            into->key[into->n + o] = (forward ? a->key[si] : (small ? (u128)ss[i].k : sw[i].k)) >> a->bp;
            memset(into->val + (into->n + o) * 2 * V, 0, sizeof(double) * V);
            o++;
        } else if (fresh) {
            u128 k = (forward ? a->key[si] : (small ? (u128)ss[i].k : sw[i].k)) >> a->bp;
            int64_t *row = fields_out + o * K;
            if (narrow) { /* the fields in one 64-bit word: fixed shifts */
                uint64_t k64 = (uint64_t)k;
                for (int d = 0; d < K; d++) row[d] = (int64_t)((k64 >> sh[d]) & mk[d]);
            } else {
                for (int m = 0; m < M; m++, k >>= a->bc) row[NFIXED + m] = (int64_t)(k & field_mask(a->bc));
                for (int d = NFIXED - 1; d >= 0; d--) {
                    row[d] = (int64_t)(k & field_mask(a->bits[d]));
                    k >>= a->bits[d];
                }
            }
            row[F_W] -= 1;
            memset(sums_out + o * V, 0, sizeof(double) * V);
            o++;
        }
        double *s = into ? into->val + (into->n + o - 1) * 2 * V : sums_out + (o - 1) * V;
        const double *v = a->val + si * V;
        for (int c = 0; c < V; c++) s[c] += v[c];
    }
    if (into) {
        for (int64_t r = into->n; r < into->n + o; r++)
            for (int c = 0; c < V; c++) into->val[r * 2 * V + V + c] = into->val[r * 2 * V + c] * into->val[r * 2 * V + c];
        into->n += o;
        if (a->max_count > into->max_count) into->max_count = a->max_count;
    }
    *u = o;
    return 0;
}

int tb_reduce(tb_acc *a, int forward, int64_t *fields_out, double *sums_out, int64_t *u) {
    return reduce_impl(a, forward, fields_out, sums_out, u, NULL);
}

/* tb_reduce's per-key sums s of `a` (V values) appended to `into` (2 V values: s, then s * s)
 * under their key without the path field (into's fields are a's without path), in ascending
 * key order: what tb_add_sums of tb_reduce's output adds, without unpacking the keys. The
 * caller checks that `into` was made with a's widths (path 0). Returns 0 or -1. */
int tb_reduce_into(tb_acc *a, int forward, tb_acc *into) {
    int64_t u = 0;
    if (into->M != a->M || into->bp != 0 || into->total != a->total - a->bp) return -1;
    return reduce_impl(a, forward, NULL, NULL, &u, into);
}

/* ---- A tile's sparse blocks (reduce.py _local_blocks) -----------------------
 * From a tile's per-key sums (tb_reduce's output: fields (U, 5 + M) int64 rec, obj, bounce, j,
 * w, counts and values (U, 6) float64 sum, then sum of per-path squares), per (eye object,
 * bounce) block in ascending (object, bounce) order: the records that occur (upix, ascending),
 * the terms (w, counts) that occur in _local_blocks' order (w, then the multiset in
 * _multiset_ids' order: count digits last object first when that code fits in 62 bits for the
 * block's largest count, else first object first), and the entries in ascending local key
 * (j Z + z) P + p with their mean sum / spp and variance ((sq / spp - mean^2) / max(spp - 1, 1))
 * clamped at 0, in float64 then float32, as torch computes them (so the same bits).
 * bits: widths of rec, obj, bounce, j, w + 1 and one count digit (the tile's key_bits).
 * spp_rec (records,) int64 paths of each record, or NULL: spp for all.
 * Out (capacity U each): key (U,) int64; vals, var (3 U) float32, block after block, each (3, E)
 * row-major; upix (U,) int64 and term_row (U,) int64 (a row of `fields` holding the term),
 * block after block; meta (obj, bounce, E, P, Z) int64 per block (capacity: room blocks).
 * Returns the number of blocks; -1 out of memory; -2 fields too wide (torch does it then). */
static int fits_code(int M, int64_t max_count) {
    double b = (double)(max_count + 1 < 2 ? 2 : max_count + 1);
    return M * log2(b) < 62;
}

int64_t tb_blocks(int64_t U, int M, const int32_t *bits, const int64_t *fields, const double *vals,
                  const int64_t *spp_rec, int64_t spp, int64_t room, int64_t *key, float *mean_out, float *var_out,
                  int64_t *upix, int64_t *term_row, int64_t *meta) {
    const int br = bits[F_REC], bo = bits[F_OBJ], bb = bits[F_BOUNCE], bj = bits[F_J], bw = bits[F_W], bc = bits[NFIXED];
    const int K = NFIXED + M, total = bo + bb + bw + M * bc + bj + br;
    if (bo + bb > 20 || br > 24 || total > 127) return -2;
    const int64_t nblk = (int64_t)1 << (bo + bb), nrec = (int64_t)1 << br;
    int64_t *maxc = (int64_t *)calloc(nblk, sizeof(int64_t));
    int32_t *rank = (int32_t *)malloc(sizeof(int32_t) * nrec);
    item *x = (item *)malloc(sizeof(item) * (U ? U : 1)), *y = (item *)malloc(sizeof(item) * (U ? U : 1)), *sorted;
    item64 *x2 = (item64 *)malloc(sizeof(item64) * (U ? U : 1)), *y2 = (item64 *)malloc(sizeof(item64) * (U ? U : 1));
    int64_t *cnt = (int64_t *)malloc(sizeof(int64_t) * 2048), *fin = (int64_t *)malloc(sizeof(int64_t) * (U ? U : 1));
    int64_t nb = 0;
    if (!maxc || !rank || !x || !y || !x2 || !y2 || !cnt || !fin) {
        nb = -1;
        goto done;
    }
    for (int64_t i = 0; i < U; i++) {
        const int64_t *f = fields + i * K;
        int64_t b = (f[F_OBJ] << bb) | f[F_BOUNCE];
        for (int m = 0; m < M; m++)
            if (f[NFIXED + m] > maxc[b]) maxc[b] = f[NFIXED + m];
    }
    /* order 1: (block, w + 1, multiset, j, rec): each block's terms contiguous and ascending */
    for (int64_t i = 0; i < U; i++) {
        const int64_t *f = fields + i * K;
        int64_t b = (f[F_OBJ] << bb) | f[F_BOUNCE];
        u128 k = ((u128)b << bw) | (u128)(f[F_W] + 1);
        if (fits_code(M, maxc[b]))
            for (int m = M - 1; m >= 0; m--) k = (k << bc) | (u128)f[NFIXED + m];
        else
            for (int m = 0; m < M; m++) k = (k << bc) | (u128)f[NFIXED + m];
        x[i].k = (((k << bj) | (u128)f[F_J]) << br) | (u128)f[F_REC], x[i].s = i;
    }
    sorted = U ? sort128(x, y, U, total, cnt) : x;
    const int tail = bj + br; /* the term is the key without (block) above and (j, rec) below it */
    const u128 term_mask = (((u128)1) << (bw + M * bc)) - 1;
    int64_t at = 0, up = 0;
    for (int64_t i0 = 0; i0 < U;) {
        const int64_t *f0 = fields + sorted[i0].s * K;
        const int64_t b = (f0[F_OBJ] << bb) | f0[F_BOUNCE];
        int64_t i1 = i0;
        while (i1 < U && (int64_t)(sorted[i1].k >> (tail + bw + M * bc)) == b) i1++;
        if (nb >= room) {
            nb = -1;
            goto done;
        }
        /* the block's records, ascending, and their ranks p */
        for (int64_t i = i0; i < i1; i++) rank[fields[sorted[i].s * K + F_REC]] = 1;
        int64_t P = 0;
        for (int64_t i = i0; i < i1; i++) { /* mark-and-count without scanning every record id */
            int64_t r = fields[sorted[i].s * K + F_REC];
            if (rank[r] == 1) rank[r] = -1, P++;
        }
        int64_t *pix = upix + up, np = 0;
        for (int64_t i = i0; i < i1; i++) {
            int64_t r = fields[sorted[i].s * K + F_REC];
            if (rank[r] == -1) pix[np++] = r, rank[r] = 0;
        }
        /* pix holds the distinct records in order of first appearance: sort them (radix) */
        for (int64_t q = 0; q < np; q++) x2[q].k = (uint64_t)pix[q], x2[q].s = q;
        item64 *ps = np ? sort64(x2, y2, np, br, cnt) : x2;
        for (int64_t q = 0; q < np; q++) pix[q] = (int64_t)ps[q].k, rank[pix[q]] = (int32_t)q;
        /* terms: z per row (order 1 is ascending in the term), the final key (j Z + z) P + p */
        int64_t Z = 0;
        u128 prev = 0;
        for (int64_t i = i0; i < i1; i++) {
            u128 t = (sorted[i].k >> tail) & term_mask;
            if (i == i0 || t != prev) term_row[up + Z] = sorted[i].s, Z++, prev = t;
            fin[i] = Z - 1; /* z for now */
        }
        int kbits = 1;
        for (int64_t i = i0; i < i1; i++) {
            const int64_t *f = fields + sorted[i].s * K;
            uint64_t k = (uint64_t)((f[F_J] * Z + fin[i]) * P + rank[f[F_REC]]);
            x2[i - i0].k = k, x2[i - i0].s = sorted[i].s;
            while (kbits < 64 && (k >> kbits)) kbits++;
        }
        const int64_t E = i1 - i0;
        item64 *ks = sort64(x2, y2, E, kbits, cnt);
        float *mo = mean_out + 3 * at, *vo = var_out + 3 * at;
        for (int64_t e = 0; e < E; e++) {
            int64_t r = ks[e].s;
            const double *v = vals + 6 * r;
            int64_t n = spp_rec ? spp_rec[fields[r * K + F_REC]] : spp;
            double dn = (double)n, dof = (double)(n - 1 < 1 ? 1 : n - 1);
            key[at + e] = (int64_t)ks[e].k;
            for (int c = 0; c < 3; c++) {
                double mu = v[c] / dn, q = (v[3 + c] / dn - mu * mu) / dof;
                mo[c * E + e] = (float)mu, vo[c * E + e] = (float)(q < 0 ? 0.0 : q);
            }
        }
        int64_t *mt = meta + 5 * nb;
        mt[0] = f0[F_OBJ], mt[1] = f0[F_BOUNCE], mt[2] = E, mt[3] = P, mt[4] = Z;
        /* term_row and upix share one offset per block: the larger of P and Z */
        for (int64_t q = Z; q < P; q++) term_row[up + q] = -1;
        for (int64_t q = P; q < Z; q++) upix[up + q] = -1;
        up += P > Z ? P : Z, at += E, nb++;
        i0 = i1;
    }
done:
    free(maxc), free(rank), free(x), free(y), free(x2), free(y2), free(cnt), free(fin);
    return nb;
}

/* Next-event samples of an area light from float32 points (scene/lights.py AreaLight.sample_points
 * and AreaLight.sample, then pathtrace.py sample_light's cosines), operation for operation in
 * the torch code's order and precision (float64 points on the triangle, float32 after). The two
 * square roots stay in torch (its vectorised sqrt is not always the correctly rounded one), so
 * the results are the same bit for bit: tb_area_points, then dist = sqrt(d2) in torch, then
 * tb_area_finish.
 * tb_area_points: u (n, 3) float64 uniforms and s = sqrt(u[:, 1]) (n,) float64 (both from torch);
 * cdf (T,) float64; tri (T, 3, 3) float32; points (n, 3) float32 -> d (n, 3) = y - points and
 * d2 (n,) = |d|^2 float32, idx (n,) int64 the triangle. */
/* The triangle (searchsorted(cdf, u0, right=True), clamped) and the point on it at barycentrics
 * (b1, b2) in float64, rounded to float32, less p: into d (3,). Returns the triangle. */
static int64_t area_point(double u0, double b1, double b2, const double *cdf, int64_t T, const float *tri,
                          const float *p, float *d) {
    int64_t a = 0, b = T;
    while (a < b) {
        int64_t m = (a + b) / 2;
        if (cdf[m] <= u0)
            a = m + 1;
        else
            b = m;
    }
    int64_t k = a < T - 1 ? a : T - 1;
    const float *t = tri + 9 * k;
    for (int c = 0; c < 3; c++) {
        double t0 = t[c], t1 = t[3 + c], t2 = t[6 + c];
        float y = (float)((t0 + b1 * (t1 - t0)) + b2 * (t2 - t0));
        d[c] = y - p[c];
    }
    return k;
}

void tb_area_points(int64_t n, const double *u, const double *s, const double *cdf, int64_t T, const float *tri,
                    const float *points, float *d, float *d2, int64_t *idx) {
    for (int64_t i = 0; i < n; i++) {
        float *di = d + 3 * i;
        idx[i] = area_point(u[3 * i], 1 - s[i], u[3 * i + 2] * s[i], cdf, T, tri, points + 3 * i, di);
        d2[i] = (di[0] * di[0] + di[1] * di[1]) + di[2] * di[2];
    }
}

/* tb_area_finish: d, d2, dist = sqrt(d2) (float32) and idx from above; nrm (T, 3) float32;
 * radiance (3,); area: the total area as float32; ng, ns (n, 3) float32. Out: dir, weight (n, 3),
 * pdf, cos (n,) float32 and ok (n,) uint8: cos > 0, the light in front of ng and pdf > 0. */
void tb_area_finish(int64_t n, const float *d, const float *d2, const float *dist, const int64_t *idx,
                    const float *nrm, const float *radiance, float area, const float *ng, const float *ns,
                    float *dir, float *weight, float *pdf, float *cosv, uint8_t *ok) {
    const float tiny = 1.17549435e-38f, lo_cos = (float)1e-12, lo_pdf = (float)1e-30;
    for (int64_t i = 0; i < n; i++) {
        const float *nl = nrm + 3 * idx[i];
        float r = dist[i], den = r < tiny ? tiny : r, w[3];
        for (int c = 0; c < 3; c++) w[c] = d[3 * i + c] / den;
        float cl = -((w[0] * nl[0] + w[1] * nl[1]) + w[2] * nl[2]);
        int valid = cl > 0 && r > 0;
        float p = valid ? d2[i] / ((cl < lo_cos ? lo_cos : cl) * area) : 0.0f;
        float pc = p < lo_pdf ? lo_pdf : p;
        for (int c = 0; c < 3; c++) {
            dir[3 * i + c] = w[c];
            weight[3 * i + c] = valid ? radiance[c] / pc : 0.0f;
        }
        pdf[i] = p;
        const float *s_ = ns + 3 * i, *g_ = ng + 3 * i;
        float cs = (w[0] * s_[0] + w[1] * s_[1]) + w[2] * s_[2];
        float cg = (w[0] * g_[0] + w[1] * g_[1]) + w[2] * g_[2];
        cosv[i] = cs;
        ok[i] = cs > 0 && cg > 0 && p > 0;
    }
}

/* ---- A pass group's eye rays (polynomial/driver.py eye_rays) ----------------------
 * camera.py Camera.rays_through at the raster positions driver.py _tile_entries makes, around the
 * two steps that stay torch's (the (n, 3) @ (3, 3) product and the row norms, whose BLAS and
 * vectorised reductions round their own way): the same float64 operations in the same order, so
 * the rays are the same bit for bit, with two passes instead of ~15 torch ops on fresh pages.
 * tb_camera_local: ray i at pixel pixels[rec[i]] (flat, row-major in a W x H image) with offsets
 * off[i] (row, column) in [0, 1): local (n, 3) = (sx, sy, 1). Returns 0, or -1 - i when ray i's
 * raster position is not finite. */
int64_t tb_camera_local(int64_t n, const int64_t *rec, const int64_t *pixels, int64_t W, int64_t H, const double *off,
                        double tan_half, double aspect, double *local) {
    const double w = (double)W, h = (double)H;
    for (int64_t i = 0; i < n; i++) {
        const int64_t pix = pixels[rec[i]];
        const double x = (double)(pix % W) + off[2 * i + 1], y = (double)(pix / W) + off[2 * i];
        if (!isfinite(x) || !isfinite(y)) return -1 - i;
        local[3 * i] = ((2.0 * x / w - 1.0) * tan_half) * aspect;
        local[3 * i + 1] = (1.0 - 2.0 * y / h) * tan_half;
        local[3 * i + 2] = 1.0;
    }
    return 0;
}

/* tb_camera_finish: d (n, 3) float64 directions (local @ frame) and their norms (n,) float64 ->
 * origins o (n, 3) = origin and unit directions dir (n, 3) = d / norm, both rounded to float32. */
void tb_camera_finish(int64_t n, const double *d, const double *norm, const double *origin, float *o, float *dir) {
    const float o0 = (float)origin[0], o1 = (float)origin[1], o2 = (float)origin[2];
    for (int64_t i = 0; i < n; i++) {
        const double r = norm[i];
        o[3 * i] = o0, o[3 * i + 1] = o1, o[3 * i + 2] = o2;
        for (int c = 0; c < 3; c++) dir[3 * i + c] = (float)(d[3 * i + c] / r);
    }
}

/* ---- The per-vertex steps of the GI tracer (tracer.py _Tracer.run) ----------
 * One call per step and wavefront instead of ~40 torch ops: the shading frame, an area light's
 * next-event sample with its shadow ray, the light samples' local directions, the band slots
 * and quotients of the editable objects (_Layers), the direction mixture (sampler.py Mixture)
 * and the path's advance (throughput, counts, world direction, the next ray). Same formulas
 * and operation order as the torch code, in float32 (float64 where it uses float64), but libm's
 * scalar sqrtf/atan2f/powf/expm1f/logf (and the mixture's own cos/sin:
 * sincos_fd) instead of torch's vectorised ones: results
 * may differ from the torch path in the last ulp (and a path that then lands on a band edge or
 * grazes an edge of the geometry may take the other side), so the tests compare them with
 * tolerances and the exactness oracles re-evaluate the paths this code traced. */

static float dot3(const float *a, const float *b) { return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]; }
static float sqrt0f(float x) { return x > 0 ? sqrtf(x) : 0.0f; }

/* frame.py Frame.to_local with the (n, 9) rows s, t, n */
static void to_local(const float *fr, const float *v, float *out) {
    out[0] = dot3(v, fr), out[1] = dot3(v, fr + 3), out[2] = dot3(v, fr + 6);
}

/* pathtrace.py shading_frame: flipped normals (in place), the frame (n, 9: s, t, n) from the
 * shading normal (frame.py orthonormal_basis, Duff et al. 2017) and wo = to_local(-d_in). */
static inline void frame_row(const float *d, float *g, float *s, float *fr, float *wo) {
    {
        float flip = dot3(d, g) > 0 ? -1.0f : 1.0f;
        for (int c = 0; c < 3; c++) g[c] *= flip, s[c] *= flip;
        if (!(dot3(s, g) > 0))
            for (int c = 0; c < 3; c++) s[c] = g[c];
        float x = s[0], y = s[1], z = s[2];
        float sign = z >= 0 ? 1.0f : -1.0f, a = -1.0f / (sign + z), b = x * y * a;
        fr[0] = 1.0f + sign * x * x * a, fr[1] = sign * b, fr[2] = -sign * x;
        fr[3] = b, fr[4] = sign + y * y * a, fr[5] = -y;
        fr[6] = x, fr[7] = y, fr[8] = z;
        float md[3] = {-d[0], -d[1], -d[2]};
        to_local(fr, md, wo);
    }
}

void tb_frame(int64_t n, const float *d_in, float *ng, float *ns, float *frame, float *wo) {
    for (int64_t i = 0; i < n; i++) frame_row(d_in + 3 * i, ng + 3 * i, ns + 3 * i, frame + 9 * i, wo + 3 * i);
}


/* The rows k[i] (m,) whose shadow ray is not occluded (occ (m,) bool bytes), in order, into out;
 * returns their number (tracer.py: k[~occ]). */
int64_t tb_unoccluded(int64_t m, const int64_t *k, const uint8_t *occ, int64_t *out) {
    int64_t n = 0;
    for (int64_t i = 0; i < m; i++)
        if (!occ[i]) out[n++] = k[i];
    return n;
}

/* The light samples kk (m,) that reached their vertex, in the frame there: wl = to_local(dir),
 * wo, object, whether it is editable (editable (O,) bytes) and lw = (weight * cos) / reps
 * (tracer.py LightHit). */
void tb_light_gather(int64_t m, const int64_t *kk, const float *dir, const float *weight, const float *cosv, float reps,
                     const float *frame, const float *wo, const int64_t *oid, const uint8_t *editable, float *wl,
                     float *wo_k, int64_t *ob, uint8_t *ed, float *lw) {
    for (int64_t i = 0; i < m; i++) {
        int64_t r = kk[i];
        to_local(frame + 9 * r, dir + 3 * r, wl + 3 * i);
        for (int c = 0; c < 3; c++) wo_k[3 * i + c] = wo[3 * r + c], lw[3 * i + c] = (weight[3 * r + c] * cosv[r]) / reps;
        ob[i] = oid[r], ed[i] = editable[oid[r]] != 0;
    }
}

/* frame.py half_terms: h, cos_d and sin_d of a pair (float32) */
static void half_terms(const float *wi, const float *wo, float *h, float *cos_d, float *sin_d) {
    float s[3] = {wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]};
    float len = sqrt0f((s[0] * s[0] + s[1] * s[1]) + s[2] * s[2]);
    const float e = 1.1920929e-07f;
    if (len > e)
        for (int c = 0; c < 3; c++) h[c] = s[c] / len;
    else
        h[0] = 0, h[1] = 0, h[2] = 1;
    float d[3] = {wi[0] - wo[0], wi[1] - wo[1], wi[2] - wo[2]};
    float q = ((d[0] * d[0] + d[1] * d[1]) + d[2] * d[2]) * 0.25f;
    q = q < 0 ? 0 : (q > 1 ? 1 : q);
    *cos_d = 0.5f * len, *sin_d = sqrt0f(q);
}

enum { Q_ONE, Q_DISTRIBUTION, Q_MICROFACET, Q_COOK_TORRANCE, Q_ASHIKHMIN_SHIRLEY, Q_SCHLICK = 8 };

/* bands/quotients.py: the value of quotient code q (Q_SCHLICK + base: the Fresnel layer) */
static float quotient(int q, const float *wi, const float *wo, const float *h, float cos_d) {
    const float e = 1.1920929e-07f;
    float ci = wi[2] < e ? e : wi[2], co = wo[2] < e ? e : wo[2], v;
    switch (q & 7) {
    case Q_DISTRIBUTION: v = 1.0f / ((ci + co) - ci * co); break;
    case Q_MICROFACET: v = 0.25f / (ci * co); break;
    case Q_COOK_TORRANCE: {
        float ch = h[2] > 0 ? h[2] : 0.0f, cd = cos_d < e ? e : cos_d, mn = ci < co ? ci : co;
        float g = 2 * ch * mn / cd;
        g = g < 1.0f ? g : 1.0f;
        v = 0.25f * g / (ci * co);
        break;
    }
    case Q_ASHIKHMIN_SHIRLEY: {
        float cd = cos_d < e ? e : cos_d, mx = wi[2] > wo[2] ? wi[2] : wo[2];
        v = 1.0f / (cd * (mx < e ? e : mx));
        break;
    }
    default: v = 1.0f;
    }
    if (q & Q_SCHLICK) {
        float x = 1 - (cos_d < 0 ? 0 : (cos_d > 1 ? 1 : cos_d));
        v = v * powf(x, 5.0f);
    }
    return v;
}

/* tracer.py _Layers for the objects the kernel knows (spec row mode 1: banded; 2: fixed
 * Lambertian of reflectance lambert[o] (O, 3)): per object o, spec[8 * o]
 * = mode (0: torch fills the row), variable (0 theta_h, 1 theta_d), J, slot offset, layers,
 * quotient code of layer 0 and 1, first inner edge in `edges` (float32, J - 1 per object). Out:
 * idx (n, L) int64 (off + layer J + band; `fill` beyond the object's layers and for mode 0) and
 * w (n, L, 3) float32 (quotient where both directions are above the horizon, else 0). */
void tb_layers(int64_t n, int L, int64_t fill, const int32_t *spec, const float *edges, const float *lambert,
               const int64_t *oid, const float *wi, const float *wo, int64_t *idx, float *w) {
    for (int64_t i = 0; i < n; i++) {
        const int32_t *sp = spec + 8 * oid[i];
        const float *a = wi + 3 * i, *b = wo + 3 * i;
        int64_t *ir = idx + (int64_t)L * i;
        float *wr = w + (int64_t)3 * L * i;
        for (int l = 0; l < L; l++) ir[l] = fill, wr[3 * l] = wr[3 * l + 1] = wr[3 * l + 2] = 0.0f;
        if (sp[0] == 2) { /* a fixed Lambertian object: rho / pi above both horizons (brdf/base.py) */
            const float *rho = lambert + 3 * oid[i];
            int up = a[2] > 0 && b[2] > 0;
            for (int c = 0; c < 3; c++) wr[c] = up ? rho[c] / (float)3.14159265358979323846 : 0.0f;
        }
        if (sp[0] != 1) continue;
        /* the half vector and angle only where something reads them: a single band
         * (J = 1) needs no angle, and the one, distribution and microfacet quotients no h or
         * theta_d; the values written are the same */
        int need_h = sp[2] > 1;
        for (int l = 0; l < sp[4] && l < L; l++) {
            int q = sp[5 + l];
            need_h |= (q & Q_SCHLICK) || (q & 7) == Q_COOK_TORRANCE || (q & 7) == Q_ASHIKHMIN_SHIRLEY;
        }
        float h[3] = {0, 0, 1}, cos_d = 1, sin_d = 0, gamma = 0;
        if (need_h) half_terms(a, b, h, &cos_d, &sin_d);
        if (sp[2] > 1)
            gamma = sp[1] == 0 ? atan2f(sqrt0f(h[0] * h[0] + h[1] * h[1]), h[2]) : atan2f(sin_d, cos_d);
        const float *in = edges + sp[7];
        /* bucketize(right=True): the number of inner edges <= gamma (an upper bound by halving,
         * without a branch per step: the step's outcome is as random as the sample) */
        int lo = 0, len = sp[2] - 1;
        while (len > 0) {
            int half = len >> 1, go = in[lo + half] <= gamma;
            lo = go ? lo + half + 1 : lo;
            len = go ? len - half - 1 : half;
        }
        float up = (a[2] > 0 && b[2] > 0) ? 1.0f : 0.0f;
        for (int l = 0; l < sp[4] && l < L; l++) {
            float q = quotient(sp[5 + l], a, b, h, cos_d) * up;
            ir[l] = sp[3] + (int64_t)l * sp[2] + lo;
            wr[3 * l] = wr[3 * l + 1] = wr[3 * l + 2] = q;
        }
    }
}

/* a quarter of the spacing of float32 values at x (normal, positive) as a float64 */
static double ulp_quarter(float x) {
    uint32_t b;
    memcpy(&b, &x, 4);
    int e = (int)((b >> 23) & 0xff) - 127; /* x in [2^e, 2^(e+1)): its ulp is 2^(e - 23) */
    uint64_t d = (uint64_t)(e - 23 - 2 + 1023) << 52;
    double q;
    memcpy(&q, &d, 8);
    return q;
}

/* cos and sin of float angles x (|x| < 2^20), rounded to float from float64 arithmetic:
 * x - k pi/2 with k = nearest integer of x 2/pi (pi/2 as two doubles: the reduced angle r,
 * |r| <= pi/4 + 1e-9, is exact to ~1e-16 relative for these x), then Taylor polynomials of
 * sin r to r^15 and cos r to r^14 (truncation < 1e-15 relative at pi/4), the quadrant by
 * selects. The float64 result is within ~1e-15 relative of cos x / sin x, so the float is the
 * correctly rounded value unless that lies within ~1e-7 ulp of a tie: max error 0.5 ulp (+1e-7)
 * against a float64 reference (glibc's sincosf: 0.56 ulp); tests/transport/test_vertex.py
 * measures it. No branch, no call: the loops that use it vectorise. */
static inline void sincos_fd(float xf, float *cp, float *sp) {
    const double two_over_pi = 0.63661977236758134308, pio2_hi = 1.5707963267341256, pio2_lo = 6.077100506506192e-11;
    const double magic = 6755399441055744.0; /* 1.5 * 2^52: x + magic - magic rounds x to an integer */
    double x = xf, kd = (x * two_over_pi + magic) - magic;
    double r = (x - kd * pio2_hi) - kd * pio2_lo, r2 = r * r;
    double sr = r + r * r2 * (-1.0 / 6 + r2 * (1.0 / 120 + r2 * (-1.0 / 5040 + r2 * (1.0 / 362880 + r2 * (-1.0 / 39916800 + r2 * (1.0 / 6227020800.0 + r2 * (-1.0 / 1307674368000.0)))))));
    double cr = 1.0 + r2 * (-0.5 + r2 * (1.0 / 24 + r2 * (-1.0 / 720 + r2 * (1.0 / 40320 + r2 * (-1.0 / 3628800 + r2 * (1.0 / 479001600.0 + r2 * (-1.0 / 87178291200.0)))))));
    int q = (int)kd & 3;
    double c = (q & 1) ? sr : cr, s = (q & 1) ? cr : sr;
    c = (q == 1 || q == 2) ? -c : c;
    s = (q & 2) ? -s : s;
    *cp = (float)c, *sp = (float)s;
}

void tb_sincos(int64_t n, const float *x, float *c, float *s) { /* tests: sincos_fd on an array */
    for (int64_t i = 0; i < n; i++) sincos_fd(x[i], c + i, s + i);
}

/* sampler.py Mixture.sample and .pdf, then the tracer's ok and cos / pdf: u (n, 3) float32,
 * wo (n, 3) local -> wi (n, 3), pdf (n,), cosw (n,) and ok (n,) uint8. The constants as torch
 * rounds them: diffuse, gloss = 1 - diffuse, exponent n and norm = (n + 1) / (2 pi) in float64,
 * then float32.
 * In blocks of MIX_B rows, as passes over the block: the angles of the sampler drawn
 * and their cos / sin (sincos_fd, no libm call), the lobe's sin^2 (logf, expm1f) on the lobe's
 * rows only, the directions and the pdf's diffuse term, the lobe's pdf term (powf) on the rows
 * that need it, then cos / pdf: no branch on the sample in the arithmetic passes, so they
 * vectorise or at least overlap (libm's sinf/cosf were replaced: the tensors' rounding changed
 * by <= 1 ulp in those values; logf/expm1f/powf are libm's as before). */
enum { MIX_B = 256 };
TB_SIMD void tb_mixture(int64_t n, const float *u, const float *wo, float diffuse, float gloss, float exponent, float norm,
                float *wi, float *pdf, float *cosw, uint8_t *ok) {
    const double PI = 3.14159265358979323846;
    const float tiny = 1.17549435e-38f, e = 1.1920929e-07f, q1 = (float)(PI / 4), q2 = (float)(PI / 2);
    const float two_pi = (float)(2 * PI), inv_pi = (float)(1 / PI);
    /* The lobe's pdf term gloss * norm * powf(ch, n) / (4 coh) (powf: ~40% of this
     * loop) is left out where it cannot change p: for ch <= c0 it is at most lobe_bound / coh
     * (c0^n in float64 with margins for powf's ulp and the four float32 roundings), and a
     * term below half an ulp of t1 > 0 leaves the rounded sum t1 + term at t1. */
    float c0 = exponent > 0 ? (float)exp(log(1e-12) / exponent) : -1.0f;
    double lobe_bound = c0 > 0 ? (double)gloss * (double)norm * pow((double)c0, (double)exponent) * 1.01 / 4.0 : 0.0;
    float phi[MIX_B], cp[MIX_B], sp[MIX_B], s2[MIX_B], ch[MIX_B], coh[MIX_B], t1[MIX_B];
    int32_t rows[MIX_B];
    for (int64_t i0 = 0; i0 < n; i0 += MIX_B) {
        const int nb = n - i0 < MIX_B ? (int)(n - i0) : MIX_B;
        const float *ub = u + 3 * i0, *ob = wo + 3 * i0;
        float *wb = wi + 3 * i0;
        /* the angle of the sampler drawn (every division done, then selected: no branch) */
        for (int j = 0; j < nb; j++) {
            const float *ui = ub + 3 * j;
            float a = 2 * ui[1] - 1, b = 2 * ui[2] - 1;
            int first = fabsf(a) > fabsf(b);
            float r = first ? a : b, safe = r == 0 ? 1.0f : r, ba = b / safe, ab = a / safe;
            float phi_d = first ? q1 * ba : q2 - q1 * ab;
            phi[j] = ui[0] < diffuse ? phi_d : two_pi * ui[2];
            s2[j] = 0.0f;
        }
        int nl = 0; /* the lobe's rows */
        for (int j = 0; j < nb; j++) rows[nl] = j, nl += !(ub[3 * j] < diffuse);
        for (int j = 0; j < nb; j++) sincos_fd(phi[j], cp + j, sp + j);
        for (int t = 0; t < nl; t++) { /* a cos^n half vector about the normal: its sin^2 */
            int j = rows[t];
            float om = 1.0f - ub[3 * j + 1];
            float lu = logf(om < tiny ? tiny : (om > 1 ? 1.0f : om));
            float v = -expm1f(2.0f * lu / (exponent + 1.0f));
            s2[j] = v < 0 ? 0.0f : (v > 1 ? 1.0f : v);
        }
        /* the directions (Malley's, or wo mirrored about the half vector) and the pdf's terms */
        for (int j = 0; j < nb; j++) {
            const float *ui = ub + 3 * j, *o = ob + 3 * j;
            float a = 2 * ui[1] - 1, b = 2 * ui[2] - 1;
            float r = fabsf(a) > fabsf(b) ? a : b;
            int dif = ui[0] < diffuse;
            float x_d = r * cp[j], y_d = r * sp[j], z_d = 1 - (x_d * x_d + y_d * y_d);
            z_d = sqrtf(z_d > 0 ? z_d : 0.0f);
            float st = sqrtf(s2[j]), h0 = st * cp[j], h1 = st * sp[j], h2 = sqrtf(1.0f - s2[j]);
            float kl = 2 * ((o[0] * h0 + o[1] * h1) + o[2] * h2);
            float x_l = kl * h0 - o[0], y_l = kl * h1 - o[1], z_l = kl * h2 - o[2];
            float w0 = dif ? x_d : x_l, w1 = dif ? y_d : y_l, w2 = dif ? z_d : z_l;
            float *w = wb + 3 * j;
            w[0] = w0, w[1] = w1, w[2] = w2;
            float s0 = w0 + o[0], s1 = w1 + o[1], sz = w2 + o[2];
            float len = sqrt0f((s0 * s0 + s1 * s1) + sz * sz), d0 = s0 / len, d1 = s1 / len, d2 = sz / len;
            int big = len > e;
            float hx = big ? d0 : 0.0f, hy = big ? d1 : 0.0f, hz = big ? d2 : 1.0f;
            float c = fabsf((o[0] * hx + o[1] * hy) + o[2] * hz);
            coh[j] = c < 1e-12f ? 1e-12f : c;
            ch[j] = hz > 0 ? hz : 0.0f;
            float cz = w2 > 0 ? w2 : 0.0f;
            t1[j] = diffuse * (cz * inv_pi);
        }
        /* the lobe's pdf term where it can change p (p is 0 below the horizon whatever it is) */
        for (int j = 0; j < nb; j++) {
            float w2 = wb[3 * j + 2], p = t1[j];
            if (w2 > 0 && !(ch[j] <= c0 && p >= 0x1p-100f && lobe_bound < (double)coh[j] * ulp_quarter(p))) {
                float h = ch[j], ph = h > 0 ? norm * powf(h < tiny ? tiny : h, exponent) : 0.0f;
                p = p + gloss * ph / (4 * coh[j]);
            }
            p = w2 > 0 ? p : 0.0f;
            pdf[i0 + j] = p;
            int good = (p > 0) & (w2 > 0) & (ob[3 * j + 2] > 0);
            ok[i0 + j] = (uint8_t)good;
            float cw = w2 / (p < 1e-30f ? 1e-30f : p);
            cosw[i0 + j] = good ? cw : 0.0f;
        }
    }
}

/* 1 when max(x[0..k)) > 0 with torch's amax (a NaN gives NaN: not > 0) */
static int amax_pos(const float *x, int64_t k, int absval) {
    int pos = 0;
    for (int64_t c = 0; c < k; c++) {
        float v = absval ? fabsf(x[c]) : x[c];
        if (v != v) return 0;
        if (v > 0) pos = 1;
    }
    return pos;
}

/* The path's advance after the mixture sample (tracer.py run): raw (n, 3) *= f (when f, rows of
 * fixed objects) then *= cosw; with `count`, one more occurrence of each editable object;
 * world direction; the paths that go on (ok, leaving the front of ng, raw, A_w and B_w not all
 * zero) compacted into rows a (m,), origins so (m, 3) and directions sd (m, 3). Returns m. */
int64_t tb_advance(int64_t n, const float *wi, const float *cosw, const uint8_t *ok, const float *f, int count,
                   const int64_t *oid, const uint8_t *editable, int M, int8_t *counts, float *raw, const float *frame,
                   const float *ng, const float *pos, int64_t La, const float *A_w, int64_t Lb, const float *B_w,
                   float eps, int64_t *a, float *so, float *sd) {
    int64_t m = 0;
    for (int64_t i = 0; i < n; i++) {
        float *r = raw + 3 * i;
        for (int c = 0; c < 3; c++) r[c] = (f ? r[c] * f[3 * i + c] : r[c]) * cosw[i];
        if (count && editable[oid[i]]) counts[i * M + oid[i]] += 1;
        const float *fr = frame + 9 * i, *l = wi + 3 * i, *g = ng + 3 * i;
        float d[3];
        for (int c = 0; c < 3; c++) d[c] = (l[0] * fr[c] + l[1] * fr[3 + c]) + l[2] * fr[6 + c];
        float cg = dot3(d, g);
        if (!(ok[i] && cg > 0 && amax_pos(r, 3, 0) && amax_pos(A_w + 3 * La * i, 3 * La, 1) &&
              amax_pos(B_w + 3 * Lb * i, 3 * Lb, 1)))
            continue;
        float side = cg >= 0 ? eps : -eps;
        for (int c = 0; c < 3; c++) so[3 * m + c] = pos[3 * i + c] + side * g[c], sd[3 * m + c] = d[c];
        a[m++] = i;
    }
    return m;
}

/* tracer.py _fixed_f: (n, 3) the full BRDF of fixed objects, 1 for editable ones; mode[o]: 0
 * editable, 1 fixed Lambertian (lambert (O, 3) reflectance), 2 another BRDF (left 1: torch fills
 * those rows). */
void tb_fixed_f(int64_t n, const int32_t *mode, const float *lambert, const int64_t *oid, const float *wi,
                const float *wo, float *f) {
    for (int64_t i = 0; i < n; i++) {
        int64_t o = oid[i];
        int up = wi[3 * i + 2] > 0 && wo[3 * i + 2] > 0;
        for (int c = 0; c < 3; c++)
            f[3 * i + c] = mode[o] == 1 ? (up ? lambert[3 * o + c] / (float)3.14159265358979323846 : 0.0f) : 1.0f;
    }
}

/* Rows `rows` (m,) of k row-major arrays: dst[a] row i = src[a] row rows[i], rowbytes[a] bytes
 * per row (the path state's and the hits' gathers after a trace, tracer.py PathState.keep). */
void tb_gather(int64_t m, const int64_t *rows, int k, char *const *src, char *const *dst, const int64_t *rowbytes) {
    for (int a = 0; a < k; a++) {
        const char *s = src[a];
        char *d = dst[a];
        int64_t b = rowbytes[a];
        if (b == 8)
            for (int64_t i = 0; i < m; i++) memcpy(d + 8 * i, s + 8 * rows[i], 8);
        else if (b == 12)
            for (int64_t i = 0; i < m; i++) memcpy(d + 12 * i, s + 12 * rows[i], 12);
        else
            for (int64_t i = 0; i < m; i++) memcpy(d + b * i, s + b * rows[i], (size_t)b);
    }
}

/* ---- visibility cubemaps (transport/visibility.py) ----------------------------------------
 *
 * The rays go to embree's rtcOccluded1 directly: the caller passes the committed scene's
 * handle and the function's address (scene/parallel.py: embree_entry), so the query per ray is
 * the one embreex's EmbreeScene.run makes (origin, direction, tnear 0, tfar 1e37, mask ~0, time
 * 0, flags 0; occluded when embree sets tfar to -inf), in the same order, without a Python call,
 * an (n, 3) array or a result array per fan. The ray layout is embree 4's RTCRay. */
typedef struct __attribute__((aligned(16))) {
    float org_x, org_y, org_z, tnear, dir_x, dir_y, dir_z, time, tfar;
    uint32_t mask, id, flags;
} tb_ray;
typedef void (*tb_occluded1)(void *scene, tb_ray *ray, void *args);

static inline int tb_escapes(tb_occluded1 occluded, void *scene, const float *o, const float *d) {
    tb_ray r;
    r.org_x = o[0], r.org_y = o[1], r.org_z = o[2], r.tnear = 0.0f;
    r.dir_x = d[0], r.dir_y = d[1], r.dir_z = d[2], r.time = 0.0f, r.tfar = 1e37f;
    r.mask = 0xFFFFFFFFu, r.id = 0, r.flags = 0;
    occluded(scene, &r, NULL);
    return !(r.tfar < 0.0f);
}

/* The horizon of a vertex with normal n over one block of side x side texels (centres in
 * block order, row-major, float64 (3, T) as cx, cy, cz from texel t0): texel t is above it when
 * (n.x c.x + n.y c.y) + n.z c.z > eps. A block lies on one cube face, its centres are c = p / |p|
 * for points p of a square grid on the face (|p| >= 1), and n . p is linear in p: when the four
 * corner centres all give n . c > BLOCK_MARGIN, every centre gives n . c >= BLOCK_MARGIN / sqrt(3),
 * far above eps and any rounding (the block is all up: 1); all below -BLOCK_MARGIN: all down (0);
 * else -1 (test the texels). */
#define BLOCK_MARGIN 1e-6
static int tb_block_side(const double *n, const double *cx, const double *cy, const double *cz, int64_t t0,
                         int64_t side) {
    const int64_t corner[4] = {0, side - 1, side * (side - 1), side * side - 1};
    int above = 0, below = 0;
    for (int k = 0; k < 4; k++) {
        int64_t t = t0 + corner[k];
        double d = (n[0] * cx[t] + n[1] * cy[t]) + n[2] * cz[t];
        above += d > BLOCK_MARGIN, below += d < -BLOCK_MARGIN;
    }
    return above == 4 ? 1 : below == 4 ? 0 : -1;
}

/* tb_vis_fans: the visibility of m vertices, blocks of side x side texels (T in all). Above the
 * horizon of the vertex's normal (normals (m, 3) float64; centres (3, T) float64, see
 * tb_block_side), a texel's k2 rays dirs[t k2 .. t k2 + k2) (float32 (T k2, 3)) are cast from the
 * vertex's origin (origins (m, 3) float32).
 * Binary maps (k2 == 1, counts given): the flips of each block (texel -1 reads 0): counts
 * (m, T / side^2) int16 and their texel positions in index (capacity m T), in order; returns
 * their number. Graded maps (frac given): frac (m, T) float32 = escaping rays / k2 (0 below the
 * horizon); returns 0. */
int64_t tb_vis_fans(void *scene, void *fn, int64_t m, const float *origins, const double *normals, int64_t T,
                    const double *centres, const float *dirs, int64_t k2, double eps, int64_t side, int16_t *counts,
                    uint8_t *index, float *frac) {
    tb_occluded1 occluded = (tb_occluded1)fn;
    const double *cx = centres, *cy = centres + T, *cz = centres + 2 * T;
    const int64_t bt = side * side, nb = T / bt;
    int64_t f = 0;
    for (int64_t v = 0; v < m; v++) {
        const double *n = normals + 3 * v;
        const float *o = origins + 3 * v;
        for (int64_t b = 0; b < nb; b++) {
            const int64_t t0 = b * bt;
            const int all = tb_block_side(n, cx, cy, cz, t0, side);
            if (frac) {
                float *row = frac + v * T + t0;
                for (int64_t i = 0; i < bt; i++) {
                    const int64_t t = t0 + i;
                    int free_rays = 0;
                    if (all == 1 || (all == -1 && (n[0] * cx[t] + n[1] * cy[t]) + n[2] * cz[t] > eps))
                        for (int64_t s = 0; s < k2; s++) free_rays += tb_escapes(occluded, scene, o, dirs + 3 * (t * k2 + s));
                    row[i] = (float)free_rays / (float)k2;
                }
                continue;
            }
            int prev = 0, c = 0;
            if (all == 1)
                for (int64_t i = 0; i < bt; i++) {
                    const int vis = tb_escapes(occluded, scene, o, dirs + 3 * (t0 + i));
                    if (vis != prev) index[f++] = (uint8_t)i, c++, prev = vis;
                }
            else if (all == -1)
                for (int64_t i = 0; i < bt; i++) {
                    const int64_t t = t0 + i;
                    const int vis = (n[0] * cx[t] + n[1] * cy[t]) + n[2] * cz[t] > eps &&
                                    tb_escapes(occluded, scene, o, dirs + 3 * t);
                    if (vis != prev) index[f++] = (uint8_t)i, c++, prev = vis;
                }
            counts[v * nb + b] = (int16_t)c;
        }
    }
    return f;
}

/* tb_occluded_fans: embree alone on given rays (the benchmark's baseline): fan v casts counts[v]
 * rays from origins[v] (float32 (m, 3)), ray i in the direction dirs[texel[i]] (texel: uint16
 * (sum counts,), dirs float32 (D, 3)); out[i] = occluded (uint8, or NULL). Returns the
 * occluded rays. */
int64_t tb_occluded_fans(void *scene, void *fn, int64_t m, const float *origins, const int64_t *counts,
                         const uint16_t *texel, const float *dirs, uint8_t *out) {
    tb_occluded1 occluded = (tb_occluded1)fn;
    int64_t i = 0, hits = 0;
    for (int64_t v = 0; v < m; v++)
        for (int64_t e = i + counts[v]; i < e; i++) {
            int hit = !tb_escapes(occluded, scene, origins + 3 * v, dirs + 3 * (int64_t)texel[i]);
            hits += hit;
            if (out) out[i] = (uint8_t)hit;
        }
    return hits;
}

/* ---- GI ray casting (transport/rays.py) -----------------------------------------------------
 *
 * The GI tracer's closest-hit rays and shadow rays, cast straight into embree as the visibility
 * fans above are (the scene handle and rtcIntersect1 / rtcOccluded1 from the library embreex
 * loaded: scene/parallel.py), with the hit interpolation of scene/parallel.py's
 * TraceKernel._hits fused in: the same query per ray as EmbreeScene.run (tnear 0, tfar as given,
 * mask ~0, time 0, flags 0, hit ids and instID[0] invalid), the same per-triangle table (3 x
 * (vertex, vertex normal), unit face normal; 21 floats a row) and the same float32 formulas in
 * the same order, one ray at a time instead of numpy's passes over arrays. */
typedef struct __attribute__((aligned(16))) {
    tb_ray ray;
    float Ng_x, Ng_y, Ng_z, u, v;
    uint32_t primID, geomID, instID0;
    /* room for the RTCHit fields that depend on embree's build (instPrimID, more instance levels):
     * embree writes them, we never read them */
    uint32_t spare[24];
} tb_rayhit;
typedef void (*tb_intersect1)(void *scene, tb_rayhit *rayhit, void *args);
#define TB_INVALID_ID 0xFFFFFFFFu

static inline int tb_finite3(const float *x) { return isfinite(x[0]) && isfinite(x[1]) && isfinite(x[2]); }

static inline void tb_rayhit_init(tb_rayhit *r, const float *o, const float *d, float tfar) {
    r->ray.org_x = o[0], r->ray.org_y = o[1], r->ray.org_z = o[2], r->ray.tnear = 0.0f;
    r->ray.dir_x = d[0], r->ray.dir_y = d[1], r->ray.dir_z = d[2], r->ray.time = 0.0f, r->ray.tfar = tfar;
    r->ray.mask = 0xFFFFFFFFu, r->ray.id = 0, r->ray.flags = 0;
    r->geomID = TB_INVALID_ID, r->primID = TB_INVALID_ID, r->instID0 = TB_INVALID_ID;
}

/* tb_trace_hits: closest hits of n rays (o, d: float32 (n, 3); tfar = inf) and what
 * TraceKernel._hits makes of them. table: float32 (F, 21) rows of the triangles of all objects;
 * offsets: (O,) int64 first row of each object (NULL: one object); flat: (O,) uint8, 1 where the
 * shading normal is the face normal (NULL: none). Out: t (n,) float32 (inf on a miss), obj and
 * prim (n,) int64 (-1 on a miss), bary (n, 2), pos, ng, ns (n, 3) float32 (0 on a miss).
 * Returns the hits, or -1 - i when ray i is not finite (the rays before it are cast). */
int64_t tb_trace_hits(void *scene, void *fn, int64_t n, const float *o, const float *d, const float *table,
                      const int64_t *offsets, const uint8_t *flat, float *t, int64_t *obj, int64_t *prim, float *bary,
                      float *pos, float *ng, float *ns) {
    /* Two passes, the same values. The embree calls first (t, obj, prim, bary), then
     * the interpolation of every ray from those: the rows' arithmetic (and its sqrtf's latency)
     * does not sit between one embree call and the next, and the second loop has no call. */
    tb_intersect1 intersect = (tb_intersect1)fn;
    int64_t hits = 0, cast = n, rc = 0;
    tb_rayhit r;
    for (int64_t i = 0; i < n; i++) {
        if (!tb_finite3(o + 3 * i) || !tb_finite3(d + 3 * i)) { /* the outputs are then partial */
            cast = i, rc = -1 - i;
            break;
        }
        tb_rayhit_init(&r, o + 3 * i, d + 3 * i, INFINITY);
        intersect(scene, &r, NULL);
        t[i] = r.ray.tfar;
        if (r.geomID == TB_INVALID_ID) {
            obj[i] = -1, prim[i] = -1, bary[2 * i] = 0.0f, bary[2 * i + 1] = 0.0f;
            continue;
        }
        hits++;
        obj[i] = r.geomID, prim[i] = r.primID, bary[2 * i] = r.u, bary[2 * i + 1] = r.v;
    }
    for (int64_t i = 0; i < cast; i++) {
        float *p = pos + 3 * i, *g = ng + 3 * i, *s = ns + 3 * i;
        if (obj[i] < 0) {
            for (int c = 0; c < 3; c++) p[c] = 0.0f, g[c] = 0.0f, s[c] = 0.0f;
            continue;
        }
        const int64_t face = (offsets ? offsets[obj[i]] : 0) + prim[i];
        const float *row = table + 21 * face;
        const float w1 = bary[2 * i], w2 = bary[2 * i + 1], w0 = (1.0f - w1) - w2;
        float q[6];
        for (int c = 0; c < 6; c++) q[c] = (w0 * row[c] + w1 * row[6 + c]) + w2 * row[12 + c];
        float len = q[3] * q[3];
        len += q[4] * q[4];
        len += q[5] * q[5];
        len = sqrtf(len);
        if (!(len >= 1e-12f)) len = 1e-12f;
        const int is_flat = flat && flat[obj[i]];
        for (int c = 0; c < 3; c++) {
            p[c] = q[c], g[c] = row[18 + c];
            s[c] = is_flat ? row[18 + c] : q[3 + c] / len;
        }
    }
    return rc ? rc : hits;
}

/* tb_occluded_rays: whether anything lies on ray i within (0, min(tmax[i], 1e37)) (origins o
 * (n, 3), directions d[rows[i]] (d: (D, 3); rows NULL: d[i]), float32): out[i] = 1 occluded,
 * 0 free. Returns the occluded rays, or -1 - i when ray i is not finite, tmax[i] is NaN or
 * rows[i] is outside [0, D) (the rays before it are cast). */
int64_t tb_occluded_rays(void *scene, void *fn, int64_t n, const float *o, const float *d, int64_t D,
                         const int64_t *rows, const float *tmax, uint8_t *out) {
    tb_occluded1 occluded = (tb_occluded1)fn;
    int64_t hits = 0;
    tb_ray r;
    for (int64_t i = 0; i < n; i++) {
        if (rows && (rows[i] < 0 || rows[i] >= D)) return -1 - i;
        const float *oi = o + 3 * i, *di = d + 3 * (rows ? rows[i] : i);
        if (!tb_finite3(oi) || !tb_finite3(di) || isnan(tmax[i])) return -1 - i;
        r.org_x = oi[0], r.org_y = oi[1], r.org_z = oi[2], r.tnear = 0.0f;
        r.dir_x = di[0], r.dir_y = di[1], r.dir_z = di[2], r.time = 0.0f;
        r.tfar = tmax[i] < 1e37f ? tmax[i] : 1e37f;
        r.mask = 0xFFFFFFFFu, r.id = 0, r.flags = 0;
        occluded(scene, &r, NULL);
        out[i] = (uint8_t)(r.tfar < 0.0f);
        hits += out[i];
    }
    return hits;
}

/* tb_intersect_only: embree alone on n closest-hit rays (the benchmark's baseline): the query of
 * tb_trace_hits (tfar: tfar[i], NULL: 1e37) keeping only the geometry id (geom (n,) int32, -1 on a
 * miss, or NULL). Returns the hits. */
int64_t tb_intersect_only(void *scene, void *fn, int64_t n, const float *o, const float *d, const float *tfar,
                          int32_t *geom) {
    tb_intersect1 intersect = (tb_intersect1)fn;
    int64_t hits = 0;
    tb_rayhit r;
    for (int64_t i = 0; i < n; i++) {
        tb_rayhit_init(&r, o + 3 * i, d + 3 * i, tfar ? tfar[i] : 1e37f);
        intersect(scene, &r, NULL);
        hits += r.geomID != TB_INVALID_ID;
        if (geom) geom[i] = r.geomID == TB_INVALID_ID ? -1 : (int32_t)r.geomID;
    }
    return hits;
}

/* ==== A tile's sums per key, gathered record by record (bookkeeping) ========
 * The twin of tb_reduce_into (a pass group's per-path sums appended as a sorted run) followed
 * by the tile's final merge (reduce_impl over the runs), without sorting keys: a pass group's
 * entries are bucketed by (record, path) with one stable counting sort (arrival order kept
 * within a bucket); each bucket's entries are summed per key in arrival order from 0.0 (the
 * path's sum s, as the group's sort summed it) and kept as rows (key, s), bucket by bucket, so
 * each group leaves its rows by record, paths ascending. When the tile is read (tt_finish),
 * each record's rows, group after group, are summed per key (s and s * s from 0.0) in a small
 * hash table that stays in cache. A key's tile sums thus add the per-path sums group by group
 * and within a group path by path ascending: the merged runs' order, the same sums bit for
 * bit. The keys leave the tile ascending as tb_reduce returns them (tb_tile_export);
 * tb_blocks does not depend on their order (it sorts by keys unique per row). */

#define TT_EMPTY (~(u128)0)   /* a free hash slot: no key has all 128 bits set (keys have <= 127) */
#define TT_AHEAD 32           /* rows prefetched ahead in the gathers of tb_tile_add and tb_tile_blocks */
#define TT_MAX_BUCKET_BITS 22 /* record + path bits of a group: its counting sort's buckets (16 MB) */

typedef struct __attribute__((aligned(16))) {
    u128 k; /* the key without its path field */
    double s[3];
} tt_row; /* one path's sum of a key */

typedef struct __attribute__((aligned(16))) {
    u128 k;
    double s[3], q[3];
} tt_sum; /* a key's tile sums: sums, then sums of per-path squares */

typedef struct {
    int M, bits[NFIXED], bc, total; /* the tile key's widths (a group accumulator's without path) */
    int64_t nrec;                   /* 1 << bits[F_REC]: the record ids a key can hold */
    tt_row *rows;                   /* every group's rows, group after group, record by record */
    int64_t nrows, rows_room;
    int64_t *starts; /* per group g: (nrec + 1) offsets of each record's rows in `rows` */
    int64_t ngroups, starts_room;
    tt_sum *sums; /* after tt_finish: U keys and their sums, record by record */
    int64_t U;
    int max_count, done;
    int32_t *hist, *perm;
    int64_t hist_room, perm_room;
} tb_tile;

/* bits: rec, obj, bounce, j, w + 1, one count digit (a group accumulator's without the path) */
tb_tile *tb_tile_new(int M, const int32_t *bits) {
    tb_tile *t = (tb_tile *)calloc(1, sizeof(tb_tile));
    if (!t) return NULL;
    t->M = M, t->bc = bits[NFIXED], t->total = M * t->bc;
    for (int f = 0; f < NFIXED; f++) t->bits[f] = bits[f], t->total += bits[f];
    if (t->total > 127 || bits[F_REC] > TT_MAX_BUCKET_BITS) {
        free(t);
        return NULL;
    }
    t->nrec = (int64_t)1 << bits[F_REC];
    return t;
}

void tb_tile_free(tb_tile *t) {
    if (!t) return;
    free(t->rows), free(t->starts), free(t->sums), free(t->hist), free(t->perm), free(t);
}

/* Add the per-path sums of a pass group's entries (a: values 3, with a path field) to the tile:
 * what tb_reduce_into(a, ., into) and the final merge add, in the same order. Returns 0; -1 out
 * of memory; -2 a's widths are not the tile's (plus a path field), too many buckets, or the
 * tile was already read. */
int tb_tile_add(tb_tile *t, const tb_acc *a) {
    const int bp = a->bp;
    if (t->done || a->M != t->M || a->V != 3 || a->bc != t->bc || a->total - bp != t->total || bp < 1) return -2;
    for (int f = 0; f < NFIXED; f++)
        if (a->bits[f] != t->bits[f]) return -2;
    const int64_t n = a->n, nb = t->nrec << bp;
    if (t->bits[F_REC] + bp > TT_MAX_BUCKET_BITS || n >= INT32_MAX) return -2;
    if (!n) return 0;
    if (t->hist_room < nb + 1) {
        free(t->hist);
        t->hist = (int32_t *)malloc(sizeof(int32_t) * (nb + 1)), t->hist_room = t->hist ? nb + 1 : 0;
    }
    if (t->perm_room < n) {
        free(t->perm);
        t->perm = (int32_t *)malloc(sizeof(int32_t) * n), t->perm_room = t->perm ? n : 0;
    }
    if (t->nrows + n > t->rows_room) {
        int64_t room = t->rows_room ? t->rows_room : 1 << 16;
        while (room < t->nrows + n) room *= 2;
        tt_row *r = (tt_row *)realloc(t->rows, sizeof(tt_row) * room);
        if (!r) return -1;
        t->rows = r, t->rows_room = room;
    }
    if ((t->ngroups + 1) * (t->nrec + 1) > t->starts_room) {
        int64_t room = t->starts_room ? 2 * t->starts_room : 16 * (t->nrec + 1);
        int64_t *st = (int64_t *)realloc(t->starts, sizeof(int64_t) * room);
        if (!st) return -1;
        t->starts = st, t->starts_room = room;
    }
    if (!t->hist || !t->perm) return -1;
    /* bucket (record, path) of an entry: its key's top field and its bottom one */
    const int shr = a->total - t->bits[F_REC];
    const uint64_t pm = ((uint64_t)1 << bp) - 1;
#define TT_BUCKET(k) ((int64_t)(((uint64_t)((k) >> shr) << bp) | ((uint64_t)(k) & pm)))
    int32_t *h = t->hist;
    memset(h, 0, sizeof(int32_t) * (nb + 1));
    for (int64_t i = 0; i < n; i++) h[TT_BUCKET(a->key[i]) + 1]++;
    for (int64_t b = 0; b < nb; b++) h[b + 1] += h[b];
    for (int64_t i = 0; i < n; i++) t->perm[h[TT_BUCKET(a->key[i])]++] = (int32_t)i;
    /* the buckets in order: a key's rows of one bucket summed into one (the bucket's first rows
     * are its keys so far: a short linear search, buckets hold a path's few entries) */
    int64_t *st = t->starts + t->ngroups * (t->nrec + 1), r0 = 0, cur = -1, first = t->nrows;
    tt_row *out = t->rows;
    for (int64_t at = 0; at < n; at++) {
        int64_t i = t->perm[at], b = TT_BUCKET(a->key[i]);
        if (at + TT_AHEAD < n) { /* the entry TT_AHEAD ahead: its key and both lines its 24 bytes may touch */
            const int64_t j = t->perm[at + TT_AHEAD];
            __builtin_prefetch(a->key + j), __builtin_prefetch(a->val + 3 * j), __builtin_prefetch(a->val + 3 * j + 2);
        }
        if (b != cur) {
            for (int64_t r = b >> bp; r0 <= r; r0++) st[r0] = t->nrows; /* records up to b's start here */
            cur = b, first = t->nrows;
        }
        u128 k = a->key[i] >> bp;
        int64_t x = t->nrows - 1;
        while (x >= first && out[x].k != k) x--;
        if (x < first) {
            x = t->nrows++;
            out[x].k = k;
            for (int c = 0; c < 3; c++) out[x].s[c] = 0.0;
        }
        for (int c = 0; c < 3; c++) out[x].s[c] += a->val[3 * i + c];
    }
#undef TT_BUCKET
    for (; r0 <= t->nrec; r0++) st[r0] = t->nrows;
    t->ngroups++;
    if (a->max_count > t->max_count) t->max_count = a->max_count;
    return 0;
}

static inline uint64_t tt_hash(u128 k) { return ((uint64_t)k ^ (uint64_t)(k >> 64)) * 0x9E3779B97F4A7C15ull; }

/* the tile's sums per key, record by record (once; later adds are refused). 0 or -1. */
static int tt_finish(tb_tile *t) {
    if (t->done) return 0;
    int64_t most = 0; /* the most rows of one record: the hash table's size */
    for (int64_t r = 0; r < t->nrec; r++) {
        int64_t m = 0;
        for (int64_t g = 0; g < t->ngroups; g++) m += t->starts[g * (t->nrec + 1) + r + 1] - t->starts[g * (t->nrec + 1) + r];
        if (m > most) most = m;
    }
    int lg = 4;
    while (((int64_t)1 << lg) < 2 * most) lg++;
    const int64_t cap = (int64_t)1 << lg;
    u128 *hk = (u128 *)malloc(sizeof(u128) * cap);
    int64_t *hv = (int64_t *)malloc(sizeof(int64_t) * cap), *used = (int64_t *)malloc(sizeof(int64_t) * cap);
    tt_sum *sums = (tt_sum *)malloc(sizeof(tt_sum) * (t->nrows ? t->nrows : 1)); /* U <= rows */
    if (!hk || !hv || !used || !sums) {
        free(hk), free(hv), free(used), free(sums);
        return -1;
    }
    for (int64_t i = 0; i < cap; i++) hk[i] = TT_EMPTY;
    int64_t U = 0;
    for (int64_t r = 0; r < t->nrec; r++) {
        int64_t nu = 0;
        for (int64_t g = 0; g < t->ngroups; g++) {
            const int64_t *st = t->starts + g * (t->nrec + 1);
            for (int64_t e = st[r]; e < st[r + 1]; e++) {
                const tt_row *row = t->rows + e;
                int64_t i = (int64_t)(tt_hash(row->k) >> (64 - lg));
                while (hk[i] != row->k && hk[i] != TT_EMPTY) i = (i + 1) & (cap - 1);
                if (hk[i] == TT_EMPTY) {
                    hk[i] = row->k, hv[i] = U, used[nu++] = i;
                    sums[U].k = row->k;
                    for (int c = 0; c < 3; c++) sums[U].s[c] = 0.0, sums[U].q[c] = 0.0;
                    U++;
                }
                tt_sum *s = sums + hv[i];
                for (int c = 0; c < 3; c++) {
                    double v = row->s[c];
                    s->s[c] += v, s->q[c] += v * v;
                }
            }
        }
        for (int64_t x = 0; x < nu; x++) hk[used[x]] = TT_EMPTY;
    }
    free(hk), free(hv), free(used);
    free(t->rows), free(t->starts);
    t->rows = NULL, t->starts = NULL, t->nrows = t->rows_room = t->ngroups = t->starts_room = 0;
    t->sums = sums, t->U = U, t->done = 1;
    return 0;
}

/* the tile's keys (after its sums are finished); -1 out of memory */
int64_t tb_tile_size(tb_tile *t) { return tt_finish(t) ? -1 : t->U; }
int tb_tile_max_count(const tb_tile *t) { return t->max_count; }

/* The tile's keys and sums: fields_out (U, 5 + M) int64 (rec, obj, bounce, j, w, counts) and
 * vals_out (U, 6) float64 (sums, then sums of per-path squares), ascending as tb_reduce returns them (count digits last object first, or first object first
 * when forward). Returns U; -1 out of memory. */
int64_t tb_tile_export(tb_tile *t, int forward, int64_t *fields_out, double *vals_out) {
    if (tt_finish(t)) return -1;
    const int64_t U = t->U;
    const int M = t->M, K = NFIXED + M;
    item *x, *y, *sorted;
    int64_t cnt[2048];
    x = (item *)malloc(sizeof(item) * (U ? U : 1)), y = (item *)malloc(sizeof(item) * (U ? U : 1));
    if (!x || !y) {
        free(x), free(y);
        return -1;
    }
    tb_acc shape; /* forward_key's view of the tile's widths (no path field) */
    memset(&shape, 0, sizeof(shape));
    shape.M = M, shape.bc = t->bc;
    for (int64_t u = 0; u < U; u++) x[u].k = forward ? forward_key(&shape, t->sums[u].k) : t->sums[u].k, x[u].s = u;
    sorted = U ? sort128(x, y, U, t->total, cnt) : x;
    for (int64_t o = 0; o < U; o++) {
        const tt_sum *s = t->sums + sorted[o].s;
        u128 k = s->k;
        int64_t *row = fields_out + o * K;
        for (int m = 0; m < M; m++, k >>= t->bc) row[NFIXED + m] = (int64_t)(k & field_mask(t->bc));
        for (int d = NFIXED - 1; d >= 0; d--) {
            row[d] = (int64_t)(k & field_mask(t->bits[d]));
            k >>= t->bits[d];
        }
        row[F_W] -= 1;
        for (int c = 0; c < 3; c++) vals_out[6 * o + c] = s->s[c], vals_out[6 * o + 3 + c] = s->q[c];
    }
    free(x), free(y);
    return U;
}

/* A tile's sparse blocks straight from its sums (tb_blocks' output without the fields export
 * and without sorting keys): per (eye object, bounce) block in ascending order, the records that
 * occur (ascending: the sums are record by record, and a stable counting sort by block keeps
 * that), the terms (w, counts) in tb_blocks' order (w, then the count digits last object first
 * when the block's code fits, else first object first; distinct terms found with a small hash
 * table, then sorted), and the entries in ascending local key (j Z + z) P + p by a stable
 * counting sort over (j, z) of the rows in record order; means and variances as tb_blocks.
 * Out: key (U,) int64; vals, var (3 U) float32 block after block, each (3, E); upix (U,) int64
 * block after block (P each); tw (U,) int64 and tc (U, M) int8 the terms, block after block (Z
 * each); meta (obj, bounce, E, P, Z) int64 per block (room blocks). Returns the number of
 * blocks; -1 out of memory; -2 fields too wide (tb_blocks' limits). */
static int tt_u128_cmp(const void *x, const void *y) {
    u128 a = *(const u128 *)x, b = *(const u128 *)y;
    return a < b ? -1 : a > b;
}

int64_t tb_tile_blocks(tb_tile *t, const int64_t *spp_rec, int64_t spp, int64_t room, int64_t *key, float *mean_out,
                       float *var_out, int64_t *upix, int64_t *tw, int8_t *tc, int64_t *meta) {
    if (tt_finish(t)) return -1;
    const int M = t->M, bc = t->bc, bo = t->bits[F_OBJ], bb = t->bits[F_BOUNCE], bj = t->bits[F_J], bw = t->bits[F_W];
    if (bo + bb > 20 || t->bits[F_REC] > 24) return -2;
    const int s_w = M * bc, s_j = s_w + bw, s_b = s_j + bj, s_r = s_b + bo + bb;
    const int64_t U = t->U, nblk = (int64_t)1 << (bo + bb);
    const u128 cmask = field_mask(bc);
    int64_t *hb = (int64_t *)calloc(nblk + 1, sizeof(int64_t)), *maxc = (int64_t *)calloc(nblk, sizeof(int64_t));
    int64_t *jmax = (int64_t *)calloc(nblk, sizeof(int64_t));
    int32_t *ord = (int32_t *)malloc(sizeof(int32_t) * (U ? U : 1)), *zid = (int32_t *)malloc(sizeof(int32_t) * (U ? U : 1));
    int32_t *ord2 = (int32_t *)malloc(sizeof(int32_t) * (U ? U : 1)), *prank = (int32_t *)malloc(sizeof(int32_t) * (U ? U : 1));
    int64_t hcap = 1024, *jh = NULL, jh_room = 0, nb = 0;
    u128 *hk = (u128 *)malloc(sizeof(u128) * hcap), *terms = (u128 *)malloc(sizeof(u128) * (U ? U : 1));
    int32_t *hv = (int32_t *)malloc(sizeof(int32_t) * hcap), *zrank = (int32_t *)malloc(sizeof(int32_t) * (U ? U : 1));
    u128 *sorted_terms = (u128 *)malloc(sizeof(u128) * (U ? U : 1));
    if (!hb || !maxc || !jmax || !ord || !zid || !ord2 || !prank || !hk || !terms || !hv || !zrank || !sorted_terms) {
        nb = -1;
        goto done;
    }
    if (U >= INT32_MAX) {
        nb = -2;
        goto done;
    }
    const tt_sum *S = t->sums;
    for (int64_t i = 0; i < U; i++) { /* per block: rows, largest count digit, largest j */
        u128 k = S[i].k;
        int64_t b = (int64_t)((k >> s_b) & field_mask(bo + bb)), j = (int64_t)((k >> s_j) & field_mask(bj));
        hb[b + 1]++;
        for (int m = 0; m < M; m++) {
            int64_t c = (int64_t)((k >> (m * bc)) & cmask);
            if (c > maxc[b]) maxc[b] = c;
        }
        if (j > jmax[b]) jmax[b] = j;
    }
    for (int64_t b = 0; b < nblk; b++) hb[b + 1] += hb[b];
    {
        int64_t *at = (int64_t *)malloc(sizeof(int64_t) * (nblk ? nblk : 1));
        if (!at) {
            nb = -1;
            goto done;
        }
        memcpy(at, hb, sizeof(int64_t) * nblk);
        for (int64_t i = 0; i < U; i++) ord[at[(int64_t)((S[i].k >> s_b) & field_mask(bo + bb))]++] = (int32_t)i;
        free(at);
    }
    int64_t at_e = 0, at_p = 0, at_z = 0;
    for (int64_t b = 0; b < nblk; b++) {
        const int64_t i0 = hb[b], i1 = hb[b + 1], E = i1 - i0;
        if (!E) continue;
        if (nb >= room) {
            nb = -1;
            goto done;
        }
        const int fwd = !fits_code(M, maxc[b]);
        /* records (ascending in ord) and their ranks */
        int64_t P = 0, prev = -1;
        for (int64_t i = i0; i < i1; i++) {
            int64_t r = (int64_t)(S[ord[i]].k >> s_r);
            if (r != prev) upix[at_p + P++] = r, prev = r;
            prank[i] = (int32_t)(P - 1);
        }
        /* terms: (w + 1, digits in the block's order) -> first-seen id, then their ascending rank */
        for (int64_t x = 0; x < hcap; x++) hk[x] = TT_EMPTY;
        int64_t Z = 0;
        int lg = __builtin_ctzll((unsigned long long)hcap);
        for (int64_t i = i0; i < i1; i++) {
            u128 k = S[ord[i]].k, term = (k & field_mask(s_w + bw));
            if (fwd) { /* first object most significant */
                u128 d = 0;
                for (int m = 0; m < M; m++) d = (d << bc) | ((k >> (m * bc)) & cmask);
                term = ((term >> s_w) << s_w) | d;
            }
            if (2 * (Z + 1) > hcap) { /* grow the term table (rehash the terms so far) */
                int64_t nc = 2 * hcap;
                u128 *k2 = (u128 *)malloc(sizeof(u128) * nc);
                int32_t *v2 = (int32_t *)malloc(sizeof(int32_t) * nc);
                if (!k2 || !v2) {
                    free(k2), free(v2);
                    nb = -1;
                    goto done;
                }
                int nlg = lg + 1;
                for (int64_t x = 0; x < nc; x++) k2[x] = TT_EMPTY;
                for (int64_t z = 0; z < Z; z++) {
                    int64_t x = (int64_t)(tt_hash(terms[z]) >> (64 - nlg));
                    while (k2[x] != TT_EMPTY) x = (x + 1) & (nc - 1);
                    k2[x] = terms[z], v2[x] = (int32_t)z;
                }
                free(hk), free(hv);
                hk = k2, hv = v2, hcap = nc, lg = nlg;
            }
            int64_t x = (int64_t)(tt_hash(term) >> (64 - lg));
            while (hk[x] != term && hk[x] != TT_EMPTY) x = (x + 1) & (hcap - 1);
            if (hk[x] == TT_EMPTY) hk[x] = term, hv[x] = (int32_t)Z, terms[Z++] = term;
            zid[i] = hv[x];
        }
        memcpy(sorted_terms, terms, sizeof(u128) * Z);
        qsort(sorted_terms, Z, sizeof(u128), tt_u128_cmp);
        for (int64_t z = 0; z < Z; z++) { /* rank of each first-seen id; the terms out in rank order */
            int64_t x = (int64_t)(tt_hash(sorted_terms[z]) >> (64 - lg));
            while (hk[x] != sorted_terms[z]) x = (x + 1) & (hcap - 1);
            zrank[hv[x]] = (int32_t)z;
            u128 term = sorted_terms[z];
            tw[at_z + z] = (int64_t)((term >> s_w) & field_mask(bw)) - 1;
            for (int m = 0; m < M; m++) { /* digit of object m: packed last object first, or first first */
                int sh = fwd ? (M - 1 - m) * bc : m * bc;
                tc[(at_z + z) * M + m] = (int8_t)((term >> sh) & cmask);
            }
        }
        /* entries by (j Z + z), stable over the rows' record order: ascending (j Z + z) P + p */
        const int64_t nk = (jmax[b] + 1) * Z;
        float *mo = mean_out + 3 * at_e, *vo = var_out + 3 * at_e;
        if (nk > 8 * E + (1 << 20)) { /* too many buckets for a counting sort: a radix sort of the keys */
            item64 *x = (item64 *)malloc(sizeof(item64) * E), *y = (item64 *)malloc(sizeof(item64) * E);
            int64_t cnt[2048];
            if (!x || !y) {
                free(x), free(y);
                nb = -1;
                goto done;
            }
            int kbits = 1;
            for (int64_t i = i0; i < i1; i++) {
                int64_t j = (int64_t)((S[ord[i]].k >> s_j) & field_mask(bj));
                uint64_t k = (uint64_t)((j * Z + zrank[zid[i]]) * P + prank[i]);
                x[i - i0].k = k, x[i - i0].s = i;
                while (kbits < 64 && (k >> kbits)) kbits++;
            }
            item64 *ks = sort64(x, y, E, kbits, cnt);
            for (int64_t e = 0; e < E; e++) ord2[i0 + e] = (int32_t)ks[e].s, zid[ks[e].s] = -1, key[at_e + e] = (int64_t)ks[e].k;
            free(x), free(y);
        } else {
        if (jh_room < nk + 1) {
            free(jh);
            jh = (int64_t *)malloc(sizeof(int64_t) * (nk + 1)), jh_room = jh ? nk + 1 : 0;
            if (!jh) {
                nb = -1;
                goto done;
            }
        }
        memset(jh, 0, sizeof(int64_t) * (nk + 1));
        for (int64_t i = i0; i < i1; i++) {
            int64_t j = (int64_t)((S[ord[i]].k >> s_j) & field_mask(bj));
            zid[i] = (int32_t)(j * Z + zrank[zid[i]]); /* now the (j, z) bucket */
            jh[zid[i] + 1]++;
        }
        for (int64_t q = 0; q < nk; q++) jh[q + 1] += jh[q];
        for (int64_t i = i0; i < i1; i++) ord2[i0 + jh[zid[i]]++] = (int32_t)i;
        for (int64_t e = 0; e < E; e++) key[at_e + e] = (int64_t)zid[ord2[i0 + e]] * P + prank[ord2[i0 + e]];
        }
        for (int64_t e = 0; e < E; e++) {
            int64_t i = ord2[i0 + e];
            const tt_sum *s = S + ord[i];
            if (e + TT_AHEAD < E) { /* the sums TT_AHEAD entries ahead (64 bytes: up to two lines) */
                const char *ahead = (const char *)(S + ord[ord2[i0 + e + TT_AHEAD]]);
                __builtin_prefetch(ahead), __builtin_prefetch(ahead + sizeof(tt_sum) - 1);
            }
            int64_t n = spp_rec ? spp_rec[(int64_t)(s->k >> s_r)] : spp;
            double dn = (double)n, dof = (double)(n - 1 < 1 ? 1 : n - 1);
            for (int c = 0; c < 3; c++) {
                double mu = s->s[c] / dn, q = (s->q[c] / dn - mu * mu) / dof;
                mo[c * E + e] = (float)mu, vo[c * E + e] = (float)(q < 0 ? 0.0 : q);
            }
        }
        int64_t *mt = meta + 5 * nb;
        mt[0] = b >> bb, mt[1] = b & (((int64_t)1 << bb) - 1), mt[2] = E, mt[3] = P, mt[4] = Z;
        at_e += E, at_p += P, at_z += Z, nb++;
    }
done:
    free(hb), free(maxc), free(jmax), free(ord), free(zid), free(ord2), free(prank), free(hk), free(terms), free(hv);
    free(zrank), free(sorted_terms), free(jh);
    return nb;
}

/* ---- The GI tracer's wavefront in reused buffers (tracer.py _Tracer._run_wavefront)
 *
 * The sampling side of a bounce without torch ops between the steps: the random numbers are drawn
 * here from the bytes of torch's CPU generator state (Generator.get_state(), written back after
 * the wavefront), the light samples that reach their vertex are gathered with their diffuse
 * factor, and the paths whose next ray hits are compacted in place into the wavefront's buffers
 * (allocated once per tracer, sized by the largest wavefront), instead of torch.rand, boolean
 * indexing and fresh tensors per step. The arithmetic is the per-vertex steps' above (tb_frame,
 * tb_area_sample, tb_layers, tb_mixture, tb_advance), called on those buffers, so the tensors
 * are the same bit for bit. */

/* torch's CPU generator (ATen CPUGeneratorImpl: at::mt19937) as Generator.get_state() lays it
 * out (CPUGeneratorImplState: initial seed int64 at byte 0, left int32 at 8, seeded int32 at 12,
 * next uint64 at 16, state uint64[624] at 24). torch.rand fills a tensor element after element
 * (row-major) from one serial engine: float32 as (u32 & 0xFFFFFF) * 2^-24, float64 as
 * ((u32 << 32 | u32') & (2^53 - 1)) * 2^-53, the first draw the high word. _native.py checks
 * once per process that this equals torch.rand bit for bit on a copy of a generator. */
enum { MT_N = 624, MT_M = 397, GS_LEFT = 8, GS_NEXT = 16, GS_STATE = 24 };
typedef struct {
    uint32_t s[MT_N]; /* the engine's words (what get_state holds) */
    uint32_t t[MT_N]; /* the same words tempered, drawn in order */
    int32_t left;
    uint64_t next;
} tb_mt;

static void mt_temper(tb_mt *g) { /* all 624 at once: a loop the compiler vectorises */
    for (int i = 0; i < MT_N; i++) {
        uint32_t y = g->s[i];
        y ^= (y >> 11);
        y ^= (y << 7) & 0x9d2c5680u;
        y ^= (y << 15) & 0xefc60000u;
        g->t[i] = y ^ (y >> 18);
    }
}

static void mt_load(tb_mt *g, const uint8_t *b) {
    memcpy(&g->left, b + GS_LEFT, 4), memcpy(&g->next, b + GS_NEXT, 8);
    for (int i = 0; i < MT_N; i++) {
        uint64_t v;
        memcpy(&v, b + GS_STATE + 8 * i, 8);
        g->s[i] = (uint32_t)v;
    }
    mt_temper(g);
}

static void mt_store(const tb_mt *g, uint8_t *b) {
    memcpy(b + GS_LEFT, &g->left, 4), memcpy(b + GS_NEXT, &g->next, 8);
    for (int i = 0; i < MT_N; i++) {
        uint64_t v = g->s[i];
        memcpy(b + GS_STATE + 8 * i, &v, 8);
    }
}

static inline uint32_t mt_twist(uint32_t u, uint32_t v) {
    return ((((u & 0x80000000u) | (v & 0x7fffffffu)) >> 1) ^ ((v & 1u) ? 0x9908b0dfu : 0u));
}

static void mt_refill(tb_mt *g) { /* at::mt19937::next_state */
    uint32_t *p = g->s;
    g->left = MT_N, g->next = 0;
    for (int j = MT_N - MT_M + 1; --j; p++) *p = p[MT_M] ^ mt_twist(p[0], p[1]);
    for (int j = MT_M; --j; p++) *p = p[MT_M - MT_N] ^ mt_twist(p[0], p[1]);
    *p = p[MT_M - MT_N] ^ mt_twist(p[0], g->s[0]);
}

static inline uint32_t mt_u32(tb_mt *g) {
    if (--g->left == 0) mt_refill(g), mt_temper(g);
    return g->t[g->next++];
}

static inline float mt_f32(tb_mt *g) { return (float)(mt_u32(g) & 0xFFFFFFu) * (1.0f / 16777216.0f); }

static inline double mt_f64(tb_mt *g) {
    uint64_t hi = mt_u32(g), lo = mt_u32(g);
    return (double)(((hi << 32) | lo) & ((1ull << 53) - 1)) * (1.0 / 9007199254740992.0);
}

/* torch.rand(n, generator=g, dtype=float64 if dbl else float32) into out, drawn from and
 * advancing the state bytes gs (Generator.get_state()). */
void tb_rand(uint8_t *gs, int64_t n, int dbl, void *out) {
    tb_mt g;
    mt_load(&g, gs);
    if (dbl)
        for (int64_t i = 0; i < n; i++) ((double *)out)[i] = mt_f64(&g);
    else
        for (int64_t i = 0; i < n; i++) ((float *)out)[i] = mt_f32(&g);
    mt_store(&g, gs);
}

/* The path state of a wavefront, one row per live path (tracer.py PathState): idx, m1 (int64),
 * raw (3 float32), A_i (La int64), A_w (La x 3), B_i (Lb), B_w (Lb x 3), counts (M int8), and the
 * vertex the path is at: d_in, pos, ng, ns (3 float32 each), oid (int64). */
typedef struct {
    int64_t *idx, *m1, *A_i, *B_i, *oid;
    float *raw, *A_w, *B_w, *d_in, *pos, *ng, *ns;
    int8_t *counts;
    float *frame, *wo; /* the vertex's shading frame (9) and wo (3): tb_frame's outputs */
    int64_t La, Lb, M;
} tb_wf;

/* row `from` of the path state into row `to` < from (distinct rows: plain loops, no libc call
 * per field) */
static void wf_copy_row(const tb_wf *s, int64_t to, int64_t from) {
    const int64_t La = s->La, Lb = s->Lb, M = s->M;
    s->idx[to] = s->idx[from], s->m1[to] = s->m1[from];
    for (int c = 0; c < 3; c++) s->raw[3 * to + c] = s->raw[3 * from + c];
    for (int64_t l = 0; l < La; l++) s->A_i[La * to + l] = s->A_i[La * from + l];
    for (int64_t l = 0; l < 3 * La; l++) s->A_w[3 * La * to + l] = s->A_w[3 * La * from + l];
    for (int64_t l = 0; l < Lb; l++) s->B_i[Lb * to + l] = s->B_i[Lb * from + l];
    for (int64_t l = 0; l < 3 * Lb; l++) s->B_w[3 * Lb * to + l] = s->B_w[3 * Lb * from + l];
    for (int64_t l = 0; l < M; l++) s->counts[M * to + l] = s->counts[M * from + l];
}

/* the vertex of ray i (its hit) into row h; its frame comes after, in wf_frames */
static inline void wf_vertex(const tb_wf *s, int64_t h, int64_t i, const float *d, const int64_t *obj,
                             const float *hpos, const float *hng, const float *hns) {
    for (int c = 0; c < 3; c++) {
        s->d_in[3 * h + c] = d[3 * i + c], s->pos[3 * h + c] = hpos[3 * i + c];
        s->ng[3 * h + c] = hng[3 * i + c], s->ns[3 * h + c] = hns[3 * i + c];
    }
    s->oid[h] = obj[i];
}

/* The frames of rows 0..h-1 in a pass of their own, after the rows are in place:
 * no branch on which rays hit, so the loop runs without mispredictions (and GCC's AVX2 copy
 * vectorises what it can); tb_frame's operations, so the same bits */
TB_SIMD static void wf_frames(int64_t h, const float *restrict d, float *restrict ng, float *restrict ns,
                              float *restrict fr, float *restrict wo) {
    for (int64_t i = 0; i < h; i++) frame_row(d + 3 * i, ng + 3 * i, ns + 3 * i, fr + 9 * i, wo + 3 * i);
}

static tb_wf wf_make(void *const *p, int64_t La, int64_t Lb, int64_t M) {
    tb_wf s = {(int64_t *)p[0], (int64_t *)p[1], (int64_t *)p[2],  (int64_t *)p[3], (int64_t *)p[4],
               (float *)p[5],   (float *)p[6],   (float *)p[7],    (float *)p[8],   (float *)p[9],
               (float *)p[10],  (float *)p[11],  (int8_t *)p[12],  (float *)p[13],  (float *)p[14],
               La,              Lb,              M};
    return s;
}

/* The eye vertices: rays 0..n-1 (directions d (n, 3)) whose closest hit obj[i] >= 0 (hit
 * positions and normals hpos, hng, hns (n, 3)) start paths (PathState.start: idx = ray, m1 = the
 * object, raw 1, A (0, 1), B (-1, 1), counts 0) in the state buffers p (15 pointers in tb_wf's
 * order), each vertex with its shading frame (tb_frame: normals flipped). Returns the paths. */
int64_t tb_wf_start(int64_t n, const float *d, const int64_t *obj, const float *hpos, const float *hng,
                    const float *hns, void *const *p, int64_t La, int64_t Lb, int64_t M) {
    tb_wf s = wf_make(p, La, Lb, M);
    int64_t h = 0;
    for (int64_t i = 0; i < n; i++) {
        if (obj[i] < 0) continue;
        s.idx[h] = i, s.m1[h] = obj[i];
        for (int c = 0; c < 3; c++) s.raw[3 * h + c] = 1.0f;
        for (int64_t l = 0; l < La; l++) s.A_i[La * h + l] = 0;
        for (int64_t l = 0; l < 3 * La; l++) s.A_w[3 * La * h + l] = 1.0f;
        for (int64_t l = 0; l < Lb; l++) s.B_i[Lb * h + l] = -1;
        for (int64_t l = 0; l < 3 * Lb; l++) s.B_w[3 * Lb * h + l] = 1.0f;
        memset(s.counts + M * h, 0, M);
        wf_vertex(&s, h, i, d, obj, hpos, hng, hns);
        h++;
    }
    wf_frames(h, s.d_in, s.ng, s.ns, s.frame, s.wo);
    return h;
}

/* After a bounce's trace: ray i (n rays, directions d (n, 3)) continued path a[i] (increasing
 * rows of the state); the paths whose ray hit (obj[i] >= 0) keep their rows, compacted in place
 * (row h <- row a[i], h <= a[i]: no row is overwritten before it is read), with their new vertex
 * and its frame. Returns the live paths (tracer.py: st.keep(a[hit]), the gathers of the hits and
 * tb_frame). */
int64_t tb_wf_compact(int64_t n, const int64_t *a, const float *d, const int64_t *obj, const float *hpos,
                      const float *hng, const float *hns, void *const *p, int64_t La, int64_t Lb, int64_t M) {
    tb_wf s = wf_make(p, La, Lb, M);
    int64_t h = 0;
    for (int64_t i = 0; i < n; i++) {
        if (obj[i] < 0) continue;
        if (a[i] != h) wf_copy_row(&s, h, a[i]);
        wf_vertex(&s, h, i, d, obj, hpos, hng, hns);
        h++;
    }
    wf_frames(h, s.d_in, s.ng, s.ns, s.frame, s.wo);
    return h;
}

/* The light samples that reach their vertex: candidates k (m,) of tb_area_sample (per vertex
 * dir, weight (n, 3), cos (n,)), occluded ones (occ (m,) bytes) dropped, in order, gathered as
 * tb_unoccluded + tb_light_gather do (kk, wl, wo_k, ob, ed, lw = (weight cos) / reps); with
 * `diffuse` also the factor of a diffuse-equivalent vertex (tracer.py _diffuse_f): 1/pi for
 * editable objects, else the fixed BRDF (mode (O,): 1 Lambertian, reflectance lambert (O, 3),
 * else 1), into f (m, 3). Returns the samples. */
int64_t tb_wf_light_hits(int64_t m, const int64_t *k, const uint8_t *occ, const float *dir, const float *weight,
                         const float *cosv, float reps, const float *frame, const float *wo, const int64_t *oid,
                         const uint8_t *editable, int diffuse, const int32_t *mode, const float *lambert, int64_t *kk,
                         float *wl, float *wo_k, int64_t *ob, uint8_t *ed, float *lw, float *f) {
    const float inv_pi = (float)(1.0 / 3.14159265358979323846);
    int64_t h = 0;
    for (int64_t i = 0; i < m; i++) {
        if (occ[i]) continue;
        int64_t r = k[i];
        kk[h] = r;
        float *l = wl + 3 * h;
        const float *o = wo + 3 * r;
        to_local(frame + 9 * r, dir + 3 * r, l);
        for (int c = 0; c < 3; c++) wo_k[3 * h + c] = o[c], lw[3 * h + c] = (weight[3 * r + c] * cosv[r]) / reps;
        int64_t b = oid[r];
        ob[h] = b, ed[h] = editable[b] != 0;
        if (diffuse) {
            int up = l[2] > 0 && o[2] > 0;
            for (int c = 0; c < 3; c++)
                f[3 * h + c] = ed[h] ? inv_pi
                               : mode[b] == 1 ? (up ? lambert[3 * b + c] / (float)3.14159265358979323846 : 0.0f)
                                              : 1.0f;
        }
        h++;
    }
    return h;
}

/* the area-light samples work in chunks of this many vertices: their points on the light and
 * candidate rows stay in the stack (L1) between the passes */
enum { AS_CHUNK = 256 };

/* the light's triangle at u0: searchsorted(cdf, u0, right=True) clamped to T - 1, by halving
 * with selects */
static inline int64_t area_triangle(double u0, const double *cdf, int64_t T) {
    int64_t a = 0, len = T;
    while (len > 0) {
        int64_t half = len >> 1, go = cdf[a + half] <= u0;
        a = go ? a + half + 1 : a;
        len = go ? len - half - 1 : half;
    }
    return a < T - 1 ? a : T - 1;
}

/* The samples' arithmetic for b vertices at once, given their points on the light lp (b, 3) and
 * its normals there nl (b, 3) (area_light_point): dir, weight, cos per vertex, and per vertex
 * (not yet compacted) whether it is a candidate, its shadow-ray origin and t_max. No
 * branch on the sample's values (~20 ns per vertex, not ~45 with them), and the uniforms and
 * the point on the light in their own pass, which leaves one straight loop of
 * float operations with no loop-carried value: GCC's AVX2 copy computes 8 vertices per
 * instruction (the divisions and square roots are the latency). The passes change no IEEE
 * operation and no order, so the bits are those of one loop per vertex. */
TB_SIMD static void area_sample_math(int64_t b, const float *restrict lp, const float *restrict nl,
                                     const float *restrict radiance, float area, const float *restrict pos,
                                     const float *restrict ng, const float *restrict ns, float eps,
                                     float *restrict dir, float *restrict weight, float *restrict cosv,
                                     int32_t *restrict cand, float *restrict so, float *restrict tmax) {
    const float tiny = 1.17549435e-38f, lo_cos = (float)1e-12, lo_pdf = (float)1e-30;
    const float r0 = radiance[0], r1 = radiance[1], r2 = radiance[2];
    for (int64_t i = 0; i < b; i++) {
        const float *p = pos + 3 * i, *n = nl + 3 * i, *g = ng + 3 * i, *s = ns + 3 * i;
        float d0 = lp[3 * i] - p[0], d1 = lp[3 * i + 1] - p[1], d2_ = lp[3 * i + 2] - p[2];
        float d2 = (d0 * d0 + d1 * d1) + d2_ * d2_, r = sqrtf(d2), den = r < tiny ? tiny : r;
        float w0 = d0 / den, w1 = d1 / den, w2 = d2_ / den;
        dir[3 * i] = w0, dir[3 * i + 1] = w1, dir[3 * i + 2] = w2;
        float cl = -((w0 * n[0] + w1 * n[1]) + w2 * n[2]);
        int valid = (cl > 0) & (r > 0);
        float pv = d2 / ((cl < lo_cos ? lo_cos : cl) * area), pdf = valid ? pv : 0.0f, pc = pdf < lo_pdf ? lo_pdf : pdf;
        float q0 = r0 / pc, q1 = r1 / pc, q2 = r2 / pc;
        weight[3 * i] = valid ? q0 : 0.0f, weight[3 * i + 1] = valid ? q1 : 0.0f, weight[3 * i + 2] = valid ? q2 : 0.0f;
        float cs = (w0 * s[0] + w1 * s[1]) + w2 * s[2], cg = (w0 * g[0] + w1 * g[1]) + w2 * g[2];
        cosv[i] = cs;
        cand[i] = pdf > 0 ? (cs > 0) & (cg > 0) : 0; /* (cs > 0) & (cg > 0) & (pdf > 0): GCC 12 vectorises this form */
        float side = cg >= 0 ? eps : -eps;
        so[3 * i] = p[0] + side * g[0], so[3 * i + 1] = p[1] + side * g[1], so[3 * i + 2] = p[2] + side * g[2];
        tmax[i] = r - 2 * eps;
    }
}

/* the point on the light at uniforms (u0, u1, u2) into lp (3), the normal of its triangle into
 * nl (3) */
static inline void area_light_point(double u0, double u1, double u2, const double *cdf, int64_t T, const float *tri,
                                    const float *nrm, float *lp, float *nl) {
    double sq = sqrt(u1), b1 = 1 - sq, b2 = u2 * sq;
    const int64_t kt = area_triangle(u0, cdf, T);
    const float *t = tri + 9 * kt;
    for (int c = 0; c < 3; c++) {
        double t0 = t[c], t1 = t[3 + c], t2 = t[6 + c];
        lp[c] = (float)((t0 + b1 * (t1 - t0)) + b2 * (t2 - t0)), nl[c] = nrm[3 * kt + c];
    }
}

/* The samples of tb_area_sample / tb_wf_area_sample, their uniforms read from u (n, 3) or, when
 * g, drawn from it. Chunk by chunk: each vertex's point on the light, area_sample_math, then the
 * candidates compacted (every row written, kept by m += cand: no branch). */
static int64_t area_samples(tb_mt *g, const double *u, int64_t n, const double *cdf, int64_t T, const float *tri,
                            const float *nrm, const float *radiance, float area, const float *pos, const float *ng,
                            const float *ns, float eps, float *dir, float *weight, float *cosv, int64_t *k, float *so,
                            float *sd, float *tmax) {
    float lp[3 * AS_CHUNK], nl[3 * AS_CHUNK], so_c[3 * AS_CHUNK], tmax_c[AS_CHUNK];
    int32_t cand[AS_CHUNK];
    int64_t m = 0;
    for (int64_t i0 = 0; i0 < n; i0 += AS_CHUNK) {
        const int64_t b = n - i0 < AS_CHUNK ? n - i0 : AS_CHUNK;
        for (int64_t j = 0; j < b; j++) {
            const double *ui = u ? u + 3 * (i0 + j) : NULL;
            double u0 = g ? mt_f64(g) : ui[0], u1 = g ? mt_f64(g) : ui[1], u2 = g ? mt_f64(g) : ui[2];
            area_light_point(u0, u1, u2, cdf, T, tri, nrm, lp + 3 * j, nl + 3 * j);
        }
        area_sample_math(b, lp, nl, radiance, area, pos + 3 * i0, ng + 3 * i0, ns + 3 * i0, eps, dir + 3 * i0,
                         weight + 3 * i0, cosv + i0, cand, so_c, tmax_c);
        for (int64_t j = 0; j < b; j++) {
            const float *w = dir + 3 * (i0 + j);
            for (int c = 0; c < 3; c++) so[3 * m + c] = so_c[3 * j + c], sd[3 * m + c] = w[c];
            tmax[m] = tmax_c[j], k[m] = i0 + j;
            m += cand[j];
        }
    }
    return m;
}

/* An area light's next-event samples from every vertex (lights.py AreaLight.sample_points and
 * sample, pathtrace.py sample_light and Scene.visible's shadow ray): u (n, 3) float64 uniforms
 * (drawn by torch, as the torch path draws them); cdf (T,) float64, tri (T, 3, 3), nrm (T, 3),
 * radiance (3,) float32; pos, ng, ns (n, 3). Out per vertex: dir (n, 3), weight (n, 3), cos (n,);
 * the candidates (cos > 0, light in front of ng, pdf > 0) compacted: rows k (m,), shadow-ray
 * origins so (m, 3) (spawned off the surface by eps), directions sd (m, 3) = dir[k] and
 * t_max (m,) = dist - 2 eps.
 * Returns m. */
int64_t tb_area_sample(int64_t n, const double *u, const double *cdf, int64_t T, const float *tri, const float *nrm,
                       const float *radiance, float area, const float *pos, const float *ng, const float *ns, float eps,
                       float *dir, float *weight, float *cosv, int64_t *k, float *so, float *sd, float *tmax) {
    return area_samples(NULL, u, n, cdf, T, tri, nrm, radiance, area, pos, ng, ns, eps, dir, weight, cosv, k, so, sd,
                        tmax);
}

/* tb_area_sample with its uniforms drawn here, vertex after vertex, from the generator's state
 * bytes gs (torch.rand(n, 3, dtype=float64)'s numbers in its order), not read from an array. */
int64_t tb_wf_area_sample(uint8_t *gs, int64_t n, const double *cdf, int64_t T, const float *tri, const float *nrm,
                          const float *radiance, float area, const float *pos, const float *ng, const float *ns,
                          float eps, float *dir, float *weight, float *cosv, int64_t *k, float *so, float *sd,
                          float *tmax) {
    tb_mt g;
    mt_load(&g, gs);
    int64_t m = area_samples(&g, NULL, n, cdf, T, tri, nrm, radiance, area, pos, ng, ns, eps, dir, weight, cosv, k, so,
                             sd, tmax);
    mt_store(&g, gs);
    return m;
}
