/* A tile's sums per key, gathered record by record, and its sparse blocks.
 *
 * The twin of tb_reduce_into (a pass group's per-path sums appended as a sorted run) followed
 * by the tile's final merge (reduce_impl over the runs), without sorting keys: a pass group's
 * entries are bucketed by (record, path) with one stable counting sort (arrival order kept
 * within a bucket); each bucket's entries are summed per key in arrival order from 0.0 (the
 * path's sum s, as the group's sort summed it) and kept as rows (key, s), bucket by bucket, so
 * each group leaves its rows by record, paths ascending. When the tile is read (tt_finish),
 * each record's rows, group after group, are summed per key (s and s * s from 0.0) in a small
 * hash table that stays in cache. A key's tile sums thus add the per-path sums group by group
 * and within a group path by path ascending: the merged runs' order, the same sums bit for
 * bit. The keys leave the tile ascending as tb_reduce returns them (tb_tile_export);
 * tb_blocks does not depend on their order (it sorts by keys unique per row). */
#include "kernel.h"

#define TT_EMPTY (~(u128)0)   /* a free hash slot: no key has all 128 bits set (keys have <= 127) */
#define TT_AHEAD 32           /* rows prefetched ahead in the gathers of tb_tile_add and tb_tile_blocks */
#define TT_MAX_BUCKET_BITS 22 /* record + path bits of a group: its counting sort's buckets (16 MB) */

typedef struct __attribute__((aligned(16))) {
    u128 k; /* the key without its path field */
    double s[3];
} tt_row; /* one path's sum of a key */

typedef struct __attribute__((aligned(16))) {
    u128 k;
    double s[3], q[3];
} tt_sum; /* a key's tile sums: sums, then sums of per-path squares */

struct tb_tile {
    int M, bits[NFIXED], bc, total; /* the tile key's widths (a group accumulator's without path) */
    int64_t nrec;                   /* 1 << bits[F_REC]: the record ids a key can hold */
    tt_row *rows;                   /* every group's rows, group after group, record by record */
    int64_t nrows, rows_room;
    int64_t *starts; /* per group g: (nrec + 1) offsets of each record's rows in `rows` */
    int64_t ngroups, starts_room;
    tt_sum *sums; /* after tt_finish: U keys and their sums, record by record */
    int64_t U;
    int max_count, done;
    int32_t *hist, *perm;
    int64_t hist_room, perm_room;
};

/* bits: rec, obj, bounce, j, w + 1, one count digit (a group accumulator's without the path) */
tb_tile *tb_tile_new(int M, const int32_t *bits) {
    tb_tile *t = (tb_tile *)calloc(1, sizeof(tb_tile));
    if (!t) return NULL;
    t->M = M, t->bc = bits[NFIXED], t->total = M * t->bc;
    for (int f = 0; f < NFIXED; f++) t->bits[f] = bits[f], t->total += bits[f];
    if (t->total > 127 || bits[F_REC] > TT_MAX_BUCKET_BITS) {
        free(t);
        return NULL;
    }
    t->nrec = (int64_t)1 << bits[F_REC];
    return t;
}

void tb_tile_free(tb_tile *t) {
    if (!t) return;
    free(t->rows), free(t->starts), free(t->sums), free(t->hist), free(t->perm), free(t);
}

/* Add the per-path sums of a pass group's entries (a: values 3, with a path field) to the tile:
 * what tb_reduce_into(a, ., into) and the final merge add, in the same order. Returns 0; -1 out
 * of memory; -2 a's widths are not the tile's (plus a path field), too many buckets, or the
 * tile was already read. */
