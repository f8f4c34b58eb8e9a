/* relight.c: one relighting frame of locally adaptive triple products (Inger et al., Algorithm 1)
 * over a range of shaded vertices, and the Phong lobe it evaluates.
 *
 * The twin is TripleProductRenderer.shade_torch (render/triple.py); the Python side
 * (render/_relight.py) hands over per-vertex frames, the vertex visibility in CSR form and the
 * block lighting re-expressed per sample (G_l = inverse_l^T DCT_l, W_l = inverse_l^T B_l, both
 * computed once per lighting change), so that every BRDF projection of Sec. 4.1 folds into the
 * lighting: a block costs one dot product per sample, not a projection and a contraction.
 *
 * Per vertex: (1) the level of every unoccluded-or-partial block (the Appendix A rule as a
 * per-object table: near / mid / far levels by the angle between the view direction and the
 * block centre reflected about the normal); (2) every sample direction of those blocks in one
 * array; (3) the BRDF at all of them in one branch-free loop (TB_SIMD: vectorised, the AVX2 copy
 * picked at load time); (4) the block products: line 6 (unoccluded: f . (n . G_l), or the texel
 * sum with the 256 samples), line 9 (constant BRDF: f (n . sum_e v_e I_e)) and line 11 (at 4 or
 * 16 samples the same sum over the flips with J_l, the suffix sums of W_l M, W_l taking samples to
 * texels; at 256 samples the visibility expanded from its flips and the texel sum). Vertices are independent:
 * callers split them over threads (ctypes releases the GIL).
 *
 * The Phong lobe cos^n(alpha) = exp(n log1p(-omc)) uses its own log and exp (polynomials on a
 * reduced range, no libm), so the loop vectorises; their error is below 1.5e-7 relative (log)
 * and 2e-7 relative (exp), tighter than the paper's Remez powf approximation (Sec. 5). Sums run
 * in another order than torch's and the lobe is not libm's: the frame agrees with the torch path
 * to float32 rounding of the sums (tests/render/test_relight_native.py states the tolerance). */
#include "kernel.h"

enum { RL_CH = 3, RL_S = 256 };

static const float RL_PI = 3.14159265358979323846f;
static const float RL_HORIZON = 1e-4f;

/* log(u) for u in (0, 1]: u = m 2^e, m in [sqrt(1/2), sqrt(2)), log m = 2 atanh(z), z = (m-1)/(m+1),
 * |z| <= 0.1716: the odd series to z^9 is exact to 4e-10 relative. */
static inline float rl_log(float u) {
    union {
        float f;
        uint32_t i;
    } b = {u};
    int32_t e = (int32_t)((b.i >> 23) & 0xff) - 127;
    b.i = (b.i & 0x007fffffu) | 0x3f800000u; /* m in [1, 2) */
    float m = b.f;
    int big = m > 1.41421356f;
    m = big ? 0.5f * m : m;
    e += big;
    float z = (m - 1.0f) / (m + 1.0f);
    float z2 = z * z;
    float p = 1.0f / 9.0f;
    p = p * z2 + 1.0f / 7.0f;
    p = p * z2 + 1.0f / 5.0f;
    p = p * z2 + 1.0f / 3.0f;
    p = p * z2 + 1.0f;
    return 2.0f * z * p + (float)e * 0.693147180559945309f;
}

/* exp(y) for y <= 0 (0 below -87.3, float32's normal range): y = k ln2 + r, |r| <= ln2/2, the
 * Taylor polynomial of degree 7 (error < 5e-9 relative) times 2^k set in the exponent bits. */
static inline float rl_exp(float y) {
    float yc = y < -87.3f ? -87.3f : y;
    float k = __builtin_roundf(yc * 1.44269504088896341f);
    float r = (yc - k * 0.693145751953125f) - k * 1.42860682030941723212e-6f; /* ln2 in two parts */
    float p = 1.0f / 5040.0f;
    p = p * r + 1.0f / 720.0f;
    p = p * r + 1.0f / 120.0f;
    p = p * r + 1.0f / 24.0f;
    p = p * r + 1.0f / 6.0f;
    p = p * r + 0.5f;
    p = p * r + 1.0f;
    p = p * r + 1.0f;
    union {
        uint32_t i;
        float f;
    } s;
    s.i = (uint32_t)((int32_t)k + 127) << 23;
    return y < -87.3f ? 0.0f : p * s.f;
}

