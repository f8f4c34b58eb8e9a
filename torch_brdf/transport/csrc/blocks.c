/* A tile's sparse blocks (polynomial/reduce.py _local_blocks).
 *
 * From a tile's per-key sums (tb_reduce's output: fields (U, 5 + M) int64 rec, obj, bounce, j,
 * w, counts and values (U, 6) float64 sum, then sum of per-path squares), per (eye object,
 * bounce) block in ascending (object, bounce) order: the records that occur (upix, ascending),
 * the terms (w, counts) that occur in _local_blocks' order (w, then the multiset in
 * _multiset_ids' order: count digits last object first when that code fits in 62 bits for the
 * block's largest count, else first object first), and the entries in ascending local key
 * (j Z + z) P + p with their mean sum / spp and variance ((sq / spp - mean^2) / max(spp - 1, 1))
 * clamped at 0, in float64 then float32, as torch computes them (so the same bits).
 * bits: widths of rec, obj, bounce, j, w + 1 and one count digit (the tile's key_bits).
 * spp_rec (records,) int64 paths of each record, or NULL: spp for all.
 * Out (capacity U each): key (U,) int64; vals, var (3 U) float32, block after block, each (3, E)
 * row-major; upix (U,) int64 and term_row (U,) int64 (a row of `fields` holding the term),
 * block after block; meta (obj, bounce, E, P, Z) int64 per block (capacity: room blocks).
 * Returns the number of blocks; -1 out of memory; -2 fields too wide (torch does it then). */
#include "kernel.h"

