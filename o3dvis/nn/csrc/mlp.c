/* The predictor's MLP on the inputs of inputs.c while they are in the L1 cache
 * (o3dvis/nn/predictor.py, VisibilityPredictor.margin_from_inputs): in bfloat16 with the CPU's
 * bfloat16 dot products (the hidden layers on the AMX tiles where the build and the operating
 * system allow them), or in float32; the blocks of points shared out among the crew. */

#include "kernels.h"

/* Whether this build has o3dvis_view_margin_bf16: it needs the CPU's bfloat16 dot products. */
int o3dvis_has_view_margin_bf16(void) {
#ifdef __AVX512BF16__
    return 1;
#else
    return 0;
#endif
}

#ifdef __AVX512BF16__

/* x: k rows of 16 values (row j at rows + j * ld) -> (k + 1) / 2 rows of 16 pairs of bfloat16,
   rows 2i and 2i + 1 in pair i (a zero after an odd last row) */
static void pair_rows(const float *rows, int64_t ld, int k, uint32_t *x) {
    /* both rows rounded at once ([a, b] as bfloat16), then interleaved: a0 b0 a1 b1 ... */
    const __m512i interleave = _mm512_set_epi16(31, 15, 30, 14, 29, 13, 28, 12, 27, 11, 26, 10, 25, 9, 24, 8,
                                                23, 7, 22, 6, 21, 5, 20, 4, 19, 3, 18, 2, 17, 1, 16, 0);
    for (int i = 0; i < k / 2; i++) {
        const float *a = rows + 2 * i * ld, *b = a + ld;
        const __m512i both = (__m512i)_mm512_cvtne2ps_pbh(_mm512_loadu_ps(b), _mm512_loadu_ps(a));
        _mm512_storeu_si512(x + 16 * i, _mm512_permutexvar_epi16(interleave, both));
    }
    if (k % 2)
        for (int l = 0; l < 16; l++) x[16 * (k / 2) + l] = bf16_of(rows[(k - 1) * ld + l]);
}

/* One layer for 16 points: y (outputs rows of 16) = relu(bias + W x), x as pair_rows writes it,
   pairs rows; w: (pairs, outputs) pairs of bfloat16, outputs a multiple of 16 */
static void dense_relu(const uint32_t *x, int pairs, const uint32_t *w, const float *bias, int outputs,
                       float *y) {
    for (int o0 = 0; o0 < outputs; o0 += 16) {
        __m512 acc[16];
#pragma GCC unroll 16
        for (int j = 0; j < 16; j++) acc[j] = _mm512_set1_ps(bias[o0 + j]);
        for (int i = 0; i < pairs; i++) {
            const __m512bh a = (__m512bh)_mm512_loadu_si512(x + 16 * i);
            const uint32_t *wi = w + (int64_t)i * outputs + o0;
#pragma GCC unroll 16
            for (int j = 0; j < 16; j++)
                acc[j] = _mm512_dpbf16_ps(acc[j], a, (__m512bh)_mm512_set1_epi32((int)wi[j]));
        }
#pragma GCC unroll 16
        for (int j = 0; j < 16; j++) _mm512_storeu_ps(y + 16 * (o0 + j), _mm512_max_ps(acc[j], _mm512_setzero_ps()));
    }
}

/* The last layer's one output for 16 points, rounded to bfloat16 as torch rounds it: x as pair_rows
   writes it, pairs rows; w: pairs pairs of bfloat16; the first min(count, 16) margins to out */
static void last_margins(const uint32_t *x, int pairs, const uint32_t *w, float bias, int count, float *out) {
    __m512 acc = _mm512_set1_ps(bias);
    for (int i = 0; i < pairs; i++)
        acc = _mm512_dpbf16_ps(acc, (__m512bh)_mm512_loadu_si512(x + 16 * i), (__m512bh)_mm512_set1_epi32((int)w[i]));
    float margin[16];
    _mm512_storeu_ps(margin, acc);
    for (int l = 0; l < 16 && l < count; l++) out[l] = float_of((uint32_t)bf16_of(margin[l]) << 16);
}
#endif