/* cos^n(alpha) from omc = 1 - cos(alpha): exp(n log1p(-omc)), 0 where omc >= 1 (Phong._lobe).
 * log1p(-x) = log(u) * (-x) / (u - 1) with u = 1 - x rounded (Goldberg's log1p: the rounding
 * of u cancels), -x where u rounds to 1. */
static inline float rl_lobe(float omc, float n) {
    float x = omc < 0.0f ? 0.0f : omc;
    x = x > 0.99999988f ? 0.99999988f : x; /* 1 - float32 eps, as torch's clamp */
    float u = 1.0f - x;
    float um1 = u - 1.0f;
    float l = um1 == 0.0f ? -x : rl_log(u) * (-x / (um1 == 0.0f ? 1.0f : um1));
    float v = rl_exp(n * l);
    return omc < 1.0f ? v : 0.0f;
}

TB_API TB_SIMD void tb_phong_lobe(int64_t n, const float *omc, float exponent, float *out) {
    for (int64_t i = 0; i < n; i++) out[i] = rl_lobe(omc[i], exponent);
}

/* The BRDF (3 channels) at m world directions (SoA x, y, z) for one vertex: local directions in
 * the frame (s, t, nn), lifted above the horizon as the torch sampler does, then Lambert or Phong
 * (kind 0: kd / pi only; 1: Phong) with wo local. */
static TB_SIMD void rl_eval(int m, const float *x, const float *y, const float *z, const float *s, const float *t,
                            const float *nn, const float *wo, const float *prm, float *f0, float *f1, float *f2) {
    const float kd0 = prm[0] / RL_PI, kd1 = prm[1] / RL_PI, kd2 = prm[2] / RL_PI;
    const float ks0 = prm[3], ks1 = prm[4], ks2 = prm[5], n = prm[6];
    const float phong = prm[7];
    const float norm = (n + 2.0f) / (2.0f * RL_PI);
    const float up_o = wo[2] > 0.0f ? 1.0f : 0.0f;
    for (int i = 0; i < m; i++) {
        float lx = x[i] * s[0] + y[i] * s[1] + z[i] * s[2];
        float ly = x[i] * t[0] + y[i] * t[1] + z[i] * t[2];
        float lz = x[i] * nn[0] + y[i] * nn[1] + z[i] * nn[2];
        int below = !(lz > RL_HORIZON);
        float hz = below ? RL_HORIZON : lz;
        float inv = 1.0f / sqrtf(lx * lx + ly * ly + hz * hz);
        float sc = below ? inv : 1.0f;
        lx *= sc;
        ly *= sc;
        lz = below ? hz * inv : lz;
        float dx = lx + wo[0], dy = ly + wo[1], dz = lz - wo[2];
        float omc = 0.5f * (dx * dx + dy * dy + dz * dz);
        float spec = phong * norm * rl_lobe(omc, n);
        float up = lz > 0.0f ? up_o : 0.0f;
        f0[i] = up * (kd0 + spec * ks0);
        f1[i] = up * (kd1 + spec * ks1);
        f2[i] = up * (kd2 + spec * ks2);
    }
}

/* sum_i a[i] (n . T[:, c, i]) for the 3 channels of a (3, C, K) table at stride K */
static inline void rl_dot_table(int K, const float *f0, const float *f1, const float *f2, const float *T,
                                const float *nv, double *acc) {
    const float *fc[RL_CH] = {f0, f1, f2};
    for (int c = 0; c < RL_CH; c++) {
        const float *t0 = T + (0 * RL_CH + c) * K, *t1 = T + (1 * RL_CH + c) * K, *t2 = T + (2 * RL_CH + c) * K;
        float s = 0.0f;
        for (int i = 0; i < K; i++) s += fc[c][i] * (nv[0] * t0[i] + nv[1] * t1[i] + nv[2] * t2[i]);
        acc[c] += s;
    }
}

static inline int rl_level_index(int l) { return l == 1 ? 0 : l == 2 ? 1 : l == 4 ? 2 : 3; }

