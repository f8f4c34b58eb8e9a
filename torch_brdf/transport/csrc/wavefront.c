/* The GI tracer's wavefront in reused buffers (polynomial/tracer.py _Tracer._run_wavefront).
 *
 * The sampling side of a bounce without torch ops between the steps: the random numbers are drawn
 * here from the bytes of torch's CPU generator state (rng.c; Generator.get_state(), written back
 * after the wavefront), the light samples that reach their vertex are gathered with their diffuse
 * factor, and the paths whose next ray hits are compacted in place into the wavefront's buffers
 * (allocated once per tracer, sized by the largest wavefront), instead of torch.rand, boolean
 * indexing and fresh tensors per step. The arithmetic is the per-vertex steps' (tb_frame,
 * tb_area_sample, tb_layers, tb_mixture, tb_advance), called on those buffers, so the tensors
 * are the same bit for bit as with those steps. */
#include "kernel.h"

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

/* the frames of rows 0..h-1 in a pass of their own, after the rows are in place:
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
