/* The C kernels of o3dvis (o3dvis/nn/native/): what every file of the library shares, its
 * arithmetic helpers, the helper threads' job, a view's description, and the library's functions.
 *
 * The library is C with no dependency but POSIX threads (the bfloat16 MLP with the AVX512-BF16
 * intrinsics, the float32 one with GCC/Clang vector extensions), built by setup.py from every file
 * of this folder into one shared library per instruction set (o3dvis/clib.py) and loaded with
 * ctypes (o3dvis/nn/native/_library.py), which releases the GIL: the view workers run it side by
 * side. The convolutions, up-samplings, view margins and the keys' sort also share one call's
 * blocks with a crew of helper threads kept between calls (threads.c), their answers the same to
 * the bit on any number of threads. Every buffer but the convolutions' scratch is allocated by
 * the caller.
 *
 * The arithmetic is torch's, op for op, but: sin, cos, log, atan2, exp and tanh are short
 * polynomials (a few float32 ulps off, with fused multiply-adds where the CPU has them); asinh is
 * log(|x| + sqrt(x^2 + 1)), or its series below 1/8, where torch's log1p form loses digits; the
 * pixel size enters as its reciprocal; the mean view direction is summed in double. A point
 * within an ulp of a pixel border may thus land on the other side. The bfloat16 MLP rounds to
 * nearest even, as torch rounds. Built with -fno-math-errno -fno-trapping-math
 * -ffp-contract=off, so that the loops vectorise and rounding follows torch's op order (the
 * MLPs aside: their sums run in another order than oneDNN's, with multiply-adds fused as it
 * fuses them).
 */

#ifndef O3DVIS_KERNELS_H
#define O3DVIS_KERNELS_H

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifdef __AVX512F__
#include <immintrin.h>
#endif

#define BLOCK 64          /* points per block: the block's buffers stay in L1 */
#define MAX_SCALES 7      /* depth-buffer scales */
#define MAX_CUES (9 * MAX_SCALES)
#define MAX_EMBED 64      /* 3 + 6 x frequencies */
#define MAX_INPUTS (MAX_EMBED + MAX_CUES + 1)
#define MAX_WIDTH 128     /* the widest hidden layer of the fused MLP */

/* a function of the library that other files of it call, which the library does not export */
#define INTERNAL __attribute__((visibility("hidden")))

/* a * b + c, fused where the CPU has fused multiply-adds (the polynomials below) */
#ifdef FP_FAST_FMAF
#define MADD(a, b, c) fmaf(a, b, c)
#else
#define MADD(a, b, c) ((a) * (b) + (c))
#endif

static inline uint32_t bits_of(float x) { uint32_t u; memcpy(&u, &x, 4); return u; }
static inline float float_of(uint32_t u) { float x; memcpy(&x, &u, 4); return x; }

/* log(u) for finite normal u > 0: the exponent, and a polynomial on the mantissa
   reduced to [sqrt(1/2) - 1, sqrt(2) - 1] (Cephes' logf scheme) */
static inline float log_pos(float u) {
    uint32_t b = bits_of(u);
    float e = (float)((int32_t)(b >> 23) - 126);
    float m = float_of((b & 0x007fffffu) | 0x3f000000u); /* [0.5, 1) */
    int low = m < 0.707106781186547524f;
    e = low ? e - 1.0f : e;
    float f = low ? m + m - 1.0f : m - 1.0f;
    float z = f * f;
    float p = 7.0376836292e-2f;
    p = MADD(p, f, -1.1514610310e-1f);
    p = MADD(p, f, 1.1676998740e-1f);
    p = MADD(p, f, -1.2420140846e-1f);
    p = MADD(p, f, 1.4249322787e-1f);
    p = MADD(p, f, -1.6668057665e-1f);
    p = MADD(p, f, 2.0000714765e-1f);
    p = MADD(p, f, -2.4999993993e-1f);
    p = MADD(p, f, 3.3333331174e-1f);
    float r = f * z * p;
    r = r - 2.12194440e-4f * e;
    r = r - 0.5f * z;
    return f + r + 0.693359375f * e;
}