int tb_tile_add(tb_tile *t, const tb_acc *a) {
    const int bp = a->bp;
    if (t->done || a->M != t->M || a->V != 3 || a->bc != t->bc || a->total - bp != t->total || bp < 1) return -2;
    for (int f = 0; f < NFIXED; f++)
        if (a->bits[f] != t->bits[f]) return -2;
    const int64_t n = a->n, nb = t->nrec << bp;
    if (t->bits[F_REC] + bp > TT_MAX_BUCKET_BITS || n >= INT32_MAX) return -2;
    if (!n) return 0;
    if (t->hist_room < nb + 1) {
        free(t->hist);
        t->hist = (int32_t *)malloc(sizeof(int32_t) * (nb + 1)), t->hist_room = t->hist ? nb + 1 : 0;
    }
    if (t->perm_room < n) {
        free(t->perm);
        t->perm = (int32_t *)malloc(sizeof(int32_t) * n), t->perm_room = t->perm ? n : 0;
    }
    if (t->nrows + n > t->rows_room) {
        int64_t room = t->rows_room ? t->rows_room : 1 << 16;
        while (room < t->nrows + n) room *= 2;
        tt_row *r = (tt_row *)realloc(t->rows, sizeof(tt_row) * room);
        if (!r) return -1;
        t->rows = r, t->rows_room = room;
    }
    if ((t->ngroups + 1) * (t->nrec + 1) > t->starts_room) {
        int64_t room = t->starts_room ? 2 * t->starts_room : 16 * (t->nrec + 1);
        int64_t *st = (int64_t *)realloc(t->starts, sizeof(int64_t) * room);
        if (!st) return -1;
        t->starts = st, t->starts_room = room;
    }
    if (!t->hist || !t->perm) return -1;
    /* bucket (record, path) of an entry: its key's top field and its bottom one */
    const int shr = a->total - t->bits[F_REC];
    const uint64_t pm = ((uint64_t)1 << bp) - 1;
#define TT_BUCKET(k) ((int64_t)(((uint64_t)((k) >> shr) << bp) | ((uint64_t)(k) & pm)))
    int32_t *h = t->hist;
    memset(h, 0, sizeof(int32_t) * (nb + 1));
    for (int64_t i = 0; i < n; i++) h[TT_BUCKET(a->key[i]) + 1]++;
    for (int64_t b = 0; b < nb; b++) h[b + 1] += h[b];
    for (int64_t i = 0; i < n; i++) t->perm[h[TT_BUCKET(a->key[i])]++] = (int32_t)i;
    /* the buckets in order: a key's rows of one bucket summed into one (the bucket's first rows
     * are its keys so far: a short linear search, buckets hold a path's few entries) */
    int64_t *st = t->starts + t->ngroups * (t->nrec + 1), r0 = 0, cur = -1, first = t->nrows;
    tt_row *out = t->rows;
    for (int64_t at = 0; at < n; at++) {
        int64_t i = t->perm[at], b = TT_BUCKET(a->key[i]);
        if (at + TT_AHEAD < n) { /* the entry TT_AHEAD ahead: its key and both lines its 24 bytes may touch */
            const int64_t j = t->perm[at + TT_AHEAD];
            __builtin_prefetch(a->key + j), __builtin_prefetch(a->val + 3 * j), __builtin_prefetch(a->val + 3 * j + 2);
        }
        if (b != cur) {
            for (int64_t r = b >> bp; r0 <= r; r0++) st[r0] = t->nrows; /* records up to b's start here */
            cur = b, first = t->nrows;
        }
        u128 k = a->key[i] >> bp;
        int64_t x = t->nrows - 1;
        while (x >= first && out[x].k != k) x--;
        if (x < first) {
            x = t->nrows++;
            out[x].k = k;
            for (int c = 0; c < 3; c++) out[x].s[c] = 0.0;
        }
        for (int c = 0; c < 3; c++) out[x].s[c] += a->val[3 * i + c];
    }
#undef TT_BUCKET
    for (; r0 <= t->nrec; r0++) st[r0] = t->nrows;
    t->ngroups++;
    if (a->max_count > t->max_count) t->max_count = a->max_count;
    return 0;
}

static inline uint64_t tt_hash(u128 k) { return ((uint64_t)k ^ (uint64_t)(k >> 64)) * 0x9E3779B97F4A7C15ull; }

