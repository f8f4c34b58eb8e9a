/* GI ray casting (transport/rays.py).
 *
 * The GI tracer's closest-hit rays and shadow rays, cast straight into embree as the visibility
 * fans of visibility.c are (the scene handle and rtcIntersect1 / rtcOccluded1 from the library embreex
 * loaded: scene/parallel.py), with the hit interpolation of scene/parallel.py's
 * TraceKernel._hits fused in: the same query per ray as EmbreeScene.run (tnear 0, tfar as given,
 * mask ~0, time 0, flags 0, hit ids and instID[0] invalid), the same per-triangle table (3 x
 * (vertex, vertex normal), unit face normal; 21 floats a row) and the same float32 formulas in
 * the same order, one ray at a time instead of numpy's passes over arrays. */
#include "kernel.h"

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
    /* Two passes: the embree calls first (t, obj, prim, bary), then the interpolation of every
     * ray from those, so the rows' arithmetic (and its sqrtf's latency) does not sit between one
     * embree call and the next, and the second loop has no call. */
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
