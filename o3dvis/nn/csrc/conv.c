/* The U-Net's gathered convolutions (o3dvis/nn/conv.py, ConvBnRelu in inference) with bfloat16
 * dot products: on the AMX tiles where the build and the operating system have them, else in
 * AVX-512 vectors, skipping the missing neighbours by the lists of o3dvis_conv_entries. */

#include "kernels.h"

#ifdef __AVX512BF16__
/* The end of one row's 16 outputs of o3dvis_gather_conv from their float32 sums: rounded to
 * bfloat16 and back (torch's bfloat16 product), plus the shift (and the residual), through the ReLU. */
static inline void finish_sums(const float *sums, int64_t row, int col, int outputs, const float *shift,
                               const float *residual, int relu, float *out) {
    const __m256i rounded = (__m256i)_mm512_cvtneps_pbh(_mm512_loadu_ps(sums));
    __m512 v = _mm512_add_ps((__m512)_mm512_slli_epi32(_mm512_cvtepu16_epi32(rounded), 16),
                             _mm512_loadu_ps(shift + col));
    if (residual) v = _mm512_add_ps(_mm512_loadu_ps(residual + row * outputs + col), v);
    if (relu) v = _mm512_max_ps(v, _mm512_setzero_ps());
    _mm512_storeu_ps(out + row * outputs + col, v);
}

/* Copies the rows taken[0 .. taps - 1] of xb, pairs int32 each, one after the other into dst: whole
 * vector moves for the widths of the U-Net's layers, masked ones for the others. */
static inline void gather_row(uint32_t *restrict dst, const uint32_t *restrict xb, const int64_t *taken, int taps,
                              int pairs) {
#define GATHER_ROW(MOVE)                                                                                     \
    for (int t = 0; t < taps; t++) {                                                                         \
        const uint32_t *src = xb + taken[t] * pairs;                                                         \
        uint32_t *to = dst + t * pairs;                                                                      \
        MOVE;                                                                                                \
    }                                                                                                        \
    return
#define MOVE16(c) _mm512_storeu_si512(to + (c), _mm512_loadu_si512(src + (c)))
    switch (pairs) {
    case 4: GATHER_ROW(_mm_storeu_si128((__m128i *)to, _mm_loadu_si128((const __m128i *)src)));
    case 8: GATHER_ROW(_mm256_storeu_si256((__m256i *)to, _mm256_loadu_si256((const __m256i *)src)));
    case 16: GATHER_ROW(MOVE16(0));
    case 32: GATHER_ROW(MOVE16(0); MOVE16(16));
    case 48: GATHER_ROW(MOVE16(0); MOVE16(16); MOVE16(32));
    default:
        GATHER_ROW(for (int c = 0; c < pairs; c += 16) {
            const __mmask16 lanes = pairs - c >= 16 ? 0xffff : (__mmask16)((1u << (pairs - c)) - 1);
            _mm512_mask_storeu_epi32(to + c, lanes, _mm512_maskz_loadu_epi32(lanes, src + c));
        });
    }
#undef MOVE16
#undef GATHER_ROW
}

#define CONV_BLOCK 64 /* output rows of a block of o3dvis_gather_conv */

/* acc plus the bfloat16 dot products of the pairs w with the pair *x in every lane: the pair read
 * and broadcast by the load (an embedded broadcast), not by a shuffle before each product as a
 * compiler keeps a broadcast register for several products, so that the products alone take the
 * vector units. The products and sums are those of _mm512_dpbf16_ps(acc, set1(*x), w). */
static inline __m512 dot_broadcast(__m512 acc, __m512bh w, const uint32_t *x) {
    __asm__("vdpbf16ps %2%{1to16%}, %1, %0" : "+v"(acc) : "v"(w), "m"(*x));
    return acc;
}

/* One tap of a block of o3dvis_gather_conv in AVX-512 vectors, rows x tiles of 16 outputs at a time:
 * the float32 sums of rows of the block (in sums, outputs a row) plus the pairs of their neighbours
 * (rows of xb, pairs a row) times the tap's weights, pair after pair, with bfloat16 dot products.
 * entry: the rows, each its neighbour << 8 | its row in the block; k0: the tap's first pair along
 * the inputs; packed as conv_block reads it. */