/* the tile's sums per key, record by record (once; later adds are refused). 0 or -1. */
static int tt_finish(tb_tile *t) {
    if (t->done) return 0;
    int64_t most = 0; /* the most rows of one record: the hash table's size */
    for (int64_t r = 0; r < t->nrec; r++) {
        int64_t m = 0;
        for (int64_t g = 0; g < t->ngroups; g++) m += t->starts[g * (t->nrec + 1) + r + 1] - t->starts[g * (t->nrec + 1) + r];
        if (m > most) most = m;
    }
    int lg = 4;
    while (((int64_t)1 << lg) < 2 * most) lg++;
    const int64_t cap = (int64_t)1 << lg;
    u128 *hk = (u128 *)malloc(sizeof(u128) * cap);
    int64_t *hv = (int64_t *)malloc(sizeof(int64_t) * cap), *used = (int64_t *)malloc(sizeof(int64_t) * cap);
    tt_sum *sums = (tt_sum *)malloc(sizeof(tt_sum) * (t->nrows ? t->nrows : 1)); /* U <= rows */
    if (!hk || !hv || !used || !sums) {
        free(hk), free(hv), free(used), free(sums);
        return -1;
    }
    for (int64_t i = 0; i < cap; i++) hk[i] = TT_EMPTY;
    int64_t U = 0;
    for (int64_t r = 0; r < t->nrec; r++) {
        int64_t nu = 0;
        for (int64_t g = 0; g < t->ngroups; g++) {
            const int64_t *st = t->starts + g * (t->nrec + 1);
            for (int64_t e = st[r]; e < st[r + 1]; e++) {
                const tt_row *row = t->rows + e;
                int64_t i = (int64_t)(tt_hash(row->k) >> (64 - lg));
                while (hk[i] != row->k && hk[i] != TT_EMPTY) i = (i + 1) & (cap - 1);
                if (hk[i] == TT_EMPTY) {
                    hk[i] = row->k, hv[i] = U, used[nu++] = i;
                    sums[U].k = row->k;
                    for (int c = 0; c < 3; c++) sums[U].s[c] = 0.0, sums[U].q[c] = 0.0;
                    U++;
                }
                tt_sum *s = sums + hv[i];
                for (int c = 0; c < 3; c++) {
                    double v = row->s[c];
                    s->s[c] += v, s->q[c] += v * v;
                }
            }
        }
        for (int64_t x = 0; x < nu; x++) hk[used[x]] = TT_EMPTY;
    }
    free(hk), free(hv), free(used);
    free(t->rows), free(t->starts);
    t->rows = NULL, t->starts = NULL, t->nrows = t->rows_room = t->ngroups = t->starts_room = 0;
    t->sums = sums, t->U = U, t->done = 1;
    return 0;
}

/* the tile's keys (after its sums are finished); -1 out of memory */
int64_t tb_tile_size(tb_tile *t) { return tt_finish(t) ? -1 : t->U; }
int tb_tile_max_count(const tb_tile *t) { return t->max_count; }

/* The tile's keys and sums: fields_out (U, 5 + M) int64 (rec, obj, bounce, j, w, counts) and
 * vals_out (U, 6) float64 (sums, then sums of per-path squares), ascending as tb_reduce returns them (count digits last object first, or first object first
 * when forward). Returns U; -1 out of memory. */
int64_t tb_tile_export(tb_tile *t, int forward, int64_t *fields_out, double *vals_out) {
    if (tt_finish(t)) return -1;
    const int64_t U = t->U;
    const int M = t->M, K = NFIXED + M;
    item *x, *y, *sorted;
    int64_t cnt[2048];
    x = (item *)malloc(sizeof(item) * (U ? U : 1)), y = (item *)malloc(sizeof(item) * (U ? U : 1));
    if (!x || !y) {
        free(x), free(y);
        return -1;
    }
    tb_acc shape; /* forward_key's view of the tile's widths (no path field) */
    memset(&shape, 0, sizeof(shape));
    shape.M = M, shape.bc = t->bc;
    for (int64_t u = 0; u < U; u++) x[u].k = forward ? forward_key(&shape, t->sums[u].k) : t->sums[u].k, x[u].s = u;
    sorted = U ? sort128(x, y, U, t->total, cnt) : x;
    for (int64_t o = 0; o < U; o++) {
        const tt_sum *s = t->sums + sorted[o].s;
        u128 k = s->k;
        int64_t *row = fields_out + o * K;
        for (int m = 0; m < M; m++, k >>= t->bc) row[NFIXED + m] = (int64_t)(k & field_mask(t->bc));
        for (int d = NFIXED - 1; d >= 0; d--) {
            row[d] = (int64_t)(k & field_mask(t->bits[d]));
            k >>= t->bits[d];
        }
        row[F_W] -= 1;
        for (int c = 0; c < 3; c++) vals_out[6 * o + c] = s->s[c], vals_out[6 * o + 3 + c] = s->q[c];
    }
    free(x), free(y);
    return U;
}