#ifdef __AMX_BF16__

#define ROUND16(k) (((k) + 15) / 16 * 16)

/* Where the tiles' path keeps its work (see tile_work): a group's inputs as pair_rows writes them,
   up to MAX_INPUTS / 2 pairs, and its outputs, up to MAX_WIDTH rows of 16 */
#define GROUP_PAIRS (MAX_INPUTS / 2 * 16)
#define GROUP_ROWS (MAX_WIDTH * 16)
#define GROUPS_SIDE_BY_SIDE (BLOCK / 16)

/* The tiles' path's memory: the hidden layers' packed weights (pairs, outputs) and biases as the
   tiles read them, each layer's (outputs, pairs rounded up to 16) pairs of bfloat16, padding zero,
   then its (outputs, 16) biases, each repeated for 16 points; then, for each of a block's groups
   of 16 points, GROUP_PAIRS inputs and GROUP_ROWS outputs. NULL when out of memory. */
static uint32_t *tile_work(int32_t layers, const int32_t *sizes, const uint32_t *w, const float *bias) {
    size_t total = (size_t)GROUPS_SIDE_BY_SIDE * (GROUP_PAIRS + GROUP_ROWS);
    for (int l = 0; l < layers; l++) total += (size_t)sizes[l + 1] * (ROUND16(sizes[l] / 2) + 16);
    uint32_t *work = calloc(total, sizeof *work), *t = work;
    if (work == NULL) return NULL;
    for (int l = 0; l < layers; l++) {
        const int pairs = sizes[l] / 2, kp = ROUND16(pairs), outputs = sizes[l + 1];
        for (int i = 0; i < pairs; i++)
            for (int o = 0; o < outputs; o++) t[o * kp + i] = w[i * outputs + o];
        t += outputs * kp;
        for (int o = 0; o < outputs; o++)
            for (int p = 0; p < 16; p++) t[16 * o + p] = bits_of(bias[o]);
        w += pairs * outputs, t += 16 * outputs, bias += outputs;
    }
    return work;
}

/* dense_relu for the four groups of a block side by side on the tiles, each sum in the order of
   dense_relu's (a pair's two products added as the tiles add them): x, y: the groups' inputs
   (zero from their pairs up to a multiple of 16) and outputs in tile_work; t: the layer's. */
__attribute__((target("amx-tile,amx-bf16")))
static void dense_relu_tiles(const uint32_t *x, int pairs, const uint32_t *t, int outputs, float *y) {
    const int kp = ROUND16(pairs);
    const int64_t xg = GROUP_PAIRS + GROUP_ROWS; /* from a group's inputs or outputs to the next's */
    for (int o0 = 0; o0 < outputs; o0 += 16) {
        const uint32_t *bias = t + outputs * kp + 16 * o0;
        _tile_loadd(0, bias, 64);
        _tile_loadd(1, bias, 64);
        _tile_loadd(2, bias, 64);
        _tile_loadd(3, bias, 64);
        for (int k0 = 0; k0 < kp; k0 += 16) {
            _tile_loadd(4, t + o0 * kp + k0, 4 * kp);
            _tile_loadd(5, x + 16 * k0, 64);
            _tile_dpbf16ps(0, 4, 5);
            _tile_loadd(6, x + xg + 16 * k0, 64);
            _tile_dpbf16ps(1, 4, 6);
            _tile_loadd(5, x + 2 * xg + 16 * k0, 64);
            _tile_dpbf16ps(2, 4, 5);
            _tile_loadd(6, x + 3 * xg + 16 * k0, 64);
            _tile_dpbf16ps(3, 4, 6);
        }
        _tile_stored(0, y + 16 * o0, 64);
        _tile_stored(1, y + xg + 16 * o0, 64);
        _tile_stored(2, y + 2 * xg + 16 * o0, 64);
        _tile_stored(3, y + 3 * xg + 16 * o0, 64);
    }
    for (int g = 0; g < GROUPS_SIDE_BY_SIDE; g++)
        for (int o = 0; o < outputs; o++) {
            float *row = y + g * xg + 16 * o;
            _mm512_storeu_ps(row, _mm512_max_ps(_mm512_loadu_ps(row), _mm512_setzero_ps()));
        }
}
#endif

