/* The U-Net in inference (o3dvis/nn/network.py, o3dvis/nn/unet.py): its input per octree leaf, its
 * up-samplings for the nodes that exist, and its layers one after the other in one call. */

#include "kernels.h"

/* The U-Net's input per octree leaf, as o3dvis/nn/network.py's _signal computes it with torch ops:
 * the mean over each leaf's points of [the point's coordinates inside its cell of a 2^depth grid,
 * in [-1, 1) (((p + 1) 2^depth / 2) less its truncation, times 2, less 1), the point, then its
 * normal where normals is not NULL]. Sums in float32 in the points' order, as index_add_ sums them.
 * leaf: (n,) each point's leaf in [0, leaves); out: (leaves, channels) zeroed by the caller,
 * channels 6 or 9; counts: (leaves,) float32 zeroed by the caller. Returns 0, -1 (nothing written)
 * for a leaf out of [0, leaves), -2 when a leaf has no point. */
int o3dvis_leaf_means(int64_t n, const float *points, const float *normals, const int64_t *leaf, int32_t depth,
                      int64_t leaves, float *counts, float *out) {
    const float half = (float)(1 << depth) / 2.0f;
    const int channels = normals ? 9 : 6;
    int outside = 0;
    for (int64_t i = 0; i < n; i++) outside |= (leaf[i] < 0) | (leaf[i] >= leaves);
    if (outside) return -1;
    for (int64_t i = 0; i < n; i++) {
        float *o = out + leaf[i] * channels;
        for (int a = 0; a < 3; a++) {
            const float u = (points[3 * i + a] + 1.0f) * half;
            o[a] += (u - truncf(u)) * 2.0f - 1.0f;
            o[3 + a] += points[3 * i + a];
            if (normals) o[6 + a] += normals[3 * i + a];
        }
        counts[leaf[i]] += 1.0f;
    }
    int empty = 0;
    for (int64_t l = 0; l < leaves; l++) {
        empty |= counts[l] == 0.0f;
        for (int c = 0; c < channels; c++) out[l * channels + c] /= counts[l];
    }
    return empty ? -2 : 0;
}

#define UPSAMPLE_ROWS 256 /* rows of an item of o3dvis_upsample's crew job: a multiple of 4 */

struct upsample_job {
    struct crew_job crew;
    int64_t n;
    const float *x;
    int channels;
    const int64_t *rows;
    const float *weight;
    int outputs, relu;
    const float *shift, *residual, *addend;
    float *out;
};

/* out[i][j] of o3dvis_upsample from the sum v of its products: plus the shift, plus the residual,
 * through the ReLU, plus the addend, each where given */
#define UPSAMPLE_FINISH(v, i, j, ADD, MAX)                                                                   \
    do {                                                                                                     \
        if (s->residual) v = ADD(v, s->residual + (i) * outputs + (j));                                      \
        if (relu) v = MAX(v);                                                                                \
        if (s->addend) v = ADD(v, s->addend + (i) * outputs + (j));                                          \
    } while (0)

/* A worker of o3dvis_upsample: the items of UPSAMPLE_ROWS rows it claims. */
static void upsample_worker(struct crew_job *crew_job, int worker) {
    (void)worker;
    const struct upsample_job *s = (const struct upsample_job *)crew_job;
    const int channels = s->channels, outputs = s->outputs, relu = s->relu;
    const float *x = s->x, *weight = s->weight, *shift = s->shift;
    const int64_t *rows = s->rows, stride = 8 * (int64_t)outputs;
    float *out = s->out;
    for (int64_t item = crew_claim(crew_job); item >= 0; item = crew_claim(crew_job)) {
        int64_t i = item * UPSAMPLE_ROWS;
        const int64_t end = s->n - i < UPSAMPLE_ROWS ? s->n : i + UPSAMPLE_ROWS;
#ifdef __AVX512F__
        /* the sums of four rows in up to sixteen registers: four rows' chains of multiply-adds side by side */
        if (outputs % 16 == 0 && outputs <= 64)
            for (; i + 4 <= end; i += 4) {
                const int t = outputs / 16;
                const float *xp[4], *w[4];
                __m512 acc[4][4];
                for (int r = 0; r < 4; r++) {
                    xp[r] = x + (rows[i + r] >> 3) * channels, w[r] = weight + (rows[i + r] & 7) * outputs;
                    for (int u = 0; u < 4; u++) acc[r][u] = _mm512_setzero_ps();
                }
                for (int k = 0; k < channels; k++)
                    for (int r = 0; r < 4; r++) {
                        const __m512 a = _mm512_set1_ps(xp[r][k]);
                        const float *wk = w[r] + k * stride;
                        for (int u = 0; u < t; u++)
                            acc[r][u] = _mm512_fmadd_ps(a, _mm512_loadu_ps(wk + 16 * u), acc[r][u]);
                    }
#define ADD_V(v, p) _mm512_add_ps(v, _mm512_loadu_ps(p))
#define MAX_V(v) _mm512_max_ps(v, _mm512_setzero_ps())
                for (int r = 0; r < 4; r++)
                    for (int u = 0; u < t; u++) {
                        __m512 v = _mm512_add_ps(acc[r][u], _mm512_loadu_ps(shift + 16 * u));
                        UPSAMPLE_FINISH(v, i + r, 16 * u, ADD_V, MAX_V);
                        _mm512_storeu_ps(out + (i + r) * outputs + 16 * u, v);
                    }
#undef ADD_V
#undef MAX_V
            }
#endif
        for (; i < end; i++) {
            const float *xp = x + (rows[i] >> 3) * channels, *w = weight + (rows[i] & 7) * outputs;
            float *o = out + i * outputs;
            for (int j = 0; j < outputs; j++) o[j] = 0.0f;
            for (int k = 0; k < channels; k++) {
                const float a = xp[k], *wk = w + k * stride;
                for (int j = 0; j < outputs; j++) o[j] = MADD(a, wk[j], o[j]);
            }
#define ADD_S(v, p) ((v) + *(p))
#define MAX_S(v) ((v) < 0.0f ? 0.0f : (v))
            for (int j = 0; j < outputs; j++) {
                float v = o[j] + shift[j];
                UPSAMPLE_FINISH(v, i, j, ADD_S, MAX_S);
                o[j] = v;
            }
#undef ADD_S
#undef MAX_S
        }
    }
}

