/* The compiled kernel of torch_brdf's precomputations: what every file of it shares.
 *
 * The kernel is a plain C library (no Python or torch headers) built on first use by
 * transport/_native.py with the system compiler and called through ctypes; every entry point
 * below has one ctypes signature in scene/_bindings.py (tests/transport/test_kernel_bindings.py
 * checks the two agree) and a pure-torch twin that gives the same result (docs/kernel.md).
 *
 * Files by job:
 *   rng.c         torch's CPU random generator (mt19937) drawn from its state bytes
 *   sort.c        stable radix sorts and run merges of packed keys
 *   reduce.c      the tracer's entries and their per-key sums (an accumulator of packed keys)
 *   blocks.c      sparse blocks from per-key sums
 *   tile.c        a tile's per-key sums gathered record by record, and its sparse blocks
 *   lights.c      area-light next-event samples
 *   camera.c      eye rays of a pass group
 *   vertex.c      the GI tracer's per-vertex steps (frame, bands, direction mixture, advance)
 *   wavefront.c   the GI tracer's path state in reused buffers
 *   visibility.c  visibility cubemaps: ray fans cast into embree
 *   rays.c        the GI tracer's closest-hit and shadow rays cast into embree
 *
 * Floating point: built with -ffp-contract=off and without -ffast-math (no fused multiply-add,
 * no reassociation), so every float32/float64 operation is IEEE's, in the order written, which
 * is the torch code's order: the entries and sums equal the torch path's bit for bit.
 * -fno-math-errno and -fno-trapping-math change no value; they let sqrtf inline and let selects
 * replace branches so the loops vectorise. Only the entry points are exported (the build uses
 * -fvisibility=hidden); the functions shared between files stay hidden. */
#ifndef TORCH_BRDF_KERNEL_H
#define TORCH_BRDF_KERNEL_H

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define TB_API __attribute__((visibility("default")))

/* Loops of the sampling side written to vectorise (branch-free passes over arrays) are built
 * twice, for AVX2 and for the baseline x86-64 (SSE2), and the loader picks the copy the CPU can
 * run (GCC's target_clones: an ifunc resolved once). The two copies do the same IEEE operations
 * in the same order (no FMA: -ffp-contract=off), so they give the same bits: the result does not
 * depend on the CPU. Other compilers and CPUs: one plain copy. */
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__)
#define TB_SIMD __attribute__((target_clones("avx2", "default")))
#else
#define TB_SIMD
#endif

typedef unsigned __int128 u128;

static inline u128 field_mask(int b) { return (((u128)1) << b) - 1; }

/* ---- packed keys (reduce.c, blocks.c, tile.c) ------------------------------------------------ */

enum { F_REC, F_OBJ, F_BOUNCE, F_J, F_W, NFIXED };

/* An accumulator of entries keyed by (rec, obj, bounce, j, w + 1, per-object counts[, path]),
 * each key packed into one 128-bit integer field by field (record most significant). */
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

typedef struct tb_tile tb_tile; /* tile.c */

typedef struct {
    u128 k;
    int64_t s;
} item; /* a key and its arrival index */

typedef struct {
    uint64_t k;
    int64_t s;
} item64; /* the same for keys of at most 64 bits (half the bytes to move) */

/* the key with its count digits in the other order (first object most significant) */
static inline u128 forward_key(const tb_acc *a, u128 k) {
    int M = a->M, bc = a->bc, bp = a->bp;
    u128 path = bp ? k & field_mask(bp) : 0, out = k >> (bp + M * bc);
    for (int m = 0; m < M; m++) out = (out << bc) | ((k >> (bp + m * bc)) & field_mask(bc));
    return bp ? (out << bp) | path : out;
}

/* whether the multiset code (base max_count + 1, M digits) of _multiset_ids fits in 62 bits:
 * then its count digits order a block's terms last object first, else first object first */
static inline int fits_code(int M, int64_t max_count) {
    double b = (double)(max_count + 1 < 2 ? 2 : max_count + 1);
    return M * log2(b) < 62;
}

