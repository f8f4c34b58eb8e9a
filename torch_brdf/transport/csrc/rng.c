/* torch's CPU random generator (kernel.h: tb_mt) drawn from the bytes of its state
 * (Generator.get_state()), so that the GI tracer's wavefront draws torch.rand's numbers without a
 * torch call between its steps: the same numbers in the same order, the state written back after.
 * polynomial/vertex.py c_rand_matches checks once per process that tb_rand equals torch.rand bit
 * for bit on a copy of a generator (else the wavefront keeps torch's draws). */
#include "kernel.h"

static void mt_temper(tb_mt *g) { /* all 624 at once: a loop the compiler vectorises */
    for (int i = 0; i < MT_N; i++) {
        uint32_t y = g->s[i];
        y ^= (y >> 11);
        y ^= (y << 7) & 0x9d2c5680u;
        y ^= (y << 15) & 0xefc60000u;
        g->t[i] = y ^ (y >> 18);
    }
}

void mt_load(tb_mt *g, const uint8_t *b) {
    memcpy(&g->left, b + GS_LEFT, 4), memcpy(&g->next, b + GS_NEXT, 8);
    for (int i = 0; i < MT_N; i++) {
        uint64_t v;
        memcpy(&v, b + GS_STATE + 8 * i, 8);
        g->s[i] = (uint32_t)v;
    }
    mt_temper(g);
}

void mt_store(const tb_mt *g, uint8_t *b) {
    memcpy(b + GS_LEFT, &g->left, 4), memcpy(b + GS_NEXT, &g->next, 8);
    for (int i = 0; i < MT_N; i++) {
        uint64_t v = g->s[i];
        memcpy(b + GS_STATE + 8 * i, &v, 8);
    }
}

static inline uint32_t mt_twist(uint32_t u, uint32_t v) {
    return ((((u & 0x80000000u) | (v & 0x7fffffffu)) >> 1) ^ ((v & 1u) ? 0x9908b0dfu : 0u));
}

void mt_refill(tb_mt *g) { /* at::mt19937::next_state, then the words tempered */
    uint32_t *p = g->s;
    g->left = MT_N, g->next = 0;
    for (int j = MT_N - MT_M + 1; --j; p++) *p = p[MT_M] ^ mt_twist(p[0], p[1]);
    for (int j = MT_M; --j; p++) *p = p[MT_M - MT_N] ^ mt_twist(p[0], p[1]);
    *p = p[MT_M - MT_N] ^ mt_twist(p[0], g->s[0]);
    mt_temper(g);
}

/* torch.rand(n, generator=g, dtype=float64 if dbl else float32) into out, drawn from and
 * advancing the state bytes gs (Generator.get_state()). */
void tb_rand(uint8_t *gs, int64_t n, int dbl, void *out) {
    tb_mt g;
    mt_load(&g, gs);
    if (dbl)
        for (int64_t i = 0; i < n; i++) ((double *)out)[i] = mt_f64(&g);
    else
        for (int64_t i = 0; i < n; i++) ((float *)out)[i] = mt_f32(&g);
    mt_store(&g, gs);
}