/* An up-sampling of the U-Net in inference, as o3dvis/nn/conv.py's OctreeUpsample and ConvBnRelu
 * compute it, for the rows that exist only: out[i] = relu?(x[p] W_o + shift + residual[i]) +
 * addend[i] with p = rows[i] / 8 the parent's row of x (parents, channels) and o = rows[i] % 8 the
 * octant, W_o the octant's outputs columns of weight (channels, 8 outputs); each sum in float32 along
 * the channels in order, multiply-adds fused where the CPU fuses them (as a matrix product's sums
 * run), then the shift added, then the residual and the addend (n, outputs) where not NULL, each
 * sum rounded to float32 as torch's adds round it; the rows shared out among up to threads threads,
 * the caller's and the crew's. out: (n, outputs). Returns 0, or with nothing written -1 for a row out
 * of [0, 8 parents), -5 for threads out of [1, CREW_MAX + 1]. */
int o3dvis_upsample(int64_t n, const float *x, int64_t parents, int32_t channels, const int64_t *rows,
                    const float *weight, int32_t outputs, const float *shift, const float *residual, int32_t relu,
                    const float *addend, int32_t threads, float *out) {
    if (threads < 1 || threads > CREW_MAX + 1) return -5;
    int outside = 0;
    for (int64_t i = 0; i < n; i++) outside |= (rows[i] < 0) | (rows[i] >= 8 * parents);
    if (outside) return -1;
    const int64_t items = (n + UPSAMPLE_ROWS - 1) / UPSAMPLE_ROWS;
    struct upsample_job job = {{upsample_worker, items, 0, crew_workers(threads, items), 0}, n, x, channels, rows,
                               weight, outputs, relu, shift, residual, addend, out};
    crew_run(&job.crew);
    return 0;
}

/* The fields of a layer of o3dvis_unet, an int64 each (the pointers' addresses too): the kind (0 a
 * convolution of o3dvis_gather_conv, 1 an up-sampling of o3dvis_upsample); the buffers of its input,
 * residual and addend (-1: none; buffer 0 is the network's input, buffer i + 1 the output of layer
 * i); the input channels, outputs, taps (of a convolution), ReLU; the packed weight (pack_conv's, or
 * the up-sampling's) and shift; the output rows; the index (a convolution's (rows, taps), an
 * up-sampling's rows), and a convolution's offsets, entries and listed of o3dvis_conv_entries. */
enum { UNET_KIND, UNET_INPUT, UNET_RESIDUAL, UNET_ADDEND, UNET_CHANNELS, UNET_OUTPUTS, UNET_TAPS, UNET_RELU,
       UNET_WEIGHT, UNET_SHIFT, UNET_ROWS, UNET_INDEX, UNET_OFFSETS, UNET_ENTRIES, UNET_LISTED, UNET_FIELDS };
#define UNET_MAX_LAYERS 256

/* Layers of an octree U-Net in inference, one after the other in one call: each as o3dvis_gather_conv
 * or o3dvis_upsample computes it (the same sums), on up to threads threads where its multiply-adds
 * reach shared_work, else on the caller's alone; intermediate outputs in buffers of its own, the last
 * layer's in out. table: layers x UNET_FIELDS, its addresses those of live arrays of the right
 * sizes (the caller's to keep so; a layer checks its index as it runs); x: (rows, channels) the
 * input. Returns 0, or -6 for a table that does not hold together (a buffer that is not an earlier
 * one, channels or a residual's or an addend's shape that are not its buffer's, a convolution's
 * channels odd or outputs not a multiple of 16, a null address, layers out of [1,
 * UNET_MAX_LAYERS]), -1 when out of memory, or a layer's own code
 * (see o3dvis_gather_conv and o3dvis_upsample: -1 for an up-sampling's row out of range); *failed:
 * the layer that failed. -2 in a build without AVX-512 bfloat16. */