static inline __attribute__((always_inline)) void tap_rows(const uint32_t *xb, int pairs, const int64_t *entry,
                                                           int rows, const uint32_t *packed, int otiles, int o0,
                                                           int tiles, int k0, float *sums, int outputs) {
    __m512 acc[8][4];
    const uint32_t *from[8];
    for (int r = 0; r < rows; r++) {
        from[r] = xb + (entry[r] >> 8) * pairs;
        for (int o = 0; o < tiles; o++)
            acc[r][o] = _mm512_loadu_ps(sums + (entry[r] & 255) * outputs + 16 * (o0 + o));
    }
    for (int p = 0; p < pairs; p++) {
        const unsigned k = (unsigned)(k0 + p);
        __m512bh w[4];
        for (int o = 0; o < tiles; o++)
            w[o] = (__m512bh)_mm512_loadu_si512(packed + ((int64_t)(k / 16) * otiles + o0 + o) * 256 + 16 * (k % 16));
        for (int r = 0; r < rows; r++)
            for (int o = 0; o < tiles; o++) acc[r][o] = dot_broadcast(acc[r][o], w[o], from[r] + p);
    }
    for (int r = 0; r < rows; r++)
        for (int o = 0; o < tiles; o++) _mm512_storeu_ps(sums + (entry[r] & 255) * outputs + 16 * (o0 + o), acc[r][o]);
}

/* conv_block with AVX-512 dot products instead of the tiles, tap by tap: each tap for the rows that
 * have that neighbour only (a surface's nodes miss about half of their 27), so that each row's sum
 * runs along its inputs in the order of the tiles' but for the products with a row of zeros, which
 * add nothing. offsets, entry: the block's lists of o3dvis_conv_entries (rows of xb, x in bfloat16
 * pairs); sums: CONV_BLOCK + 1 rows of outputs floats (the last takes the made-up rows). */
static void conv_block_vectors(const uint32_t *xb, int pairs, const int64_t *offsets, const int64_t *entry,
                               int taps, int m, const uint32_t *packed, int outputs, const float *shift,
                               const float *residual, int relu, float *sums, float *out) {
    const int otiles = outputs / 16;
    memset(sums, 0, sizeof *sums * (size_t)(CONV_BLOCK + 1) * outputs);
    for (int t = 0; t < taps; t++) {
        const int64_t *e = entry + offsets[t];
        const int count = (int)(offsets[t + 1] - offsets[t]);
        int o0 = 0;
        for (; o0 + 4 <= otiles; o0 += 4)
            for (int g = 0; g < count; g += 4)
                tap_rows(xb, pairs, e + g, 4, packed, otiles, o0, 4, t * pairs, sums, outputs);
        for (; o0 + 2 <= otiles; o0 += 2)
            for (int g = 0; g < count; g += 8)
                tap_rows(xb, pairs, e + g, 8, packed, otiles, o0, 2, t * pairs, sums, outputs);
        for (; o0 < otiles; o0++)
            for (int g = 0; g < count; g += 8)
                tap_rows(xb, pairs, e + g, 8, packed, otiles, o0, 1, t * pairs, sums, outputs);
    }
    for (int r = 0; r < m; r++)
        for (int o = 0; o < otiles; o++)
            finish_sums(sums + (int64_t)r * outputs + 16 * o, r, 16 * o, outputs, shift, residual, relu, out);
}
#endif

/* Whether this build runs o3dvis_gather_conv: on the AMX tiles where the operating system grants them,
   else with AVX-512 bfloat16 dot products. */
int o3dvis_has_gather_conv(void) {
#ifdef __AVX512BF16__
    return 1;
#else
    return 0;
#endif
}

#ifdef __AMX_BF16__
/* Tile instructions on tiles chosen at run time (their operands are immediates): loads into tiles
 * 4-7, products into sums 0-3 from inputs 4 or 7 and weights 5 or 6, stores of 0-3. */
__attribute__((target("amx-tile"))) static inline void load_tile(int t, const void *p, int64_t stride) {
    switch (t) {
    case 4: _tile_loadd(4, p, stride); break;
    case 5: _tile_loadd(5, p, stride); break;
    case 6: _tile_loadd(6, p, stride); break;
    default: _tile_loadd(7, p, stride); break;
    }
}

__attribute__((target("amx-tile,amx-bf16"))) static inline void product_tile(int c, int a, int b) {
    switch (c * 4 + (a == 7) * 2 + (b == 6)) {
    case 0: _tile_dpbf16ps(0, 4, 5); break;
    case 1: _tile_dpbf16ps(0, 4, 6); break;
    case 2: _tile_dpbf16ps(0, 7, 5); break;
    case 3: _tile_dpbf16ps(0, 7, 6); break;
    case 4: _tile_dpbf16ps(1, 4, 5); break;
    case 5: _tile_dpbf16ps(1, 4, 6); break;
    case 6: _tile_dpbf16ps(1, 7, 5); break;
    case 7: _tile_dpbf16ps(1, 7, 6); break;
    case 8: _tile_dpbf16ps(2, 4, 5); break;
    case 9: _tile_dpbf16ps(2, 4, 6); break;
    case 10: _tile_dpbf16ps(2, 7, 5); break;
    case 11: _tile_dpbf16ps(2, 7, 6); break;
    case 12: _tile_dpbf16ps(3, 4, 5); break;
    case 13: _tile_dpbf16ps(3, 4, 6); break;
    case 14: _tile_dpbf16ps(3, 7, 5); break;
    default: _tile_dpbf16ps(3, 7, 6); break;
    }
}