/* Shade vertices [0, P) (see the file comment); returns 0, or -1 when out of memory.
 *   nrm, fs, ft, fn, wo: (P, 3) world normal, local frame (s, t, n) and local outgoing direction
 *   obj: (P,) row of each vertex's object in prm (O, 8: kd[3], ks[3], exponent, phong 0/1) and
 *        lv (O, 3: the level near / mid / far; near == mid == far skips the angle)
 *   a0, a1: the rule's angles (radians); states (P, NB); offsets (P NB + 1) CSR starts into
 *   index (F) texel positions and delta (F) int16 level steps (NULL: binary, +1 -1 ... implied),
 *   levels: 2^bits - 1 of graded maps (a delta of k is k / levels)
 *   pts: 4 pointers, (NB, l^2, 3) world sample directions for l = 1, 2, 4, 16
 *   G: 3 pointers, (NB, l^2, 3, C) lighting per sample for l = 1, 2, 4 (line 6)
 *   M: (NB, 3, C, 256) moments (line 6 at 256 samples, line 11); I: (NB, 256, 3, C) suffix sums
 *   (line 9); J: 2 pointers, (NB, 256, l^2, 3, C) for l = 2, 4: the suffix sums over texels of
 *   W_l[s, t] M_t, W_l the sample-to-texel weights (line 11 at 4 and 16 samples)
 *   out: (P, 3); stats: 10 int64 added to: occluded, line6, line9, line11, sampling 1/4/16/256,
 *   brdf evaluations, visibility entries read */