int o3dvis_unet(int32_t layers, const int64_t *table, int64_t rows, int32_t channels, const float *x,
                int32_t threads, int64_t shared_work, float *out, int32_t *failed) {
#ifdef __AVX512BF16__
    *failed = -1;
    if (layers < 1 || layers > UNET_MAX_LAYERS || rows < 0 || channels < 1) return -6;
    if (threads < 1 || threads > CREW_MAX + 1) return -5;
    const float *in[UNET_MAX_LAYERS + 1];
    float *made[UNET_MAX_LAYERS + 1] = {NULL};
    int64_t height[UNET_MAX_LAYERS + 1], width[UNET_MAX_LAYERS + 1];
    in[0] = x, height[0] = rows, width[0] = channels;
    for (int i = 0; i < layers; i++) { /* the table holds together before anything runs */
        const int64_t *f = table + (int64_t)i * UNET_FIELDS;
        const int64_t src = f[UNET_INPUT], res = f[UNET_RESIDUAL], add = f[UNET_ADDEND];
        const int64_t c = f[UNET_CHANNELS], o = f[UNET_OUTPUTS], n = f[UNET_ROWS];
        int bad = (f[UNET_KIND] != 0 && f[UNET_KIND] != 1) || src < 0 || src > i || res < -1 || res > i || add < -1 ||
                  add > i || n < 0 || o < 1 || o > INT32_MAX / 8 || c != width[src < 0 ? 0 : src] || !f[UNET_WEIGHT] ||
                  !f[UNET_SHIFT] || !f[UNET_INDEX];
        if (f[UNET_KIND] == 0)
            bad |= c % 2 || o % 16 || f[UNET_TAPS] < 1 || f[UNET_TAPS] > INT32_MAX / c || add >= 0 ||
                   !f[UNET_OFFSETS] || !f[UNET_ENTRIES] || f[UNET_LISTED] < 0;
        if (!bad && res >= 0) bad |= height[res] != n || width[res] != o;
        if (!bad && add >= 0) bad |= height[add] != n || width[add] != o;
        if (bad) return *failed = i, -6;
        height[i + 1] = n, width[i + 1] = o;
    }
    int code = 0;
    for (int i = 0; i < layers && !code; i++) {
        const int64_t *f = table + (int64_t)i * UNET_FIELDS;
        const int64_t n = f[UNET_ROWS], c = f[UNET_CHANNELS], o = f[UNET_OUTPUTS];
        const int64_t taps = f[UNET_KIND] ? 1 : f[UNET_TAPS];
        float *dst = i == layers - 1 ? out : (made[i + 1] = malloc(sizeof(float) * (size_t)(n * o + 1)));
        if (dst == NULL) {
            code = -1;
            break;
        }
        in[i + 1] = dst;
        const float *res = f[UNET_RESIDUAL] < 0 ? NULL : in[f[UNET_RESIDUAL]];
        const int t = n * taps * c * o < shared_work ? 1 : threads;
        if (f[UNET_KIND] == 0)
            code = o3dvis_gather_conv(n, in[f[UNET_INPUT]], height[f[UNET_INPUT]], (int32_t)c,
                                      (const int64_t *)(intptr_t)f[UNET_INDEX], (int32_t)taps,
                                      (const int64_t *)(intptr_t)f[UNET_OFFSETS],
                                      (const int64_t *)(intptr_t)f[UNET_ENTRIES], f[UNET_LISTED],
                                      (const uint32_t *)(intptr_t)f[UNET_WEIGHT], (int32_t)o,
                                      (const float *)(intptr_t)f[UNET_SHIFT], res, (int32_t)f[UNET_RELU], t, dst);
        else
            code = o3dvis_upsample(n, in[f[UNET_INPUT]], height[f[UNET_INPUT]], (int32_t)c,
                                   (const int64_t *)(intptr_t)f[UNET_INDEX], (const float *)(intptr_t)f[UNET_WEIGHT],
                                   (int32_t)o, (const float *)(intptr_t)f[UNET_SHIFT], res, (int32_t)f[UNET_RELU],
                                   f[UNET_ADDEND] < 0 ? NULL : in[f[UNET_ADDEND]], t, dst);
        if (code) *failed = i;
    }
    for (int i = 1; i <= layers; i++) free(made[i]);
    return code;
#else
    (void)layers, (void)table, (void)rows, (void)channels, (void)x, (void)threads, (void)shared_work, (void)out;
    *failed = -1;
    return -2;
#endif
}
