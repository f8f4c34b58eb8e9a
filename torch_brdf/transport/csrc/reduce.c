/* The entries of the multibounce precomputation, made and summed per key.
 *
 * The compiled twin of the tracer's _Tracer._emit + _Entries (polynomial/tracer.py) and of
 * polynomial/reduce.py's _reduce: each light sample at a vertex adds, per layer combination
 * (a, b), one entry with weight ((base * X[a]) * Y[b]) (float32, in that order, as the torch path
 * multiplies) and key (record, eye object, bounce, j, w, per-object counts, path); a pass group's
 * entries are then summed per key in float64 in the order they were made (as torch's index_add_
 * sums them).
 *
 * A key is packed into one 128-bit integer field by field (record most significant, path least;
 * the widths come from the caller), so integer order is reduce.py's radix-key order. The sums
 * come from a stable LSD radix sort of (key, arrival index) (sort.c) and one pass over the sorted
 * keys, so each key's sum adds its entries in arrival order: the output equals the torch path bit
 * for bit. The count digits are packed last object most significant, the order of
 * _multiset_ids' base-(max + 1) code; when that code would not fit in 62 bits, torch numbers
 * multisets with unique(dim=0) (first object first) and the keys are repacked before sorting. */
#include "kernel.h"

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