__attribute__((target("amx-tile"))) static inline void store_sums(int c, void *p) {
    switch (c) {
    case 0: _tile_stored(0, p, 64); break;
    case 1: _tile_stored(1, p, 64); break;
    case 2: _tile_stored(2, p, 64); break;
    default: _tile_stored(3, p, 64); break;
    }
}

/* A block of up to 64 output rows of o3dvis_gather_conv (m of them real): a, the rows' gathered
 * inputs in bfloat16 (64 rows of kp values). Four sums at a time on tiles 0-3, each one group of
 * 16 rows x 16 outputs summed along the inputs in order: four groups of rows for one of outputs,
 * two by two, or one by four, so that products into different sums overlap. Then rounded to
 * bfloat16 and finished as the caller's torch ops finish them (outputs a multiple of 16). */
__attribute__((target("amx-tile,amx-bf16")))
static void conv_block(const uint16_t *a, int kp, int m, const uint32_t *packed, int outputs, const float *shift,
                       const float *residual, int relu, float *sums, float *out) {
    const int otiles = outputs / 16, groups = (m + 15) / 16;
    const int per = otiles >= 4 ? 4 : (otiles >= 2 ? 2 : 1); /* output tiles a pass */
    const int side = 4 / per < groups ? 4 / per : groups;     /* row groups a pass */
    for (int g0 = 0; g0 < groups; g0 += side)
        for (int o0 = 0; o0 < otiles; o0 += per) {
            const int rg = groups - g0 < side ? groups - g0 : side, ot = otiles - o0 < per ? otiles - o0 : per;
            _tile_zero(0);
            _tile_zero(1);
            _tile_zero(2);
            _tile_zero(3);
            for (int kc = 0; kc < kp / 32; kc++)
                for (int o = 0; o < ot; o++) {
                    const int bt = 5 + o % 2;
                    load_tile(bt, packed + ((int64_t)kc * otiles + o0 + o) * 256, 64);
                    for (int r = 0; r < rg; r++) {
                        const int at = r % 2 ? 7 : 4;
                        if (o == 0) load_tile(at, a + (int64_t)(16 * (g0 + r)) * kp + 32 * kc, 2 * kp);
                        product_tile(r * ot + o, at, bt);
                    }
                }
            for (int r = 0; r < rg; r++)
                for (int o = 0; o < ot; o++) store_sums(r * ot + o, sums + 256 * (r * ot + o));
            for (int r = 0; r < rg; r++)
                for (int o = 0; o < ot; o++)
                    for (int i = 0; i < 16 && 16 * (g0 + r) + i < m; i++)
                        finish_sums(sums + 256 * (r * ot + o) + 16 * i, 16 * (g0 + r) + i, 16 * (o0 + o), outputs,
                                    shift, residual, relu, out);
        }
}
#endif

/* The lists of conv_block_vectors for an index of o3dvis_gather_conv, made once for the convolutions
 * over the same index: for the rows of each block of CONV_BLOCK (block b) that have neighbour t, from
 * entries[offsets[b * taps + t]] to entries[offsets[b * taps + t + 1] - 1], each neighbour << 8 | its
 * row in the block, in order, made up to a whole number of groups of 8 with absent << 8 | CONV_BLOCK.
 * index: (n, taps) in [0, absent], absent meaning none (the zeros of a missing neighbour: they add
 * nothing); offsets: room for lists = ceil(n / CONV_BLOCK) * taps, and one; entries for
 * n * taps + 8 * (lists + 1) (the made-up ones, and what a vector store writes past the last).
 * None where gather_conv runs on the AMX tiles: they run every product. Returns the number of
 * entries, -2 in a build without AVX-512 bfloat16, or -3 (the lists meaningless) for an index out of
 * [0, absent]. */
