/* A pass group's eye rays (polynomial/driver.py eye_rays).
 *
 * camera.py Camera.rays_through at the raster positions driver.py _tile_entries makes, around the
 * two steps that stay torch's (the (n, 3) @ (3, 3) product and the row norms, whose BLAS and
 * vectorised reductions round their own way): the same float64 operations in the same order, so
 * the rays are the same bit for bit, with two passes instead of ~15 torch ops on fresh pages.
 * tb_camera_local: ray i at pixel pixels[rec[i]] (flat, row-major in a W x H image) with offsets
 * off[i] (row, column) in [0, 1): local (n, 3) = (sx, sy, 1). Returns 0, or -1 - i when ray i's
 * raster position is not finite. */
#include "kernel.h"

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