/* A tile's sparse blocks straight from its sums (tb_blocks' output without the fields export
 * and without sorting keys): per (eye object, bounce) block in ascending order, the records that
 * occur (ascending: the sums are record by record, and a stable counting sort by block keeps
 * that), the terms (w, counts) in tb_blocks' order (w, then the count digits last object first
 * when the block's code fits, else first object first; distinct terms found with a small hash
 * table, then sorted), and the entries in ascending local key (j Z + z) P + p by a stable
 * counting sort over (j, z) of the rows in record order; means and variances as tb_blocks.
 * Out: key (U,) int64; vals, var (3 U) float32 block after block, each (3, E); upix (U,) int64
 * block after block (P each); tw (U,) int64 and tc (U, M) int8 the terms, block after block (Z
 * each); meta (obj, bounce, E, P, Z) int64 per block (room blocks). Returns the number of
 * blocks; -1 out of memory; -2 fields too wide (tb_blocks' limits). */
static int tt_u128_cmp(const void *x, const void *y) {
    u128 a = *(const u128 *)x, b = *(const u128 *)y;
    return a < b ? -1 : a > b;
}

int64_t tb_tile_blocks(tb_tile *t, const int64_t *spp_rec, int64_t spp, int64_t room, int64_t *key, float *mean_out,
                       float *var_out, int64_t *upix, int64_t *tw, int8_t *tc, int64_t *meta) {
    if (tt_finish(t)) return -1;
    const int M = t->M, bc = t->bc, bo = t->bits[F_OBJ], bb = t->bits[F_BOUNCE], bj = t->bits[F_J], bw = t->bits[F_W];
    if (bo + bb > 20 || t->bits[F_REC] > 24) return -2;
    const int s_w = M * bc, s_j = s_w + bw, s_b = s_j + bj, s_r = s_b + bo + bb;
    const int64_t U = t->U, nblk = (int64_t)1 << (bo + bb);
    const u128 cmask = field_mask(bc);
    int64_t *hb = (int64_t *)calloc(nblk + 1, sizeof(int64_t)), *maxc = (int64_t *)calloc(nblk, sizeof(int64_t));
    int64_t *jmax = (int64_t *)calloc(nblk, sizeof(int64_t));
    int32_t *ord = (int32_t *)malloc(sizeof(int32_t) * (U ? U : 1)), *zid = (int32_t *)malloc(sizeof(int32_t) * (U ? U : 1));
    int32_t *ord2 = (int32_t *)malloc(sizeof(int32_t) * (U ? U : 1)), *prank = (int32_t *)malloc(sizeof(int32_t) * (U ? U : 1));
    int64_t hcap = 1024, *jh = NULL, jh_room = 0, nb = 0;
    u128 *hk = (u128 *)malloc(sizeof(u128) * hcap), *terms = (u128 *)malloc(sizeof(u128) * (U ? U : 1));
    int32_t *hv = (int32_t *)malloc(sizeof(int32_t) * hcap), *zrank = (int32_t *)malloc(sizeof(int32_t) * (U ? U : 1));
    u128 *sorted_terms = (u128 *)malloc(sizeof(u128) * (U ? U : 1));
    if (!hb || !maxc || !jmax || !ord || !zid || !ord2 || !prank || !hk || !terms || !hv || !zrank || !sorted_terms) {
        nb = -1;
        goto done;
    }
    if (U >= INT32_MAX) {
        nb = -2;
        goto done;
    }
    const tt_sum *S = t->sums;
    for (int64_t i = 0; i < U; i++) { /* per block: rows, largest count digit, largest j */
        u128 k = S[i].k;
        int64_t b = (int64_t)((k >> s_b) & field_mask(bo + bb)), j = (int64_t)((k >> s_j) & field_mask(bj));
        hb[b + 1]++;
        for (int m = 0; m < M; m++) {
            int64_t c = (int64_t)((k >> (m * bc)) & cmask);
            if (c > maxc[b]) maxc[b] = c;
        }
        if (j > jmax[b]) jmax[b] = j;
    }
    for (int64_t b = 0; b < nblk; b++) hb[b + 1] += hb[b];
    {
        int64_t *at = (int64_t *)malloc(sizeof(int64_t) * (nblk ? nblk : 1));
        if (!at) {
            nb = -1;
            goto done;
        }
        memcpy(at, hb, sizeof(int64_t) * nblk);
        for (int64_t i = 0; i < U; i++) ord[at[(int64_t)((S[i].k >> s_b) & field_mask(bo + bb))]++] = (int32_t)i;
        free(at);
    }
    int64_t at_e = 0, at_p = 0, at_z = 0;
    for (int64_t b = 0; b < nblk; b++) {
        const int64_t i0 = hb[b], i1 = hb[b + 1], E = i1 - i0;
        if (!E) continue;
        if (nb >= room) {
            nb = -1;
            goto done;
        }
        const int fwd = !fits_code(M, maxc[b]);
        /* records (ascending in ord) and their ranks */
        int64_t P = 0, prev = -1;
        for (int64_t i = i0; i < i1; i++) {
            int64_t r = (int64_t)(S[ord[i]].k >> s_r);
            if (r != prev) upix[at_p + P++] = r, prev = r;
            prank[i] = (int32_t)(P - 1);
        }
        /* terms: (w + 1, digits in the block's order) -> first-seen id, then their ascending rank */
        for (int64_t x = 0; x < hcap; x++) hk[x] = TT_EMPTY;
        int64_t Z = 0;
        int lg = __builtin_ctzll((unsigned long long)hcap);
        for (int64_t i = i0; i < i1; i++) {
            u128 k = S[ord[i]].k, term = (k & field_mask(s_w + bw));
            if (fwd) { /* first object most significant */
                u128 d = 0;
                for (int m = 0; m < M; m++) d = (d << bc) | ((k >> (m * bc)) & cmask);
                term = ((term >> s_w) << s_w) | d;
            }
            if (2 * (Z + 1) > hcap) { /* grow the term table (rehash the terms so far) */
                int64_t nc = 2 * hcap;
                u128 *k2 = (u128 *)malloc(sizeof(u128) * nc);
                int32_t *v2 = (int32_t *)malloc(sizeof(int32_t) * nc);
                if (!k2 || !v2) {
                    free(k2), free(v2);
                    nb = -1;
                    goto done;
                }
                int nlg = lg + 1;
                for (int64_t x = 0; x < nc; x++) k2[x] = TT_EMPTY;
                for (int64_t z = 0; z < Z; z++) {
                    int64_t x = (int64_t)(tt_hash(terms[z]) >> (64 - nlg));
                    while (k2[x] != TT_EMPTY) x = (x + 1) & (nc - 1);
                    k2[x] = terms[z], v2[x] = (int32_t)z;
                }
                free(hk), free(hv);
                hk = k2, hv = v2, hcap = nc, lg = nlg;
            }
            int64_t x = (int64_t)(tt_hash(term) >> (64 - lg));
            while (hk[x] != term && hk[x] != TT_EMPTY) x = (x + 1) & (hcap - 1);
            if (hk[x] == TT_EMPTY) hk[x] = term, hv[x] = (int32_t)Z, terms[Z++] = term;
            zid[i] = hv[x];
        }
        memcpy(sorted_terms, terms, sizeof(u128) * Z);
        qsort(sorted_terms, Z, sizeof(u128), tt_u128_cmp);
        for (int64_t z = 0; z < Z; z++) { /* rank of each first-seen id; the terms out in rank order */
            int64_t x = (int64_t)(tt_hash(sorted_terms[z]) >> (64 - lg));
            while (hk[x] != sorted_terms[z]) x = (x + 1) & (hcap - 1);
            zrank[hv[x]] = (int32_t)z;
            u128 term = sorted_terms[z];
            tw[at_z + z] = (int64_t)((term >> s_w) & field_mask(bw)) - 1;
            for (int m = 0; m < M; m++) { /* digit of object m: packed last object first, or first first */
                int sh = fwd ? (M - 1 - m) * bc : m * bc;
                tc[(at_z + z) * M + m] = (int8_t)((term >> sh) & cmask);
            }
        }
        /* entries by (j Z + z), stable over the rows' record order: ascending (j Z + z) P + p */
        const int64_t nk = (jmax[b] + 1) * Z;
        float *mo = mean_out + 3 * at_e, *vo = var_out + 3 * at_e;
        if (nk > 8 * E + (1 << 20)) { /* too many buckets for a counting sort: a radix sort of the keys */
            item64 *x = (item64 *)malloc(sizeof(item64) * E), *y = (item64 *)malloc(sizeof(item64) * E);
            int64_t cnt[2048];
            if (!x || !y) {
                free(x), free(y);
                nb = -1;
                goto done;
            }
            int kbits = 1;
            for (int64_t i = i0; i < i1; i++) {
                int64_t j = (int64_t)((S[ord[i]].k >> s_j) & field_mask(bj));
                uint64_t k = (uint64_t)((j * Z + zrank[zid[i]]) * P + prank[i]);
                x[i - i0].k = k, x[i - i0].s = i;
                while (kbits < 64 && (k >> kbits)) kbits++;
            }
            item64 *ks = sort64(x, y, E, kbits, cnt);
            for (int64_t e = 0; e < E; e++) ord2[i0 + e] = (int32_t)ks[e].s, zid[ks[e].s] = -1, key[at_e + e] = (int64_t)ks[e].k;
            free(x), free(y);
        } else {
        if (jh_room < nk + 1) {
            free(jh);
            jh = (int64_t *)malloc(sizeof(int64_t) * (nk + 1)), jh_room = jh ? nk + 1 : 0;
            if (!jh) {
                nb = -1;
                goto done;
            }
        }
        memset(jh, 0, sizeof(int64_t) * (nk + 1));
        for (int64_t i = i0; i < i1; i++) {
            int64_t j = (int64_t)((S[ord[i]].k >> s_j) & field_mask(bj));
            zid[i] = (int32_t)(j * Z + zrank[zid[i]]); /* now the (j, z) bucket */
            jh[zid[i] + 1]++;
        }
        for (int64_t q = 0; q < nk; q++) jh[q + 1] += jh[q];
        for (int64_t i = i0; i < i1; i++) ord2[i0 + jh[zid[i]]++] = (int32_t)i;
        for (int64_t e = 0; e < E; e++) key[at_e + e] = (int64_t)zid[ord2[i0 + e]] * P + prank[ord2[i0 + e]];
        }
        for (int64_t e = 0; e < E; e++) {
            int64_t i = ord2[i0 + e];
            const tt_sum *s = S + ord[i];
            if (e + TT_AHEAD < E) { /* the sums TT_AHEAD entries ahead (64 bytes: up to two lines) */
                const char *ahead = (const char *)(S + ord[ord2[i0 + e + TT_AHEAD]]);
                __builtin_prefetch(ahead), __builtin_prefetch(ahead + sizeof(tt_sum) - 1);
            }
            int64_t n = spp_rec ? spp_rec[(int64_t)(s->k >> s_r)] : spp;
            double dn = (double)n, dof = (double)(n - 1 < 1 ? 1 : n - 1);
            for (int c = 0; c < 3; c++) {
                double mu = s->s[c] / dn, q = (s->q[c] / dn - mu * mu) / dof;
                mo[c * E + e] = (float)mu, vo[c * E + e] = (float)(q < 0 ? 0.0 : q);
            }
        }
        int64_t *mt = meta + 5 * nb;
        mt[0] = b >> bb, mt[1] = b & (((int64_t)1 << bb) - 1), mt[2] = E, mt[3] = P, mt[4] = Z;
        at_e += E, at_p += P, at_z += Z, nb++;
    }
done:
    free(hb), free(maxc), free(jmax), free(ord), free(zid), free(ord2), free(prank), free(hk), free(terms), free(hv);
    free(zrank), free(sorted_terms), free(jh);
    return nb;
}