int64_t o3dvis_conv_entries(int64_t n, const int64_t *index, int32_t taps, int64_t absent, int64_t *offsets,
                            int64_t *entries) {
#ifdef __AVX512BF16__
    const __m512i lane = _mm512_set_epi64(7, 6, 5, 4, 3, 2, 1, 0), none = _mm512_set1_epi64(absent);
    const __m512i stride = _mm512_set_epi64(7 * taps, 6 * taps, 5 * taps, 4 * taps, 3 * taps, 2 * taps, taps, 0);
    int64_t count = 0;
    __mmask8 outside = 0;
#ifdef __AMX_BF16__
    if (tiles_granted()) { /* the tiles run every product: empty lists */
        memset(offsets, 0, sizeof *offsets * (size_t)((n + CONV_BLOCK - 1) / CONV_BLOCK * taps + 1));
        return 0;
    }
#endif
    for (int64_t b0 = 0; b0 < n; b0 += CONV_BLOCK) {
        const int m = n - b0 < CONV_BLOCK ? (int)(n - b0) : CONV_BLOCK;
        for (int t = 0; t < taps; t++) {
            *offsets++ = count;
            for (int r0 = 0; r0 < m; r0 += 8) { /* a gather of eight rows' neighbour t: no branch per row */
                const __mmask8 real = m - r0 >= 8 ? 0xff : (__mmask8)((1u << (m - r0)) - 1);
                const __m512i from = _mm512_mask_i64gather_epi64(none, real, stride, index + (b0 + r0) * taps + t, 8);
                const __mmask8 kept = _mm512_cmpneq_epi64_mask(from, none);
                outside |= _mm512_mask_cmplt_epi64_mask(real, from, _mm512_setzero_si512()) |
                           _mm512_mask_cmpgt_epi64_mask(real, from, none);
                const __m512i entry = _mm512_or_si512(_mm512_slli_epi64(from, 8),
                                                      _mm512_add_epi64(lane, _mm512_set1_epi64(r0)));
                _mm512_storeu_si512(entries + count, _mm512_maskz_compress_epi64(kept, entry));
                count += __builtin_popcount(kept);
            }
            for (; count % 8; count++) entries[count] = absent << 8 | CONV_BLOCK;
        }
    }
    *offsets = count;
    return outside ? -3 : count;
#else
    (void)n, (void)index, (void)taps, (void)absent, (void)offsets, (void)entries;
    return -2;
#endif
}

#ifdef __AVX512BF16__
/* o3dvis_gather_conv's work: its blocks of CONV_BLOCK rows are the crew's items; each worker has its
 * own sums (and the tiles' gathered rows, where they run). */
struct conv_job {
    struct crew_job crew;
    int64_t n;
    const uint32_t *xb;
    int pairs, taps, outputs, relu, tiles, kp;
    const int64_t *index, *offsets, *entries;
    const uint32_t *packed;
    const float *shift, *residual;
    float *sums, *out;
    size_t sums_size;
    uint16_t *a;
};

/* A worker of o3dvis_gather_conv: the blocks it claims, with its own sums. */
static void conv_worker(struct crew_job *crew_job, int worker) {
    const struct conv_job *s = (const struct conv_job *)crew_job;
    float *sums = s->sums + s->sums_size * worker;
    int64_t b = crew_claim(crew_job);
    if (b < 0) return;
#ifdef __AMX_BF16__
    uint16_t *a = s->tiles ? s->a + (size_t)CONV_BLOCK * s->kp * worker : NULL;
    if (s->tiles) configure_tiles(); /* the tiles' configuration is each thread's own */
#endif
    for (; b >= 0; b = crew_claim(crew_job)) {
        const int64_t r0 = b * CONV_BLOCK;
        const int m = s->n - r0 < CONV_BLOCK ? (int)(s->n - r0) : CONV_BLOCK;
        const float *res = s->residual ? s->residual + r0 * s->outputs : NULL;
#ifdef __AMX_BF16__
        if (s->tiles) {
            for (int r = 0; r < m; r++)
                gather_row((uint32_t *)(a + (int64_t)r * s->kp), s->xb, s->index + (r0 + r) * s->taps, s->taps,
                           s->pairs);
            for (int r = m; r < (m + 15) / 16 * 16; r++) /* rows past n: zeros */
                memset(a + (int64_t)r * s->kp, 0, sizeof *a * 2 * (size_t)s->taps * s->pairs);
            conv_block(a, s->kp, m, s->packed, s->outputs, s->shift, res, s->relu, sums, s->out + r0 * s->outputs);
            continue;
        }
#endif
        conv_block_vectors(s->xb, s->pairs, s->offsets + b * s->taps, s->entries, s->taps, m, s->packed, s->outputs,
                           s->shift, res, s->relu, sums, s->out + r0 * s->outputs);
    }
#ifdef __AMX_BF16__
    if (s->tiles) release_tiles();
#endif
}
#endif