static inline uint16_t bf16_of(float x) { /* round to nearest even; x is finite */
    uint32_t u = bits_of(x);
    return (uint16_t)((u + 0x7fffu + ((u >> 16) & 1u)) >> 16);
}

/* atan(t) for 0 <= t <= 1: reduced to |t| <= tan(pi / 8), then an odd polynomial (Cephes' atanf) */
static inline float atan_01(float t) {
    int big = t > 0.414213562373095f;
    float x = big ? (t - 1.0f) / (t + 1.0f) : t;
    float z = x * x;
    float p = 8.05374449538e-2f;
    p = MADD(p, z, -1.38776856032e-1f);
    p = MADD(p, z, 1.99777106478e-1f);
    p = MADD(p, z, -3.33329491539e-1f);
    float r = x + x * z * p;
    return big ? r + 0.785398163397448f : r;
}

/* atan2(s, z) for s >= 0, in [0, pi] */
static inline float atan2_pos(float s, float z) {
    float az = fabsf(z);
    int steep = s > az;
    float t = steep ? az / s : (az > 0.0f ? s / az : 0.0f);
    float a = atan_01(t);
    a = steep ? 1.57079632679490f - a : a;
    return z < 0.0f ? 3.14159265358979f - a : a;
}

/* out = a x b */
static inline void cross(const double *a, const double *b, double *out) {
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

/* Puts bit i of v (< 2^21) at bit 3 i (o3dvis/nn/octree.py, _spread). */
static inline uint64_t spread_bits(uint64_t v) {
    v = (v | v << 32) & 0x1f00000000ffffull;
    v = (v | v << 16) & 0x1f0000ff0000ffull;
    v = (v | v << 8) & 0x100f00f00f00f00full;
    v = (v | v << 4) & 0x10c30c30c30c30c3ull;
    return (v | v << 2) & 0x1249249249249249ull;
}

/* exp(y) for -20 <= y <= 0: y = k ln 2 + r with |r| <= ln 2 / 2 (ln 2 in two parts, as Cephes'
   expf), exp(r) by its Taylor series to r^7 (error below 1e-8), times 2^k from the exponent bits */
static inline float exp_neg(float y) {
    const float k = (y * 1.44269504088896341f + 12582912.0f) - 12582912.0f; /* rounded to an integer */
    const float r = (y - k * 0.693359375f) + k * 2.12194440e-4f;
    float p = 1.9841269841e-4f;
    p = MADD(p, r, 1.3888888889e-3f);
    p = MADD(p, r, 8.3333333333e-3f);
    p = MADD(p, r, 4.1666666667e-2f);
    p = MADD(p, r, 1.6666666667e-1f);
    p = MADD(p, r, 0.5f);
    p = MADD(p, r, 1.0f);
    p = MADD(p, r, 1.0f);
    return p * float_of((uint32_t)((int32_t)k + 127) << 23);
}

/* threads.c: the crew of helper threads. A job of items that the calling thread and up to
 * workers - 1 helpers share, each claiming the next item until none is left. */
#define CREW_MAX 64 /* helper threads at most: a kernel's threads lie in [1, CREW_MAX + 1] */

struct crew_job {
    void (*run)(struct crew_job *job, int worker); /* claims items with crew_claim until none is left */
    int64_t items, next;                         /* next: the first item not claimed yet */
    int workers, joined;                         /* the most workers, the caller included; helpers in */
};

/* The next item of the job for a worker, or -1 when every item is claimed. */
static inline int64_t crew_claim(struct crew_job *job) {
    const int64_t item = __atomic_fetch_add(&job->next, 1, __ATOMIC_RELAXED);
    return item < job->items ? item : -1;
}

INTERNAL void crew_run(struct crew_job *job);
INTERNAL int crew_workers(int threads, int64_t items);

/* linalg.c: the symmetric 3x3 eigen-solver of every kernel that needs one. */
INTERNAL void sym3_eigen(const double *a, double *values, double *axis);

/* inputs.c: what the per-view kernels read of a view and its points, filled by the caller
 * (o3dvis/nn/native/margin.py, _view).
 *
 * rows: the points' rows (NULL: start, start + 1, ...); dirs: (N, 3) view
 * directions, rows dirs_stride apart (0: one direction for all); proj: the
 * projected features, channel j of row i at proj[j * proj_ld + i]; zbufs,
 * corners, depth, rpix: as o3dvis_project writes them, widths: (scales,) the
 * buffers' row lengths, sides + 2; perspective: 1 for a camera (a residual's
 * footprint is the depth), 0 for a direction (1); empty: the residual that an
 * empty pixel takes before asinh;
 * normals: (N, 3) for a model with the normal cue, else NULL;
 * leaf: NULL, or the features stored per octree leaf: then proj holds the
 * leaves' values (channel j of leaf l at proj[j * proj_ld + l]), leaf (N,)
 * each point's leaf, and point i's channel j is its leaf's value plus
 * point_weight[3 j .. 3 j + 2] . points[3 i .. 3 i + 2].
 */
struct view {
    const int64_t *rows;
    int64_t start;
    const float *dirs;
    int64_t dirs_stride;
    const float *proj;
    int64_t proj_ld;
    int frequencies;
    const float *zbufs;
    const int32_t *corners;
    const int64_t *widths;
    const float *depth;
    const float *rpix;
    int perspective;
    int scales;
    float empty;
    const float *normals;
    const int64_t *leaf;
    const float *points;
    const float *point_weight;
};

INTERNAL int channels_of(const struct view *v);
INTERNAL void block_inputs(const struct view *v, int64_t b0, int m, float *in);

/* mlp.c: the float32 MLP of the view margins, which the fusion runs too. */
INTERNAL int mlp_f32_fits(int32_t layers, const int32_t *sizes);
INTERNAL const float *mlp_f32(const float *in, int32_t layers, const int32_t *sizes, const float *weights,
                              const float *biases, float h[2][MAX_WIDTH * BLOCK]);

#ifdef __AMX_BF16__
/* tiles.c: the AMX tiles, for the MLP and the convolutions. */
INTERNAL int tiles_granted(void);
INTERNAL void configure_tiles(void);
INTERNAL void release_tiles(void);
#endif

/* The library's functions, each described where it is defined. */
/* octree.c */
void o3dvis_morton_keys(int64_t n, const float *points, int32_t depth, int64_t *keys);
void o3dvis_bounds(int64_t n, const double *points, double *out);
void o3dvis_normalize(int64_t n, const double *points, const double *center, double scale, const double *mean,
                      float *out, int64_t *keys, double *scatter);
int o3dvis_sort_keys(int64_t n, const int64_t *keys, int64_t *sorted, int64_t *order, int64_t *rank,
                     int64_t *scratch, int32_t threads);
int o3dvis_octree_counts(int64_t n, const int64_t *keys, int32_t depth, int32_t full_depth, int64_t *counts);
void o3dvis_octree_fill(int64_t n, const int64_t *keys, int32_t depth, int32_t full_depth, const int64_t *counts,
                        int64_t *point_leaf, int64_t *out);
int o3dvis_child_neighbours(int64_t n, const int64_t *keys, const int64_t *parent, const int64_t *above,
                            int64_t m, const int64_t *children, const int64_t *parent_offset,
                            const int64_t *offset_octant, int64_t *out);
/* noise.c */
int64_t o3dvis_cell_thickness(int64_t n, const float *points, int32_t level, int64_t min_count, double *thickness);
void o3dvis_run_flatness(int64_t runs, const int64_t *starts, int32_t run, const float *points, double *flatness);
/* unet.c */
int o3dvis_leaf_means(int64_t n, const float *points, const float *normals, const int64_t *leaf, int32_t depth,
                      int64_t leaves, float *counts, float *out);
int o3dvis_upsample(int64_t n, const float *x, int64_t parents, int32_t channels, const int64_t *rows,
                    const float *weight, int32_t outputs, const float *shift, const float *residual, int32_t relu,
                    const float *addend, int32_t threads, float *out);
int o3dvis_unet(int32_t layers, const int64_t *table, int64_t rows, int32_t channels, const float *x,
                int32_t threads, int64_t shared_work, float *out, int32_t *failed);
/* conv.c */
int o3dvis_has_gather_conv(void);
int64_t o3dvis_conv_entries(int64_t n, const int64_t *index, int32_t taps, int64_t absent, int64_t *offsets,
                            int64_t *entries);
int o3dvis_gather_conv(int64_t n, const float *x, int64_t rows, int32_t channels, const int64_t *index,
                       int32_t taps, const int64_t *offsets, const int64_t *entries, int64_t listed,
                       const uint32_t *packed, int32_t outputs, const float *shift, const float *residual,
                       int32_t relu, int32_t threads, float *out);
/* views.c */
int o3dvis_project(int64_t n, const float *points, const float *camera, const float *direction,
                   int32_t scales, const int64_t *sides, float *dirs, float *depth, float *uv,
                   float *zbufs, int32_t *corners, float *rpix);
int o3dvis_surfels(int64_t n, const float *points, const int64_t *keys, int32_t finest, int32_t coarsest,
                   int64_t count, float *surfels, float *areas);
int o3dvis_plane_splat(int64_t n, const float *points, const float *surfels, const float *depth,
                       const int8_t *level, int32_t scales, const int64_t *sides, const int32_t *corners,
                       const int64_t *firsts, const float *camera, const float *frame, float half, float slope,
                       float *out);
/* zbuffer.c */
int o3dvis_surfel_zbuffer(int64_t n, const float *points, const float *surfels, const float *camera,
                          int32_t rows, int32_t max_half, int32_t max_wide, float clip, float *out);
/* mlp.c */
int o3dvis_has_view_margin_bf16(void);
int o3dvis_view_margin_bf16(int64_t n, const struct view *v, int32_t layers, const int32_t *sizes,
                            const uint32_t *weights, const float *biases, int32_t threads, float *out);
int o3dvis_view_margin_f32(int64_t n, const struct view *v, int32_t layers, const int32_t *sizes,
                           const float *weights, const float *biases, int32_t threads, float *out);
/* fusion.c */
int o3dvis_fuse_margin(int64_t n, const int64_t *rows, int64_t start, const float *zbuffer, const float *margin,
                       int32_t layers, const int32_t *sizes, const float *weights, const float *biases, float *out);
/* orientation.c */
void o3dvis_fit_planes(int64_t n, int64_t m, int32_t k, const double *points, const int64_t *neighbours,
                       const double *weight, double *normals, uint8_t *planar);
void o3dvis_visibility_affinity(int64_t m, int32_t k, int32_t v, int32_t stride, int64_t first, const float *table,
                                const int64_t *neighbours, float rate, float floor, double *weight);
void o3dvis_votes(int64_t first, int64_t m, int64_t n_all, int32_t v, const double *points, const double *normals,
                  const double *cameras, const float *visibility, double *vote, double *agreement);
/* knn.c */
void o3dvis_key_table(int64_t m, const int64_t *keys, int64_t size, int64_t *table);
void o3dvis_brute_knn(int64_t n, const double *points, int64_t m, const int64_t *rows, int32_t k,
                      int64_t *neighbours);
void o3dvis_grid_knn(const double *points, const int64_t *cells, const int64_t *keys, const int64_t *starts,
                     int64_t size, const int64_t *table, int32_t level, const double *lo, double side,
                     double slack, int32_t k, int64_t first, int64_t last, const int64_t *list,
                     const uint8_t *wanted, int64_t *neighbours, uint8_t *exact);

#endif
