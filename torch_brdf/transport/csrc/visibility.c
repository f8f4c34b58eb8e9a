/* Visibility cubemaps (transport/visibility.py): fans of rays cast into embree.
 *
 * The rays go to embree's rtcOccluded1 directly: the caller passes the committed scene's
 * handle and the function's address (scene/parallel.py: embree_entry), so the query per ray is
 * the one embreex's EmbreeScene.run makes (origin, direction, tnear 0, tfar 1e37, mask ~0, time
 * 0, flags 0; occluded when embree sets tfar to -inf), in the same order, without a Python call,
 * an (n, 3) array or a result array per fan. The ray layout is embree 4's RTCRay (kernel.h). */
#include "kernel.h"

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