/* A convolution over gathered rows, as o3dvis/nn/conv.py's gather_matmul and ConvBnRelu compute it
 * in inference: out[r] = relu?(residual[r] + (bf16(sum_t bf16(x[index[r][t]]) W_t) + shift)), the
 * products in bfloat16 with float32 sums (on the AMX tiles where the build and the operating system
 * have them, else in AVX-512 vectors), rounded to bfloat16 as torch rounds a bfloat16 product.
 * x: (rows, channels) float32, channels even; index: (n, taps), rows meaning a row of zeros; packed:
 * the weight as o3dvis/nn/native/conv.py's pack_conv lays it out; outputs a multiple of 16; shift:
 * (outputs,); residual: (n, outputs) or NULL; out: (n, outputs); offsets, entries: the index's
 * o3dvis_conv_entries, listed of them; threads: the blocks are shared out among up to this many
 * threads, the caller's and the crew's (each row's sums are the same on any number). Returns 0, or with nothing
 * written -1 when out of memory, -2 in a build without AVX-512 bfloat16, -3 for an index out of
 * [0, rows], -4 for entries that are not lists of rows of blocks and of neighbours in [0, rows], or
 * lists that are not whole groups of 8 (the index itself is read, and checked, where the tiles run),
 * -5 for threads out of [1, CREW_MAX + 1]. */
int o3dvis_gather_conv(int64_t n, const float *x, int64_t rows, int32_t channels, const int64_t *index,
                       int32_t taps, const int64_t *offsets, const int64_t *entries, int64_t listed,
                       const uint32_t *packed, int32_t outputs, const float *shift, const float *residual,
                       int32_t relu, int32_t threads, float *out) {
#ifdef __AVX512BF16__
    if (threads < 1 || threads > CREW_MAX + 1) return -5;
    int outside = 0, tiles = 0, kp = 0;
#ifdef __AMX_BF16__
    tiles = tiles_granted(), kp = (taps * channels + 31) / 32 * 32;
    if (tiles) /* the tiles read the index; the vectors only the lists, checked below */
        for (int64_t i = 0; i < n * taps; i++) outside |= (index[i] < 0) | (index[i] > rows);
    if (outside) return -3;
#endif
    const int64_t blocks = (n + CONV_BLOCK - 1) / CONV_BLOCK, lists = blocks * taps;
    for (int64_t i = 0; i < lists; i++)
        outside |= (offsets[i] < 0) | (offsets[i + 1] < offsets[i]) | ((offsets[i + 1] - offsets[i]) % 8 != 0);
    outside |= offsets[lists] > listed;
    for (int64_t i = 0; i < listed; i++)
        outside |= (entries[i] >> 8 < 0) | (entries[i] >> 8 > rows) | ((entries[i] & 255) > CONV_BLOCK);
    if (outside) return -4;
    const int pairs = channels / 2;
    uint32_t *xb = malloc(sizeof *xb * (size_t)(rows + 1) * pairs); /* x in bfloat16, then a row of zeros */
    /* per thread: the tiles' four 16 x 16 sums, or the vectors' sums of a block and a row */
    const size_t size = 4 * 256 > (CONV_BLOCK + 1) * outputs ? 4 * 256 : (size_t)(CONV_BLOCK + 1) * outputs;
    float *sums = malloc(sizeof *sums * size * (size_t)threads);
    uint16_t *a = tiles ? calloc((size_t)CONV_BLOCK * kp * (size_t)threads, sizeof *a) : NULL; /* gathered rows */
    if (xb == NULL || sums == NULL || (tiles && a == NULL)) return free(a), free(xb), free(sums), -1;
    for (int64_t i = 0; i < rows * pairs; i++)
        xb[i] = bf16_of(x[2 * i]) | (uint32_t)bf16_of(x[2 * i + 1]) << 16;
    memset(xb + rows * pairs, 0, sizeof *xb * pairs);
    struct conv_job job = {{conv_worker, blocks, 0, crew_workers(threads, blocks), 0}, n, xb, pairs, taps, outputs,
                           relu, tiles, kp, index, offsets, entries, packed, shift, residual, sums, out, size, a};
    crew_run(&job.crew);
    free(a), free(xb), free(sums);
    return 0;
#else
    (void)n, (void)x, (void)rows, (void)channels, (void)index, (void)taps, (void)offsets, (void)entries;
    (void)listed, (void)packed, (void)outputs, (void)shift, (void)residual, (void)relu, (void)threads, (void)out;
    return -2;
#endif
}
