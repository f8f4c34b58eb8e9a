/* Next-event samples of an area light from float32 points (scene/lights.py AreaLight.sample_points
 * and AreaLight.sample, then pathtrace.py sample_light's cosines), operation for operation in
 * the torch code's order and precision (float64 points on the triangle, float32 after). The two
 * square roots stay in torch (its vectorised sqrt is not always the correctly rounded one), so
 * the results are the same bit for bit: tb_area_points, then dist = sqrt(d2) in torch, then
 * tb_area_finish.
 * tb_area_points: u (n, 3) float64 uniforms and s = sqrt(u[:, 1]) (n,) float64 (both from torch);
 * cdf (T,) float64; tri (T, 3, 3) float32; points (n, 3) float32 -> d (n, 3) = y - points and
 * d2 (n,) = |d|^2 float32, idx (n,) int64 the triangle.
 *
 * tb_area_sample and tb_wf_area_sample (below) take the whole sample of the GI tracer's vertices,
 * square roots included: one of vertex.c's per-vertex steps, which agree with the torch path to
 * float32 rounding, not bit for bit (tests/transport/test_vertex.py). */
#include "kernel.h"

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
 * (not yet compacted) whether it is a candidate, its shadow-ray origin and t_max. No branch on
 * the sample's values, and the uniforms and the point on the light come from their own pass:
 * one straight loop of float operations with no loop-carried value, which GCC's AVX2 copy
 * computes 8 vertices per instruction (the divisions and square roots are the latency). */
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