/* sort.c: stable LSD radix sorts of x (n items, keys of `total` bits; y scratch) and stable
 * merges of the sorted runs at[0..runs) of x; each returns the array (x or y) holding the result */
item64 *sort64(item64 *x, item64 *y, int64_t n, int total, int64_t *cnt);
item *sort128(item *x, item *y, int64_t n, int total, int64_t *cnt);
item64 *merge64(item64 *x, item64 *y, int64_t n, int64_t *at, int64_t runs);
item *merge128(item *x, item *y, int64_t n, int64_t *at, int64_t runs);

/* ---- the shading frame (vertex.c, wavefront.c) ----------------------------------------------- */

static inline float dot3(const float *a, const float *b) { return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]; }
static inline float sqrt0f(float x) { return x > 0 ? sqrtf(x) : 0.0f; }

/* frame.py Frame.to_local with the (n, 9) rows s, t, n */
static inline void to_local(const float *fr, const float *v, float *out) {
    out[0] = dot3(v, fr), out[1] = dot3(v, fr + 3), out[2] = dot3(v, fr + 6);
}

/* pathtrace.py shading_frame: flipped normals (in place), the frame (n, 9: s, t, n) from the
 * shading normal (frame.py orthonormal_basis, Duff et al. 2017) and wo = to_local(-d_in). */