/* The work of o3dvis_view_margin_bf16 and _f32: the blocks of BLOCK points are the crew's items. */
struct margin_job {
    struct crew_job crew;
    int64_t n;
    const struct view *v;
    int channels, layers;
    const int32_t *sizes;
    const void *weights; /* pairs of bfloat16, or float32 */
    const float *biases;
    float *out;
};

#ifdef __AVX512BF16__

/* A worker of o3dvis_view_margin_bf16: the blocks it claims. */
static void margin_worker_bf16(struct crew_job *crew_job, int worker) {
    (void)worker;
    const struct margin_job *s = (const struct margin_job *)crew_job;
    const struct view *v = s->v;
    const int channels = s->channels, layers = s->layers;
    const int32_t *sizes = s->sizes;
    const uint32_t *weights = s->weights, *last = weights; /* the last layer's weights and bias */
    const float *biases = s->biases, *last_bias = biases;
    float in[MAX_INPUTS * BLOCK] = {0}, y[MAX_WIDTH * 16], *out = s->out;
    uint32_t x[MAX_WIDTH / 2 * 16];
    for (int l = 0; l < layers; l++) last += sizes[l] / 2 * sizes[l + 1], last_bias += sizes[l + 1];
    int64_t b = crew_claim(crew_job);
    if (b < 0) return;
#ifdef __AMX_BF16__
    uint32_t *work = NULL; /* the hidden layers on the AMX tiles, where there are some */
    if (layers > 0 && tiles_granted() && (work = tile_work(layers, sizes, weights, biases)) != NULL) configure_tiles();
#endif
    for (; b >= 0; b = crew_claim(crew_job)) {
        const int64_t b0 = b * BLOCK;
        const int m = s->n - b0 < BLOCK ? (int)(s->n - b0) : BLOCK;
        block_inputs(v, b0, m, in);
#ifdef __AMX_BF16__
        if (work != NULL) {
            uint32_t *t = work, *xs;
            for (int l = 0; l < layers; l++) t += sizes[l + 1] * (ROUND16(sizes[l] / 2) + 16);
            xs = t;
            for (int g = 0; g < GROUPS_SIDE_BY_SIDE; g++)
                pair_rows(in + 16 * g, BLOCK, channels, xs + g * (GROUP_PAIRS + GROUP_ROWS));
            t = work;
            for (int l = 0; l < layers; l++) {
                const int pairs = sizes[l] / 2;
                float *ys = (float *)(xs + GROUP_PAIRS);
                for (int g = 0; g < GROUPS_SIDE_BY_SIDE; g++) /* zero up to a whole tile of pairs */
                    memset(xs + g * (GROUP_PAIRS + GROUP_ROWS) + 16 * pairs, 0,
                           sizeof *xs * 16 * (ROUND16(pairs) - pairs));
                dense_relu_tiles(xs, pairs, t, sizes[l + 1], ys);
                t += sizes[l + 1] * (ROUND16(pairs) + 16);
                for (int g = 0; g < GROUPS_SIDE_BY_SIDE; g++)
                    pair_rows(ys + g * (GROUP_PAIRS + GROUP_ROWS), 16, sizes[l + 1],
                              xs + g * (GROUP_PAIRS + GROUP_ROWS));
            }
            for (int g = 0; 16 * g < m; g++)
                last_margins(xs + g * (GROUP_PAIRS + GROUP_ROWS), sizes[layers] / 2, last, last_bias[0],
                             m - 16 * g, out + b0 + 16 * g);
            continue;
        }
#endif
        for (int g = 0; g < m; g += 16) {
            const uint32_t *w = weights;
            const float *bias = biases;
            pair_rows(in + g, BLOCK, channels, x);
            for (int l = 0; l < layers; l++) {
                dense_relu(x, sizes[l] / 2, w, bias, sizes[l + 1], y);
                w += sizes[l] / 2 * sizes[l + 1], bias += sizes[l + 1];
                pair_rows(y, 16, sizes[l + 1], x);
            }
            last_margins(x, sizes[layers] / 2, last, last_bias[0], m - g, out + b0 + g);
        }
    }
#ifdef __AMX_BF16__
    if (work != NULL) release_tiles(), free(work);
#endif
}
#endif

