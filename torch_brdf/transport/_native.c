/* The entries of the multibounce precomputation, made and summed per key (torch_brdf, #14).
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
 * Built on first use by _native.py with the system C compiler (-O2 -ffp-contract=off: no fused
 * multiply-add, IEEE float32 products as in torch) and called through ctypes.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

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
    free(a->key), free(a->val), free(a);
}

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
int tb_emit(tb_acc *a, int64_t n, int64_t bounce, int64_t p, const int64_t *kk, const float *raw, const int64_t *idx,
            const int64_t *rec, const int64_t *m1, const int8_t *counts, const int64_t *ob, const uint8_t *ed, const float *lw,
            const float *f, const float *scale, int64_t nscale, int64_t La, const int64_t *xi, const float *xw,
            int x_rows, int64_t Lb, const int64_t *yi, const float *yw, int y_rows) {
    int M = a->M, bad = 0;
    float *base = (float *)malloc(sizeof(float) * 3 * (n ? n : 1));
    if (!base || reserve(a, n * La * Lb)) {
        free(base);
        return -1;
    }
    for (int64_t i = 0; i < n; i++) {
        int64_t r = kk[i];
        for (int c = 0; c < 3; c++) {
            float v = raw ? raw[3 * r + c] * lw[3 * i + c] : lw[3 * i + c];
            if (f) v = v * f[3 * i + c];
            base[3 * i + c] = v;
        }
        if (scale) {
            int64_t e = 0;
            for (int m = 0; m < M; m++) e += counts[r * M + m];
            if (e < 0 || e >= nscale) {
                free(base);
                return -2;
            }
            for (int c = 0; c < 3; c++) base[3 * i + c] = base[3 * i + c] * scale[e];
        }
    }
    for (int64_t ia = 0; ia < La; ia++)
        for (int64_t ib = 0; ib < Lb; ib++)
            for (int64_t i = 0; i < n; i++) {
                int64_t r = kk[i], rx = x_rows ? r : i, ry = y_rows ? r : i;
                const float *x = xw + (rx * La + ia) * 3;
                float w3[3];
                for (int c = 0; c < 3; c++) {
                    float v = base[3 * i + c] * x[c];
                    w3[c] = yw ? v * yw[(ry * Lb + ib) * 3 + c] : v;
                }
                if (w3[0] != w3[0] || w3[1] != w3[1] || w3[2] != w3[2]) continue;
                if (!(w3[0] != 0.0f || w3[1] != 0.0f || w3[2] != 0.0f)) continue;
                int64_t ray = rec[idx[r]];
                int64_t fl[NFIXED] = {ray % p, m1[r], bounce, xi[rx * La + ia], yi ? yi[ry * Lb + ib] + 1 : 0};
                int inc = (ed && ed[i]) ? (int)ob[i] : -1;
                u128 k = pack(a, fl, counts + r * M, inc, ray / p, &bad);
                a->key[a->n] = k;
                double *v = a->val + a->n * a->V;
                for (int c = 0; c < 3; c++) v[c] = (double)w3[c];
                a->n++;
            }
    free(base);
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

/* Sum the entries per key: *u distinct keys in ascending order (count digits compared last
 * object first, or first object first when forward) into fields_out (n, 5 + M) int64 (rec,
 * obj, bounce, j, w, counts) and sums_out (n, V) float64 (first *u rows; room for n). Each
 * sum adds its entries in arrival order, starting from 0.0. Returns 0 or -1 (out of memory). */
int tb_reduce(const tb_acc *a, int forward, int64_t *fields_out, double *sums_out, int64_t *u) {
    int64_t n = a->n, o = 0;
    int small = a->total <= 64;
    size_t isz = small ? sizeof(item64) : sizeof(item);
    void *xv = malloc(isz * (n ? n : 1)), *yv = malloc(isz * (n ? n : 1));
    int64_t *cnt = (int64_t *)malloc(sizeof(int64_t) * 2048);
    if (!xv || !yv || !cnt) {
        free(xv), free(yv), free(cnt);
        return -1;
    }
    item *xw = (item *)xv, *yw = (item *)yv, *sw = NULL;
    item64 *xs = (item64 *)xv, *ys = (item64 *)yv, *ss = NULL;
    for (int64_t i = 0; i < n; i++) {
        u128 k = forward ? forward_key(a, a->key[i]) : a->key[i];
        if (small)
            xs[i].k = (uint64_t)k, xs[i].s = i;
        else
            xw[i].k = k, xw[i].s = i;
    }
    if (n && small)
        RADIX_SORT(item64, xs, ys, n, a->total, cnt, ss);
    else if (n)
        RADIX_SORT(item, xw, yw, n, a->total, cnt, sw);
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
        if (fresh) {
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
        double *s = sums_out + (o - 1) * V;
        const double *v = a->val + si * V;
        for (int c = 0; c < V; c++) s[c] += v[c];
    }
    *u = o;
    free(xv), free(yv), free(cnt);
    return 0;
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
void tb_area_points(int64_t n, const double *u, const double *s, const double *cdf, int64_t T, const float *tri,
                    const float *points, float *d, float *d2, int64_t *idx) {
    for (int64_t i = 0; i < n; i++) {
        double u0 = u[3 * i], b1 = 1 - s[i], b2 = u[3 * i + 2] * s[i];
        int64_t a = 0, b = T; /* searchsorted(right=True): the first cdf entry > u0 */
        while (a < b) {
            int64_t m = (a + b) / 2;
            if (cdf[m] <= u0)
                a = m + 1;
            else
                b = m;
        }
        int64_t k = a < T - 1 ? a : T - 1;
        const float *t = tri + 9 * k;
        float *di = d + 3 * i;
        for (int c = 0; c < 3; c++) {
            double t0 = t[c], t1 = t[3 + c], t2 = t[6 + c];
            float y = (float)((t0 + b1 * (t1 - t0)) + b2 * (t2 - t0));
            di[c] = y - points[3 * i + c];
        }
        d2[i] = (di[0] * di[0] + di[1] * di[1]) + di[2] * di[2];
        idx[i] = k;
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

/* ---- visibility cubemaps (transport/visibility.py, #14) ------------------------------------
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