static inline void frame_row(const float *d, float *g, float *s, float *fr, float *wo) {
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

/* ---- torch's CPU random generator (rng.c; drawn from in lights.c) ----------------------------
 * ATen's CPUGeneratorImpl (at::mt19937) as Generator.get_state() lays it out
 * (CPUGeneratorImplState: initial seed int64 at byte 0, left int32 at 8, seeded int32 at 12,
 * next uint64 at 16, state uint64[624] at 24). torch.rand fills a tensor element after element
 * (row-major) from one serial engine: float32 as (u32 & 0xFFFFFF) * 2^-24, float64 as
 * ((u32 << 32 | u32') & (2^53 - 1)) * 2^-53, the first draw the high word. */
enum { MT_N = 624, MT_M = 397, GS_LEFT = 8, GS_NEXT = 16, GS_STATE = 24 };
typedef struct {
    uint32_t s[MT_N]; /* the engine's words (what get_state holds) */
    uint32_t t[MT_N]; /* the same words tempered, drawn in order */
    int32_t left;
    uint64_t next;
} tb_mt;

void mt_load(tb_mt *g, const uint8_t *b);  /* the engine from state bytes */
void mt_store(const tb_mt *g, uint8_t *b); /* and back */
void mt_refill(tb_mt *g);                  /* the next 624 words, tempered */

static inline uint32_t mt_u32(tb_mt *g) {
    if (--g->left == 0) mt_refill(g);
    return g->t[g->next++];
}

static inline float mt_f32(tb_mt *g) { return (float)(mt_u32(g) & 0xFFFFFFu) * (1.0f / 16777216.0f); }

static inline double mt_f64(tb_mt *g) {
    uint64_t hi = mt_u32(g), lo = mt_u32(g);
    return (double)(((hi << 32) | lo) & ((1ull << 53) - 1)) * (1.0 / 9007199254740992.0);
}

/* ---- embree's ray (visibility.c, rays.c) ------------------------------------------------------
 * The layout of embree 4's RTCRay; the caller passes the committed scene's handle and the
 * address of rtcOccluded1 / rtcIntersect1 (scene/parallel.py: embree_entry, embree_function). */
typedef struct __attribute__((aligned(16))) {
    float org_x, org_y, org_z, tnear, dir_x, dir_y, dir_z, time, tfar;
    uint32_t mask, id, flags;
} tb_ray;
typedef void (*tb_occluded1)(void *scene, tb_ray *ray, void *args);

/* ---- the entry points, file by file (shapes and returns: at each definition) ----------------- */

/* rng.c */
TB_API void tb_rand(uint8_t *gs, int64_t n, int dbl, void *out);
/* reduce.c */
TB_API tb_acc *tb_new(int M, int V, const int32_t *bits);
TB_API void tb_free(tb_acc *a);
TB_API void tb_clear(tb_acc *a);
TB_API int64_t tb_size(const tb_acc *a);
TB_API int tb_max_count(const tb_acc *a);
TB_API int tb_add_sums(tb_acc *a, int64_t n, const int64_t *rec, const int64_t *obj, const int64_t *bounce,
                       const int64_t *j, const int64_t *w, const int8_t *counts, const double *wd);
TB_API int tb_emit(tb_acc *a, int64_t n, int64_t bounce, int64_t p, const int64_t *kk, const float *raw,
                   const int64_t *idx, const int64_t *rec, const int64_t *m1, const int8_t *counts, const int64_t *ob,
                   const uint8_t *ed, const float *lw, const float *f, const float *scale, int64_t nscale, int64_t La,
                   const int64_t *xi, const float *xw, int x_rows, int64_t Lb, const int64_t *yi, const float *yw,
                   int y_rows);
TB_API int tb_reduce(tb_acc *a, int forward, int64_t *fields_out, double *sums_out, int64_t *u);
TB_API int tb_reduce_into(tb_acc *a, int forward, tb_acc *into);
/* blocks.c */
TB_API int64_t tb_blocks(int64_t U, int M, const int32_t *bits, const int64_t *fields, const double *vals,
                         const int64_t *spp_rec, int64_t spp, int64_t room, int64_t *key, float *mean_out,
                         float *var_out, int64_t *upix, int64_t *term_row, int64_t *meta);
/* tile.c */
TB_API tb_tile *tb_tile_new(int M, const int32_t *bits);
TB_API void tb_tile_free(tb_tile *t);
TB_API int tb_tile_add(tb_tile *t, const tb_acc *a);
TB_API int64_t tb_tile_size(tb_tile *t);
TB_API int tb_tile_max_count(const tb_tile *t);
TB_API int64_t tb_tile_export(tb_tile *t, int forward, int64_t *fields_out, double *vals_out);
TB_API int64_t tb_tile_blocks(tb_tile *t, const int64_t *spp_rec, int64_t spp, int64_t room, int64_t *key,
                              float *mean_out, float *var_out, int64_t *upix, int64_t *tw, int8_t *tc, int64_t *meta);
/* lights.c */
TB_API void tb_area_points(int64_t n, const double *u, const double *s, const double *cdf, int64_t T, const float *tri,
                           const float *points, float *d, float *d2, int64_t *idx);
TB_API void tb_area_finish(int64_t n, const float *d, const float *d2, const float *dist, const int64_t *idx,
                           const float *nrm, const float *radiance, float area, const float *ng, const float *ns,
                           float *dir, float *weight, float *pdf, float *cosv, uint8_t *ok);
TB_API int64_t tb_area_sample(int64_t n, const double *u, const double *cdf, int64_t T, const float *tri,
                              const float *nrm, const float *radiance, float area, const float *pos, const float *ng,
                              const float *ns, float eps, float *dir, float *weight, float *cosv, int64_t *k, float *so,
                              float *sd, float *tmax);
TB_API int64_t tb_wf_area_sample(uint8_t *gs, int64_t n, const double *cdf, int64_t T, const float *tri,
                                 const float *nrm, const float *radiance, float area, const float *pos, const float *ng,
                                 const float *ns, float eps, float *dir, float *weight, float *cosv, int64_t *k,
                                 float *so, float *sd, float *tmax);
/* camera.c */
TB_API int64_t tb_camera_local(int64_t n, const int64_t *rec, const int64_t *pixels, int64_t W, int64_t H,
                               const double *off, double tan_half, double aspect, double *local);
TB_API void tb_camera_finish(int64_t n, const double *d, const double *norm, const double *origin, float *o,
                             float *dir);
/* vertex.c */
TB_API void tb_frame(int64_t n, const float *d_in, float *ng, float *ns, float *frame, float *wo);
TB_API int64_t tb_unoccluded(int64_t m, const int64_t *k, const uint8_t *occ, int64_t *out);
TB_API void tb_light_gather(int64_t m, const int64_t *kk, const float *dir, const float *weight, const float *cosv,
                            float reps, const float *frame, const float *wo, const int64_t *oid,
                            const uint8_t *editable, float *wl, float *wo_k, int64_t *ob, uint8_t *ed, float *lw);
TB_API void tb_layers(int64_t n, int L, int64_t fill, const int32_t *spec, const float *edges, const float *lambert,
                      const int64_t *oid, const float *wi, const float *wo, int64_t *idx, float *w);
TB_API void tb_sincos(int64_t n, const float *x, float *c, float *s);
TB_API TB_SIMD void tb_mixture(int64_t n, const float *u, const float *wo, float diffuse, float gloss,
                               float exponent, float norm, float *wi, float *pdf, float *cosw, uint8_t *ok);
TB_API int64_t tb_advance(int64_t n, const float *wi, const float *cosw, const uint8_t *ok, const float *f, int count,
                          const int64_t *oid, const uint8_t *editable, int M, int8_t *counts, float *raw,
                          const float *frame, const float *ng, const float *pos, int64_t La, const float *A_w,
                          int64_t Lb, const float *B_w, float eps, int64_t *a, float *so, float *sd);
TB_API void tb_fixed_f(int64_t n, const int32_t *mode, const float *lambert, const int64_t *oid, const float *wi,
                       const float *wo, float *f);
TB_API void tb_gather(int64_t m, const int64_t *rows, int k, char *const *src, char *const *dst,
                      const int64_t *rowbytes);
/* wavefront.c */
TB_API int64_t tb_wf_start(int64_t n, const float *d, const int64_t *obj, const float *hpos, const float *hng,
                           const float *hns, void *const *p, int64_t La, int64_t Lb, int64_t M);
TB_API int64_t tb_wf_compact(int64_t n, const int64_t *a, const float *d, const int64_t *obj, const float *hpos,
                             const float *hng, const float *hns, void *const *p, int64_t La, int64_t Lb, int64_t M);
TB_API int64_t tb_wf_light_hits(int64_t m, const int64_t *k, const uint8_t *occ, const float *dir, const float *weight,
                                const float *cosv, float reps, const float *frame, const float *wo, const int64_t *oid,
                                const uint8_t *editable, int diffuse, const int32_t *mode, const float *lambert,
                                int64_t *kk, float *wl, float *wo_k, int64_t *ob, uint8_t *ed, float *lw, float *f);
/* visibility.c */
TB_API int64_t tb_vis_fans(void *scene, void *fn, int64_t m, const float *origins, const double *normals, int64_t T,
                           const double *centres, const float *dirs, int64_t k2, double eps, int64_t side,
                           int16_t *counts, uint8_t *index, float *frac);
TB_API int64_t tb_occluded_fans(void *scene, void *fn, int64_t m, const float *origins, const int64_t *counts,
                                const uint16_t *texel, const float *dirs, uint8_t *out);
/* rays.c */
TB_API int64_t tb_trace_hits(void *scene, void *fn, int64_t n, const float *o, const float *d, const float *table,
                             const int64_t *offsets, const uint8_t *flat, float *t, int64_t *obj, int64_t *prim,
                             float *bary, float *pos, float *ng, float *ns);
TB_API int64_t tb_occluded_rays(void *scene, void *fn, int64_t n, const float *o, const float *d, int64_t D,
                                const int64_t *rows, const float *tmax, uint8_t *out);
TB_API int64_t tb_intersect_only(void *scene, void *fn, int64_t n, const float *o, const float *d, const float *tfar,
                                 int32_t *geom);

/* ---- relight.c ------------------------------------------------------------------------------- */
TB_API TB_SIMD void tb_phong_lobe(int64_t n, const float *omc, float exponent, float *out);
TB_API int tb_relight(int64_t P, int NB, const float *nrm, const float *fs, const float *ft, const float *fn,
                      const float *wo, const int32_t *obj, const float *prm, const int32_t *lv, float a0, float a1,
                      const uint8_t *states, const int64_t *offsets, const uint8_t *index, const int16_t *delta,
                      float levels, const float *const *pts, const float *const *G, const float *M, const float *I,
                      const float *const *J, float *out, int64_t *stats);

#endif