int64_t tb_blocks(int64_t U, int M, const int32_t *bits, const int64_t *fields, const double *vals,
                  const int64_t *spp_rec, int64_t spp, int64_t room, int64_t *key, float *mean_out, float *var_out,
                  int64_t *upix, int64_t *term_row, int64_t *meta) {
    const int br = bits[F_REC], bo = bits[F_OBJ], bb = bits[F_BOUNCE], bj = bits[F_J], bw = bits[F_W], bc = bits[NFIXED];
    const int K = NFIXED + M, total = bo + bb + bw + M * bc + bj + br;
    if (bo + bb > 20 || br > 24 || total > 127) return -2;
    const int64_t nblk = (int64_t)1 << (bo + bb), nrec = (int64_t)1 << br;
    int64_t *maxc = (int64_t *)calloc(nblk, sizeof(int64_t));
    int32_t *rank = (int32_t *)malloc(sizeof(int32_t) * nrec);
    item *x = (item *)malloc(sizeof(item) * (U ? U : 1)), *y = (item *)malloc(sizeof(item) * (U ? U : 1)), *sorted;
    item64 *x2 = (item64 *)malloc(sizeof(item64) * (U ? U : 1)), *y2 = (item64 *)malloc(sizeof(item64) * (U ? U : 1));
    int64_t *cnt = (int64_t *)malloc(sizeof(int64_t) * 2048), *fin = (int64_t *)malloc(sizeof(int64_t) * (U ? U : 1));
    int64_t nb = 0;
    if (!maxc || !rank || !x || !y || !x2 || !y2 || !cnt || !fin) {
        nb = -1;
        goto done;
    }
    for (int64_t i = 0; i < U; i++) {
        const int64_t *f = fields + i * K;
        int64_t b = (f[F_OBJ] << bb) | f[F_BOUNCE];
        for (int m = 0; m < M; m++)
            if (f[NFIXED + m] > maxc[b]) maxc[b] = f[NFIXED + m];
    }
    /* order 1: (block, w + 1, multiset, j, rec): each block's terms contiguous and ascending */
    for (int64_t i = 0; i < U; i++) {
        const int64_t *f = fields + i * K;
        int64_t b = (f[F_OBJ] << bb) | f[F_BOUNCE];
        u128 k = ((u128)b << bw) | (u128)(f[F_W] + 1);
        if (fits_code(M, maxc[b]))
            for (int m = M - 1; m >= 0; m--) k = (k << bc) | (u128)f[NFIXED + m];
        else
            for (int m = 0; m < M; m++) k = (k << bc) | (u128)f[NFIXED + m];
        x[i].k = (((k << bj) | (u128)f[F_J]) << br) | (u128)f[F_REC], x[i].s = i;
    }
    sorted = U ? sort128(x, y, U, total, cnt) : x;
    const int tail = bj + br; /* the term is the key without (block) above and (j, rec) below it */
    const u128 term_mask = (((u128)1) << (bw + M * bc)) - 1;
    int64_t at = 0, up = 0;
    for (int64_t i0 = 0; i0 < U;) {
        const int64_t *f0 = fields + sorted[i0].s * K;
        const int64_t b = (f0[F_OBJ] << bb) | f0[F_BOUNCE];
        int64_t i1 = i0;
        while (i1 < U && (int64_t)(sorted[i1].k >> (tail + bw + M * bc)) == b) i1++;
        if (nb >= room) {
            nb = -1;
            goto done;
        }
        /* the block's records, ascending, and their ranks p */
        for (int64_t i = i0; i < i1; i++) rank[fields[sorted[i].s * K + F_REC]] = 1;
        int64_t P = 0;
        for (int64_t i = i0; i < i1; i++) { /* mark-and-count without scanning every record id */
            int64_t r = fields[sorted[i].s * K + F_REC];
            if (rank[r] == 1) rank[r] = -1, P++;
        }
        int64_t *pix = upix + up, np = 0;
        for (int64_t i = i0; i < i1; i++) {
            int64_t r = fields[sorted[i].s * K + F_REC];
            if (rank[r] == -1) pix[np++] = r, rank[r] = 0;
        }
        /* pix holds the distinct records in order of first appearance: sort them (radix) */
        for (int64_t q = 0; q < np; q++) x2[q].k = (uint64_t)pix[q], x2[q].s = q;
        item64 *ps = np ? sort64(x2, y2, np, br, cnt) : x2;
        for (int64_t q = 0; q < np; q++) pix[q] = (int64_t)ps[q].k, rank[pix[q]] = (int32_t)q;
        /* terms: z per row (order 1 is ascending in the term), the final key (j Z + z) P + p */
        int64_t Z = 0;
        u128 prev = 0;
        for (int64_t i = i0; i < i1; i++) {
            u128 t = (sorted[i].k >> tail) & term_mask;
            if (i == i0 || t != prev) term_row[up + Z] = sorted[i].s, Z++, prev = t;
            fin[i] = Z - 1; /* z for now */
        }
        int kbits = 1;
        for (int64_t i = i0; i < i1; i++) {
            const int64_t *f = fields + sorted[i].s * K;
            uint64_t k = (uint64_t)((f[F_J] * Z + fin[i]) * P + rank[f[F_REC]]);
            x2[i - i0].k = k, x2[i - i0].s = sorted[i].s;
            while (kbits < 64 && (k >> kbits)) kbits++;
        }
        const int64_t E = i1 - i0;
        item64 *ks = sort64(x2, y2, E, kbits, cnt);
        float *mo = mean_out + 3 * at, *vo = var_out + 3 * at;
        for (int64_t e = 0; e < E; e++) {
            int64_t r = ks[e].s;
            const double *v = vals + 6 * r;
            int64_t n = spp_rec ? spp_rec[fields[r * K + F_REC]] : spp;
            double dn = (double)n, dof = (double)(n - 1 < 1 ? 1 : n - 1);
            key[at + e] = (int64_t)ks[e].k;
            for (int c = 0; c < 3; c++) {
                double mu = v[c] / dn, q = (v[3 + c] / dn - mu * mu) / dof;
                mo[c * E + e] = (float)mu, vo[c * E + e] = (float)(q < 0 ? 0.0 : q);
            }
        }
        int64_t *mt = meta + 5 * nb;
        mt[0] = f0[F_OBJ], mt[1] = f0[F_BOUNCE], mt[2] = E, mt[3] = P, mt[4] = Z;
        /* term_row and upix share one offset per block: the larger of P and Z */
        for (int64_t q = Z; q < P; q++) term_row[up + q] = -1;
        for (int64_t q = P; q < Z; q++) upix[up + q] = -1;
        up += P > Z ? P : Z, at += E, nb++;
        i0 = i1;
    }
done:
    free(maxc), free(rank), free(x), free(y), free(x2), free(y2), free(cnt), free(fin);
    return nb;
}