/* Writes the margins of n points for one view: the predictor's MLP (o3dvis/nn/predictor.py,
 * VisibilityPredictor.margin_from_inputs) on the inputs block_inputs writes, each product in
 * bfloat16 with float32 sums, each layer's output rounded to bfloat16 as torch rounds it; the blocks
 * of points shared out among up to threads threads, the caller's and the crew's. Returns 0, -1 when
 * the sizes exceed the buffers or do not match, -2 in a build without o3dvis_has_view_margin_bf16,
 * -5 for threads out of [1, CREW_MAX + 1].
 *
 * layers: the hidden layers; sizes: (layers + 2,) the inputs, padded to even, each
 * hidden layer's outputs, padded to a multiple of 16, then 1; weights: each layer's (sizes[l] / 2,
 * sizes[l + 1]) pairs of bfloat16 along its inputs; biases: each layer's sizes[l + 1] float32.
 * Padding weighs zero. out: (n,) float32.
 */
int o3dvis_view_margin_bf16(int64_t n, const struct view *v, int32_t layers, const int32_t *sizes,
                            const uint32_t *weights, const float *biases, int32_t threads, float *out) {
#ifdef __AVX512BF16__
    const int channels = channels_of(v);
    if (threads < 1 || threads > CREW_MAX + 1) return -5;
    if (channels < 0 || layers < 0 || sizes[0] != channels + channels % 2 || sizes[layers + 1] != 1) return -1;
    for (int l = 1; l <= layers; l++)
        if (sizes[l] < 16 || sizes[l] % 16 || sizes[l] > MAX_WIDTH) return -1;
    const int64_t blocks = (n + BLOCK - 1) / BLOCK;
    struct margin_job job = {{margin_worker_bf16, blocks, 0, crew_workers(threads, blocks), 0}, n, v, channels,
                             layers, sizes, weights, biases, out};
    crew_run(&job.crew);
    return 0;
#else
    (void)n, (void)v, (void)layers, (void)sizes, (void)weights, (void)biases, (void)threads, (void)out;
    return -2;
#endif
}

/* A vector of the compiler's (GCC and Clang vector extensions) as wide as the CPU's registers, and
   how many of them a layer's step takes along the points: 4 x 4 x 16 sums in the 32 AVX-512
   registers, 4 x 2 x 8 in the 16 of AVX, 4 x 2 x 4 in those of SSE and NEON */
#if defined(__AVX512F__)
#define LANES 16
#define GROUPS 4
#elif defined(__AVX__)
#define LANES 8
#define GROUPS 2
#else
#define LANES 4
#define GROUPS 2
#endif
typedef float vfloat __attribute__((vector_size(4 * LANES)));
typedef float vfloat_u __attribute__((vector_size(4 * LANES), aligned(4), may_alias)); /* for loads */
typedef int32_t vint __attribute__((vector_size(4 * LANES)));

/* One layer for a block: y (outputs rows of BLOCK) = bias + W x, through a ReLU but for the last
 * layer; x: inputs rows of BLOCK, w: (outputs, inputs), outputs a multiple of 4. Four outputs of
 * GROUPS x LANES points at a time, whose sums stay in registers; multiply-adds fused, as in BLAS. */