TB_API int tb_relight(int64_t P, int NB, const float *nrm, const float *fs, const float *ft, const float *fn,
                      const float *wo, const int32_t *obj, const float *prm, const int32_t *lv, float a0, float a1,
                      const uint8_t *states, const int64_t *offsets, const uint8_t *index, const int16_t *delta,
                      float levels, const float *const *pts, const float *const *G, const float *M, const float *I,
                      const float *const *J, float *out, int64_t *stats) {
    int64_t room = (int64_t)NB * RL_S;
    float *buf = malloc(sizeof(float) * (size_t)(room * 6 + RL_S * 4));
    int *lev = malloc(sizeof(int) * (size_t)NB * 2);
    if (!buf || !lev) {
        free(buf);
        free(lev);
        return -1;
    }
    float *X = buf, *Y = X + room, *Z = Y + room, *F0 = Z + room, *F1 = F0 + room, *F2 = F1 + room;
    float *V = F2 + room, *T0 = V + RL_S, *T1 = T0 + RL_S, *T2 = T1 + RL_S;
    int *start = lev + NB;
    int64_t st[10] = {0};
    for (int64_t p = 0; p < P; p++) {
        const float *s = fs + 3 * p, *t = ft + 3 * p, *nn = fn + 3 * p, *w = wo + 3 * p, *nv = nrm + 3 * p;
        int o = obj[p];
        const int32_t *L = lv + 3 * o;
        const uint8_t *sp = states + p * NB;
        /* (1) levels and (2) sample directions */
        int m = 0;
        for (int b = 0; b < NB; b++) {
            if (!sp[b]) {
                lev[b] = 0;
                st[0]++;
                continue;
            }
            int l = L[2];
            if (!(L[0] == L[1] && L[1] == L[2])) {
                const float *c = pts[0] + 3 * b;
                float lx = c[0] * s[0] + c[1] * s[1] + c[2] * s[2];
                float ly = c[0] * t[0] + c[1] * t[1] + c[2] * t[2];
                float lz = c[0] * nn[0] + c[1] * nn[1] + c[2] * nn[2];
                if (!(lz > RL_HORIZON)) {
                    float inv = 1.0f / sqrtf(lx * lx + ly * ly + RL_HORIZON * RL_HORIZON);
                    lx *= inv;
                    ly *= inv;
                    lz = RL_HORIZON * inv;
                }
                float d = -lx * w[0] + -ly * w[1] + lz * w[2];
                float alpha = acosf(d < -1.0f ? -1.0f : d > 1.0f ? 1.0f : d);
                l = alpha < a0 ? L[0] : alpha < a1 ? L[1] : L[2];
            }
            int k = rl_level_index(l), n2 = l * l;
            lev[b] = l;
            start[b] = m;
            const float *src = pts[k] + (int64_t)b * n2 * 3;
            for (int i = 0; i < n2; i++) {
                X[m + i] = src[3 * i];
                Y[m + i] = src[3 * i + 1];
                Z[m + i] = src[3 * i + 2];
            }
            m += n2;
            st[4 + k]++;
        }
        /* (3) the BRDF at every sample */
        rl_eval(m, X, Y, Z, s, t, nn, w, prm + 8 * o, F0, F1, F2);
        st[8] += m;
        /* (4) the block products */
        double acc[RL_CH] = {0.0, 0.0, 0.0};
        for (int b = 0; b < NB; b++) {
            int l = lev[b];
            if (!l) continue;
            int n2 = l * l, k = rl_level_index(l);
            const float *f0 = F0 + start[b], *f1 = F1 + start[b], *f2 = F2 + start[b];
            const float *Mb = M + (int64_t)b * 3 * RL_CH * RL_S;
            if (sp[b] == 1) { /* line 6 */
                st[1]++;
                if (l == 16) {
                    rl_dot_table(RL_S, f0, f1, f2, Mb, nv, acc);
                } else {
                    const float *g = G[k] + (int64_t)b * n2 * 3 * RL_CH; /* (l^2, 3, C) */
                    for (int i = 0; i < n2; i++) {
                        const float *gi = g + i * 3 * RL_CH;
                        acc[0] += f0[i] * (nv[0] * gi[0] + nv[1] * gi[3] + nv[2] * gi[6]);
                        acc[1] += f1[i] * (nv[0] * gi[1] + nv[1] * gi[4] + nv[2] * gi[7]);
                        acc[2] += f2[i] * (nv[0] * gi[2] + nv[1] * gi[5] + nv[2] * gi[8]);
                    }
                }
                continue;
            }
            int64_t q = p * NB + b, e0 = offsets[q], e1 = offsets[q + 1];
            st[9] += e1 - e0;
            if (l == 1) { /* line 9: f (n . sum_e v_e I_e) */
                st[2]++;
                float irr[RL_CH] = {0.0f, 0.0f, 0.0f};
                for (int64_t e = e0; e < e1; e++) {
                    float v = delta ? (float)delta[e] / levels : ((e - e0) & 1 ? -1.0f : 1.0f);
                    const float *ie = I + ((int64_t)b * RL_S + index[e]) * 3 * RL_CH;
                    for (int c = 0; c < RL_CH; c++)
                        irr[c] += v * (nv[0] * ie[c] + nv[1] * ie[RL_CH + c] + nv[2] * ie[2 * RL_CH + c]);
                }
                acc[0] += f0[0] * irr[0];
                acc[1] += f1[0] * irr[1];
                acc[2] += f2[0] * irr[2];
                continue;
            }
            /* line 11: V from its flips, the BRDF on texels, the texel sum */
            st[3]++;
            memset(V, 0, sizeof(float) * RL_S);
            for (int64_t e = e0; e < e1; e++)
                V[index[e]] += delta ? (float)delta[e] / levels : ((e - e0) & 1 ? -1.0f : 1.0f);
            for (int i = 1; i < RL_S; i++) V[i] += V[i - 1];
            if (l < 16) { /* sum_e v_e sum_s f_s (n . J_l[b, idx_e, s]): V never expanded */
                int K = n2 * 3 * RL_CH;
                float Q[16 * 3 * RL_CH];
                for (int i = 0; i < K; i++) Q[i] = 0.0f;
                const float *Jb = J[k - 1] + (int64_t)b * RL_S * K;
                for (int64_t e = e0; e < e1; e++) {
                    float v = delta ? (float)delta[e] / levels : ((e - e0) & 1 ? -1.0f : 1.0f);
                    const float *je = Jb + (int64_t)index[e] * K;
                    for (int i = 0; i < K; i++) Q[i] += v * je[i];
                }
                for (int i = 0; i < n2; i++) {
                    const float *qi = Q + i * 3 * RL_CH;
                    acc[0] += f0[i] * (nv[0] * qi[0] + nv[1] * qi[3] + nv[2] * qi[6]);
                    acc[1] += f1[i] * (nv[0] * qi[1] + nv[1] * qi[4] + nv[2] * qi[7]);
                    acc[2] += f2[i] * (nv[0] * qi[2] + nv[1] * qi[5] + nv[2] * qi[8]);
                }
                continue;
            }
            memset(V, 0, sizeof(float) * RL_S);
            for (int64_t e = e0; e < e1; e++)
                V[index[e]] += delta ? (float)delta[e] / levels : ((e - e0) & 1 ? -1.0f : 1.0f);
            for (int i = 1; i < RL_S; i++) V[i] += V[i - 1];
            for (int i = 0; i < RL_S; i++) {
                T0[i] = V[i] * f0[i];
                T1[i] = V[i] * f1[i];
                T2[i] = V[i] * f2[i];
            }
            rl_dot_table(RL_S, T0, T1, T2, Mb, nv, acc);
        }
        for (int c = 0; c < RL_CH; c++) out[3 * p + c] = (float)acc[c];
    }
    for (int i = 0; i < 10; i++) stats[i] += st[i];
    free(buf);
    free(lev);
    return 0;
}
