/* The per-vertex steps of the GI tracer (polynomial/tracer.py _Tracer.run).
 *
 * One call per step and wavefront instead of ~40 torch ops: the shading frame, the light
 * samples' local directions, the band slots and quotients of the editable objects (_Layers), the
 * direction mixture (sampler.py Mixture) and the path's advance (throughput, counts, world
 * direction, the next ray); an area light's next-event sample with its shadow ray is lights.c's.
 * Same formulas and operation order as the torch code, in float32 (float64 where it uses
 * float64), but libm's scalar sqrtf/atan2f/powf/expm1f/logf (and the mixture's own cos/sin:
 * sincos_fd) instead of torch's vectorised ones: results may differ from the torch path in the
 * last ulp (and a path that then lands on a band edge or grazes an edge of the geometry may take
 * the other side), so the tests compare them with tolerances and the exactness oracles
 * re-evaluate the paths this code traced. */
#include "kernel.h"

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
 * In blocks of MIX_B rows, as passes over the block: the angles of the sampler drawn and their
 * cos / sin (sincos_fd, no libm call), the lobe's sin^2 (logf, expm1f) on the lobe's rows only,
 * the directions and the pdf's diffuse term, the lobe's pdf term (powf) on the rows that need it,
 * then cos / pdf: no branch on the sample in the arithmetic passes, so they vectorise or at least
 * overlap (sincos_fd is within 0.5 ulp of cos / sin, where libm's sinf/cosf are within 0.56 ulp;
 * logf/expm1f/powf are libm's). */
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