__attribute__((optimize("fp-contract=fast")))
static void dense_f32(const float *restrict x, int inputs, const float *restrict w, const float *restrict bias,
                      int outputs, int relu, float *restrict y) {
    const vfloat zero = {0};
    for (int o = 0; o < outputs; o += 4)
        for (int b0 = 0; b0 < BLOCK; b0 += GROUPS * LANES) {
            vfloat acc[4][GROUPS];
#pragma GCC unroll 4
            for (int r = 0; r < 4; r++)
#pragma GCC unroll 4
                for (int g = 0; g < GROUPS; g++) acc[r][g] = zero + bias[o + r];
            for (int i = 0; i < inputs; i++) {
                vfloat xi[GROUPS];
#pragma GCC unroll 4
                for (int g = 0; g < GROUPS; g++) xi[g] = *(const vfloat_u *)(x + i * BLOCK + b0 + g * LANES);
#pragma GCC unroll 4
                for (int r = 0; r < 4; r++) {
                    const float wr = w[(o + r) * inputs + i];
#pragma GCC unroll 4
                    for (int g = 0; g < GROUPS; g++) acc[r][g] += wr * xi[g];
                }
            }
#pragma GCC unroll 4
            for (int r = 0; r < 4; r++)
#pragma GCC unroll 4
                for (int g = 0; g < GROUPS; g++) { /* a copy stored: acc itself stays in registers */
                    vfloat sum = acc[r][g];
                    if (relu) /* the bits of the positive sums kept, the others cleared */
                        sum = (vfloat)((vint)sum & (sum > zero));
                    memcpy(y + (o + r) * BLOCK + b0 + g * LANES, &sum, sizeof sum);
                }
        }
}

/* Whether float32 MLP sizes (layers + 2,) fit dense_f32 and the buffers: every layer's outputs a
 * multiple of 4 and at most MAX_WIDTH. */
int mlp_f32_fits(int32_t layers, const int32_t *sizes) {
    if (layers < 0) return 0;
    for (int l = 1; l <= layers + 1; l++)
        if (sizes[l] < 4 || sizes[l] % 4 || sizes[l] > MAX_WIDTH) return 0;
    return 1;
}

/* Runs a packed float32 MLP (see o3dvis_view_margin_f32) on a block of inputs (rows of BLOCK);
 * returns the row of its output, in h. */
const float *mlp_f32(const float *in, int32_t layers, const int32_t *sizes, const float *weights,
                            const float *biases, float h[2][MAX_WIDTH * BLOCK]) {
    const float *x = in, *w = weights, *bias = biases;
    for (int l = 0; l <= layers; l++) {
        dense_f32(x, sizes[l], w, bias, sizes[l + 1], l < layers, h[l % 2]);
        x = h[l % 2], w += sizes[l] * sizes[l + 1], bias += sizes[l + 1];
    }
    return x;
}

/* A worker of o3dvis_view_margin_f32: the blocks it claims. */
static void margin_worker_f32(struct crew_job *crew_job, int worker) {
    (void)worker;
    const struct margin_job *s = (const struct margin_job *)crew_job;
    float in[MAX_INPUTS * BLOCK] = {0}, h[2][MAX_WIDTH * BLOCK];
    for (int64_t b = crew_claim(crew_job); b >= 0; b = crew_claim(crew_job)) {
        const int64_t b0 = b * BLOCK;
        const int m = s->n - b0 < BLOCK ? (int)(s->n - b0) : BLOCK;
        block_inputs(s->v, b0, m, in);
        memcpy(s->out + b0, mlp_f32(in, s->layers, s->sizes, s->weights, s->biases, h), sizeof(float) * m);
    }
}

/* o3dvis_view_margin_bf16 in float32, in plain C: each layer's products and sums in float32, as
 * torch's float32 products but for the order of the sums. sizes: (layers + 2,) the inputs, each
 * hidden layer's outputs, padded to a multiple of 4, then 4 (the margin and 3 of padding);
 * weights: each layer's (sizes[l + 1], sizes[l]) float32 weights; threads as for
 * o3dvis_view_margin_bf16. */
int o3dvis_view_margin_f32(int64_t n, const struct view *v, int32_t layers, const int32_t *sizes,
                           const float *weights, const float *biases, int32_t threads, float *out) {
    const int channels = channels_of(v);
    if (threads < 1 || threads > CREW_MAX + 1) return -5;
    if (channels < 0 || sizes[0] != channels || !mlp_f32_fits(layers, sizes)) return -1;
    const int64_t blocks = (n + BLOCK - 1) / BLOCK;
    struct margin_job job = {{margin_worker_f32, blocks, 0, crew_workers(threads, blocks), 0}, n, v, channels,
                             layers, sizes, weights, biases, out};
    crew_run(&job.crew);
    return 0;
}
