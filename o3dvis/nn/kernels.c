/* The per-view work of the visibility predictor in C, for queries on the CPU, and the octree's keys.
 *
 * o3dvis_project builds a view's projection (o3dvis/nn/cues.py, ViewProjection:
 * view directions, depths, the multi-scale min-depth buffers inside a border)
 * in a few passes over the points instead of some sixty torch ops.
 * o3dvis_view_margin_bf16 and o3dvis_view_margin_f32 compute the first MLP
 * layer's inputs a block of points at a time: the view embedding times the
 * projected feature, then the asinh of the depth residuals to the 3x3 pixels
 * around each point at every cue scale, which o3dvis/nn/cues.py
 * (ViewProjection.cues) and o3dvis/nn/predictor.py (ViewEmbedding, the product
 * with the features) compute in a dozen eager torch ops, each a pass over
 * memory; and they run the predictor's MLP on them while they are in the L1
 * cache (VisibilityPredictor.margin_from_inputs), in bfloat16 with the CPU's
 * bfloat16 dot products (the hidden layers on the AMX tiles where the build and
 * the operating system allow them), or in float32. o3dvis_surfel_zbuffer tests each point
 * against a z-buffer of discs (o3dvis/nn/zbuffer.py) and o3dvis_fuse_margin
 * runs the fusion of its answer with the margin (o3dvis/nn/fusion.py) in one
 * pass. And for the encoding, o3dvis_morton_keys computes the octree's Morton
 * keys (o3dvis/nn/octree.py, cell_keys) in one pass instead of some twenty,
 * o3dvis_sort_keys sorts them (a radix sort, faster than torch.sort), o3dvis_bounds and
 * o3dvis_normalize put a cloud in the unit cube, with its keys, in two passes instead of some ten,
 * o3dvis_octree_counts and o3dvis_octree_fill an octree's levels from its sorted keys (Octree), in
 * two passes instead of some forty ops, o3dvis_child_neighbours a level's 3x3x3 neighbours from its
 * parents' (Octree.neighbours)
 * in one instead of some ten, o3dvis_cell_thickness and o3dvis_run_flatness the noise cues' patch
 * terms (o3dvis/nn/noise.py: sums and eigenvalues), o3dvis_upsample the
 * U-Net's up-samplings for the nodes that exist,
 * o3dvis_leaf_means the U-Net's input (o3dvis/nn/network.py) and, with bfloat16 dot products
 * (on the AMX tiles where there are some), o3dvis_gather_conv each of its convolutions but the
 * up-samplings (o3dvis/nn/conv.py, ConvBnRelu), skipping the missing neighbours by the lists of
 * o3dvis_conv_entries;
 * for oriented normals, o3dvis_fit_planes the plane fits of
 * o3dvis/orientation.py, o3dvis_visibility_affinity their neighbours' weights, o3dvis_votes the
 * cameras' votes on their sides, and o3dvis_grid_knn the nearest neighbours it fits
 * them to, sought in the cells of a grid (o3dvis_key_table hashes the cells; o3dvis_brute_knn
 * searches all points for the few the grid cannot answer).
 *
 * The arithmetic is torch's, op for op, but: sin, cos, log, atan2, exp and tanh
 * are short polynomials (a few float32 ulps off, with fused multiply-adds where
 * the CPU has them); asinh is log(|x| + sqrt(x^2 + 1)), or its series below
 * 1/8, where torch's log1p form loses digits; the pixel size enters as its reciprocal;
 * the mean view direction is summed in double. A point within an ulp of a
 * pixel border may thus land on the other side. The bfloat16 MLP rounds to
 * nearest even, as torch rounds.
 *
 * C with no dependency but POSIX threads (the bfloat16 MLP with the AVX512-BF16
 * intrinsics, the float32 one with GCC/Clang vector extensions), loaded with
 * ctypes (o3dvis/nn/native.py), which releases the GIL: the view workers run it
 * side by side. The convolutions, up-samplings, view margins and the keys' sort
 * also share one call's blocks with a crew of helper threads kept between calls
 * (see crew_run), their answers the same to the bit on any number of threads.
 * Every buffer but the convolutions' scratch is allocated by the caller. Built with
 * -fno-math-errno -fno-trapping-math -ffp-contract=off, so that the loops
 * vectorise and rounding follows torch's op order (the MLPs aside: their sums
 * run in another order than oneDNN's, with multiply-adds fused as it fuses them).
 */

#include <math.h>
#include <pthread.h>
#include <sched.h>
#include <signal.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#ifdef __AVX512F__
#include <immintrin.h>
#endif

#define BLOCK 64          /* points per block: the block's buffers stay in L1 */
#define MAX_SCALES 7      /* depth-buffer scales */
#define MAX_CUES (9 * MAX_SCALES)
#define MAX_EMBED 64      /* 3 + 6 x frequencies */
#define MAX_INPUTS (MAX_EMBED + MAX_CUES + 1)
#define MAX_WIDTH 128     /* the widest hidden layer of the fused MLP */

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

/* asinh(x) = sign(x) log(|x| + sqrt(x^2 + 1)), below |x| = 1/8 its odd series to x^9 (error
   under 3e-12): no division, and accurate where torch's log1p form loses digits */
static inline float asinh_f(float v) {
    const float a = fabsf(v), a2 = a * a;
    float p = 3.0381944444e-2f;
    p = MADD(p, a2, -4.4642857143e-2f);
    p = MADD(p, a2, 7.5e-2f);
    p = MADD(p, a2, -1.6666666667e-1f);
    const float small = MADD(a * a2, p, a);
    return copysignf(a < 0.125f ? small : log_pos(a + sqrtf(a2 + 1.0f)), v);
}

#ifdef __AVX512F__
/* With AVX-512, asinh for 1/8 <= |x| < 2^13 by pieces: a polynomial of degree ASINH_DEGREE in u
   on each half of each octave, |x| = 2^(k / 2 - 3) (1.25 + (k % 2) / 2 + u) with |u| <= 1/4 on
   piece k, its coefficients picked from registers by the exponent and first mantissa bit. Fitted
   when the library loads, interpolating asinh at Chebyshev nodes: error under 1e-6 (a float32 ulp
   or two) where the log's own polynomial, a square root and a blend cost twice as much. */
#define ASINH_PIECES 32
#define ASINH_DEGREE 5
static float asinh_pieces[ASINH_DEGREE + 1][ASINH_PIECES];

__attribute__((constructor)) static void fit_asinh_pieces(void) {
    enum { D = ASINH_DEGREE + 1 };
    for (int k = 0; k < ASINH_PIECES; k++) {
        const double scale = ldexp(1.0, k / 2 - 3), centre = 1.25 + 0.5 * (k % 2);
        double m[D][D + 1]; /* the Vandermonde system of the nodes, the values in the last column */
        for (int j = 0; j < D; j++) {
            const double u = 0.25 * cos(3.14159265358979323846 * (2 * j + 1) / (2 * D));
            double power = 1.0;
            for (int c = 0; c < D; c++) m[j][c] = power, power *= u;
            m[j][D] = asinh(scale * (centre + u));
        }
        for (int c = 0; c < D; c++) { /* Gaussian elimination, pivoting on the largest entry */
            int pivot = c;
            for (int j = c + 1; j < D; j++) pivot = fabs(m[j][c]) > fabs(m[pivot][c]) ? j : pivot;
            for (int e = 0; e <= D; e++) {
                const double t = m[c][e];
                m[c][e] = m[pivot][e], m[pivot][e] = t;
            }
            for (int j = c + 1; j < D; j++) {
                const double f = m[j][c] / m[c][c];
                for (int e = c; e <= D; e++) m[j][e] -= f * m[c][e];
            }
        }
        for (int c = D - 1; c >= 0; c--) {
            double sum = m[c][D];
            for (int e = c + 1; e < D; e++) sum -= m[c][e] * (double)asinh_pieces[e][k];
            asinh_pieces[c][k] = (float)(sum / m[c][c]);
        }
    }
}

/* asinh of n values, n a multiple of 16, |x| < 2^13 */
static void asinh_inplace(float *restrict x, int64_t n) {
    __m512 lo[ASINH_DEGREE + 1], hi[ASINH_DEGREE + 1]; /* pieces 0-15 and 16-31 of each coefficient */
    for (int c = 0; c <= ASINH_DEGREE; c++)
        lo[c] = _mm512_loadu_ps(asinh_pieces[c]), hi[c] = _mm512_loadu_ps(asinh_pieces[c] + 16);
    for (int64_t i = 0; i < n; i += 16) {
        const __m512 v = _mm512_loadu_ps(x + i), a = _mm512_abs_ps(v);
        const __m512i bits = _mm512_castps_si512(a);
        /* the piece: exponent and first mantissa bit, from 1/8 on; u from the other mantissa bits */
        const __m512i piece = _mm512_min_epi32(
            _mm512_max_epi32(_mm512_sub_epi32(_mm512_srli_epi32(bits, 22), _mm512_set1_epi32(2 * 124)),
                             _mm512_setzero_si512()),
            _mm512_set1_epi32(ASINH_PIECES - 1));
        const __m512 u = _mm512_sub_ps(_mm512_castsi512_ps(_mm512_ternarylogic_epi32(
                                           bits, _mm512_set1_epi32(0x3fffff), _mm512_set1_epi32(0x3f800000), 0xea)),
                                       _mm512_set1_ps(1.25f));
        __m512 big = _mm512_permutex2var_ps(lo[ASINH_DEGREE], piece, hi[ASINH_DEGREE]);
        for (int c = ASINH_DEGREE - 1; c >= 0; c--)
            big = _mm512_fmadd_ps(big, u, _mm512_permutex2var_ps(lo[c], piece, hi[c]));
        const __m512 a2 = _mm512_mul_ps(a, a); /* the odd series below 1/8, as asinh_f */
        __m512 p = _mm512_set1_ps(3.0381944444e-2f);
        p = _mm512_fmadd_ps(p, a2, _mm512_set1_ps(-4.4642857143e-2f));
        p = _mm512_fmadd_ps(p, a2, _mm512_set1_ps(7.5e-2f));
        p = _mm512_fmadd_ps(p, a2, _mm512_set1_ps(-1.6666666667e-1f));
        const __m512 small = _mm512_fmadd_ps(_mm512_mul_ps(a, a2), p, a);
        const __m512 r = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(a, _mm512_set1_ps(0.125f), _CMP_LT_OQ), big, small);
        /* the sign of v: its bit where the mask has it, r's bits elsewhere */
        _mm512_storeu_ps(x + i, _mm512_castsi512_ps(_mm512_ternarylogic_epi32(
                                    _mm512_set1_epi32((int)0x80000000u), _mm512_castps_si512(v), _mm512_castps_si512(r),
                                    0xca)));
    }
}
#else
static void asinh_inplace(float *restrict x, int64_t n) {
    for (int64_t i = 0; i < n; i++) x[i] = asinh_f(x[i]);
}
#endif

/* sin(pi t) for |t| <= 1/2: Taylor series to degree 13 (error below 1e-11) */
static inline float sin_pi_half(float t) {
    float w = 3.14159265358979f * t, w2 = w * w;
    float p = 1.6059043836821613e-10f;
    p = MADD(p, w2, -2.5052108385441720e-8f);
    p = MADD(p, w2, 2.7557319223985893e-6f);
    p = MADD(p, w2, -1.9841269841269841e-4f);
    p = MADD(p, w2, 8.3333333333333333e-3f);
    p = MADD(p, w2, -1.6666666666666667e-1f);
    return w + w * w2 * p;
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

static void cross(const double *a, const double *b, double *out) {
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

/* Two unit vectors orthogonal to the unit vector forward, as cues.py's _frame */
static void frame(const double *forward, double *right, double *up) {
    double helper[3] = {0.0, 0.0, 1.0};
    if (fabs(forward[2]) > 0.9) { helper[0] = 1.0; helper[2] = 0.0; }
    cross(forward, helper, right);
    double norm = sqrt(right[0] * right[0] + right[1] * right[1] + right[2] * right[2]);
    for (int a = 0; a < 3; a++) right[a] /= norm;
    cross(forward, right, up);
}

/* Puts bit i of v (< 2^21) at bit 3 i (o3dvis/nn/octree.py, _spread). */
static inline uint64_t spread_bits(uint64_t v) {
    v = (v | v << 32) & 0x1f00000000ffffull;
    v = (v | v << 16) & 0x1f0000ff0000ffull;
    v = (v | v << 8) & 0x100f00f00f00f00full;
    v = (v | v << 4) & 0x10c30c30c30c30c3ull;
    return (v | v << 2) & 0x1249249249249249ull;
}

/* The Morton keys of n points of [-1, 1]^3 on a 2^depth grid, 1 <= depth <= 21, as
 * o3dvis/nn/octree.py's morton_encode(grid_cells(points, depth), depth) computes them in some
 * twenty passes: each coordinate's cell, (p + 1) 2^depth / 2 truncated and clamped to the grid (NaN
 * to 0), the three cells' bits interleaved with x highest. */
void o3dvis_morton_keys(int64_t n, const float *points, int32_t depth, int64_t *keys) {
    const float half = (float)(1 << (depth - 1)), top = (float)((1 << depth) - 1);
    for (int64_t i = 0; i < n; i++) {
        uint64_t cell[3];
        for (int a = 0; a < 3; a++) {
            float q = (points[3 * i + a] + 1.0f) * half;
            q = q >= 0.0f ? q : 0.0f;
            cell[a] = (uint64_t)(q < top ? q : top);
        }
        keys[i] = (int64_t)(spread_bits(cell[0]) << 2 | spread_bits(cell[1]) << 1 | spread_bits(cell[2]));
    }
}

/* The per-axis minimum, maximum and sum of n points (n, 3) float64, into out: lo[3], hi[3], sum[3]
 * (o3dvis/nn/octree.py, bounding_box: NaN where an axis has one, as torch's min and max). Eight
 * points a step, each lane of the step its own minimum, maximum and sum: the loop vectorises and
 * its sums do not wait on each other (so they add in another order than one running sum). */
void o3dvis_bounds(int64_t n, const double *points, double *out) {
    double lo[24], hi[24], sum[24];
    for (int k = 0; k < 24; k++) lo[k] = INFINITY, hi[k] = -INFINITY, sum[k] = 0.0;
    int64_t i = 0;
    for (; i + 8 <= n; i += 8) {
        const double *p = points + 3 * i;
        for (int k = 0; k < 24; k++) {
            const double x = p[k];
            lo[k] = x < lo[k] || x != x ? x : lo[k], hi[k] = x > hi[k] || x != x ? x : hi[k], sum[k] += x;
        }
    }
    for (; i < n; i++)
        for (int a = 0; a < 3; a++) {
            const double x = points[3 * i + a];
            lo[a] = x < lo[a] || x != x ? x : lo[a], hi[a] = x > hi[a] || x != x ? x : hi[a], sum[a] += x;
        }
    for (int k = 3; k < 24; k++) {
        const int a = k % 3;
        lo[a] = lo[k] < lo[a] || lo[k] != lo[k] ? lo[k] : lo[a];
        hi[a] = hi[k] > hi[a] || hi[k] != hi[k] ? hi[k] : hi[a];
        sum[a] += sum[k];
    }
    for (int a = 0; a < 3; a++) out[a] = lo[a], out[3 + a] = hi[a], out[6 + a] = sum[a];
}

/* The normalised cloud in one pass (o3dvis/nn/octree.py, normalize_points then .float(), then
 * cell_keys at MORTON_DEPTH): each coordinate (p - center) / scale in float64, rounded to float32
 * into out (n, 3); the Morton keys of those float32 points on the 2^21 grid into keys, as
 * o3dvis_morton_keys computes them; and into scatter the sums of the products of the float64
 * offsets from mean (3,): xx, xy, xz, yy, yz, zz. Eight points a step (the arithmetic along
 * their 24 coordinates vectorises). */
void o3dvis_normalize(int64_t n, const double *points, const double *center, double scale, const double *mean,
                      float *out, int64_t *keys, double *scatter) {
    const float half = (float)(1 << 20), top = (float)((1 << 21) - 1);
    double c24[24], m24[24], s[6] = {0};
    for (int k = 0; k < 24; k++) c24[k] = center[k % 3], m24[k] = mean[k % 3];
    uint64_t spread[256]; /* spread_bits of a byte: a cell's 21 bits in three lookups */
    for (int k = 0; k < 256; k++) spread[k] = spread_bits((uint64_t)k);
    for (int64_t i0 = 0; i0 < n; i0 += 8) {
        const int m = n - i0 < 8 ? (int)(n - i0) : 8;
        double q[24] = {0};
        float f[24];
        const double *p = points + 3 * i0;
        if (m == 8)
            for (int k = 0; k < 24; k++) q[k] = (p[k] - c24[k]) / scale;
        else
            for (int k = 0; k < 3 * m; k++) q[k] = (p[k] - c24[k]) / scale;
        for (int k = 0; k < 24; k++) f[k] = (float)q[k], q[k] -= m24[k];
        memcpy(out + 3 * i0, f, (size_t)(3 * m) * sizeof(float));
        for (int b = 0; b < m; b++) {
            uint64_t key = 0;
            for (int a = 0; a < 3; a++) {
                float c = (f[3 * b + a] + 1.0f) * half;
                c = c >= 0.0f ? c : 0.0f;
                const uint32_t cell = (uint32_t)(c < top ? c : top);
                key |= (spread[cell & 255] | spread[(cell >> 8) & 255] << 24 | spread[cell >> 16] << 48) << (2 - a);
            }
            keys[i0 + b] = (int64_t)key;
            const double *d = q + 3 * b;
            s[0] += d[0] * d[0], s[1] += d[0] * d[1], s[2] += d[0] * d[2];
            s[3] += d[1] * d[1], s[4] += d[1] * d[2], s[5] += d[2] * d[2];
        }
    }
    memcpy(scatter, s, sizeof s);
}

/* A crew of helper threads kept for the life of the process, that run a share of a kernel's work
 * beside the calling thread: a kernel of a few hundred microseconds cannot pay for starting a thread
 * (tens of microseconds here), so the helpers are started once and, after each piece of work, wait
 * for the next one spinning for a while (CREW_SPIN_NS), then asleep on a condition variable. The
 * work is claimed item by item from a shared counter, so a helper that starts late (or not at all,
 * on a busy machine) only takes fewer items: the caller runs what is left. A forked child starts
 * with no helpers. */
#define CREW_MAX 64
#define CREW_SPIN_NS 50000

struct crew_job {
    void (*run)(struct crew_job *job, int worker); /* claims items with crew_claim until none is left */
    int64_t items, next;                         /* next: the first item not claimed yet */
    int workers, joined;                         /* the most workers, the caller included; helpers in */
};

static struct {
    pthread_mutex_t lock;
    pthread_cond_t wake;
    struct crew_job *job; /* the one running, NULL between */
    uint64_t posted;      /* jobs posted so far */
    int helpers, sleeping, first_worker;
} crew = {PTHREAD_MUTEX_INITIALIZER, PTHREAD_COND_INITIALIZER, NULL, 0, 0, 0, 0};
static pthread_once_t crew_once = PTHREAD_ONCE_INIT;

static inline void cpu_relax(void) { /* a spinning thread's pause, which leaves the core's units to others */
#if defined(__x86_64__) || defined(__i386__)
    __builtin_ia32_pause();
#elif defined(__aarch64__)
    __asm__ volatile("yield");
#endif
}

/* The next item of the job for a worker, or -1 when every item is claimed. */
static inline int64_t crew_claim(struct crew_job *job) {
    const int64_t item = __atomic_fetch_add(&job->next, 1, __ATOMIC_RELAXED);
    return item < job->items ? item : -1;
}

static uint64_t now_ns(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (uint64_t)t.tv_sec * 1000000000u + (uint64_t)t.tv_nsec;
}

static void *crew_helper(void *unused) {
    (void)unused;
    uint64_t seen = __atomic_load_n(&crew.posted, __ATOMIC_ACQUIRE);
    for (;;) {
        const uint64_t until = now_ns() + CREW_SPIN_NS;
        while (__atomic_load_n(&crew.posted, __ATOMIC_ACQUIRE) == seen && now_ns() < until)
            for (int i = 0; i < 64; i++) cpu_relax();
        pthread_mutex_lock(&crew.lock);
        while (crew.posted == seen) {
            crew.sleeping++;
            pthread_cond_wait(&crew.wake, &crew.lock);
            crew.sleeping--;
        }
        seen = crew.posted;
        struct crew_job *job = crew.job;
        int worker = -1;
        if (job != NULL && crew.first_worker < job->workers) {
            worker = crew.first_worker++;
            __atomic_add_fetch(&job->joined, 1, __ATOMIC_ACQ_REL);
        }
        pthread_mutex_unlock(&crew.lock);
        if (worker >= 0) {
            job->run(job, worker);
            __atomic_sub_fetch(&job->joined, 1, __ATOMIC_RELEASE);
        }
    }
    return NULL;
}

static void crew_forked(void) { /* the child of a fork has this thread only */
    pthread_mutex_init(&crew.lock, NULL);
    pthread_cond_init(&crew.wake, NULL);
    crew.job = NULL, crew.helpers = crew.sleeping = 0;
}

static void crew_register(void) { pthread_atfork(NULL, NULL, crew_forked); }

/* Runs job->run on the calling thread (worker 0) and on up to job->workers - 1 helpers (workers 1,
 * 2, ...), starting helpers that are missing; returns when every worker that joined has returned. */
static void crew_run(struct crew_job *job) {
    job->next = 0, job->joined = 0;
    if (job->workers > 1) {
        pthread_once(&crew_once, crew_register);
        pthread_mutex_lock(&crew.lock);
        while (crew.helpers < job->workers - 1 && crew.helpers < CREW_MAX) {
            pthread_t thread;
            pthread_attr_t attr;
            sigset_t all, before; /* a helper takes no signal: they go to the threads of the program */
            sigfillset(&all);
            pthread_attr_init(&attr);
            pthread_attr_setdetachstate(&attr, PTHREAD_CREATE_DETACHED);
            pthread_sigmask(SIG_SETMASK, &all, &before);
            const int failed = pthread_create(&thread, &attr, crew_helper, NULL);
            pthread_sigmask(SIG_SETMASK, &before, NULL);
            pthread_attr_destroy(&attr);
            if (failed) break; /* fewer helpers: the caller claims more */
            crew.helpers++;
        }
        crew.job = job, crew.first_worker = 1;
        __atomic_add_fetch(&crew.posted, 1, __ATOMIC_RELEASE);
        if (crew.sleeping) pthread_cond_broadcast(&crew.wake);
        pthread_mutex_unlock(&crew.lock);
    }
    job->run(job, 0);
    if (job->workers > 1) {
        pthread_mutex_lock(&crew.lock);
        if (crew.job == job) crew.job = NULL; /* no helper joins from now on (another caller's may) */
        pthread_mutex_unlock(&crew.lock);
        for (int spins = 0; __atomic_load_n(&job->joined, __ATOMIC_ACQUIRE); spins++)
            if (spins < 4096) cpu_relax();
            else sched_yield();
    }
}

/* The threads a job of items shares out among: threads, but no more than the items. */
static int crew_workers(int threads, int64_t items) { return items < threads ? (items > 1 ? (int)items : 1) : threads; }

struct keyed { int64_t key, index; };

/* Sorts a[0..n) by their keys' bytes below the `digits`-th, stably: one counting pass a byte from the
 * lowest, over the bytes that differ, between a and b (n each). Returns where the result lies. */
static struct keyed *radix_passes(struct keyed *a, struct keyed *b, int64_t n, int digits) {
    uint32_t count[8][256];
    memset(count, 0, sizeof count[0] * digits);
    for (int64_t i = 0; i < n; i++)
        for (int d = 0; d < digits; d++) count[d][(a[i].key >> (8 * d)) & 255]++;
    for (int d = 0; d < digits; d++) {
        if (count[d][(a[0].key >> (8 * d)) & 255] == (uint32_t)n) continue; /* a byte every key shares */
        uint32_t start[256], sum = 0;
        for (int k = 0; k < 256; k++) start[k] = sum, sum += count[d][k];
        for (int64_t i = 0; i < n; i++) b[start[(a[i].key >> (8 * d)) & 255]++] = a[i];
        struct keyed *t = a;
        a = b, b = t;
    }
    return a;
}

/* o3dvis_sort_keys' buckets of the highest byte that differs: each is the crew's item. */
struct sort_job {
    struct crew_job crew;
    struct keyed *a, *b;
    const uint32_t *count; /* the buckets' starts, then n */
    int top;
    int64_t *sorted, *order, *rank;
};

/* A worker of o3dvis_sort_keys: the buckets it claims, sorted on their lower bytes and written out. */
static void sort_worker(struct crew_job *crew_job, int worker) {
    (void)worker;
    const struct sort_job *s = (const struct sort_job *)crew_job;
    for (int64_t k = crew_claim(crew_job); k >= 0; k = crew_claim(crew_job)) {
        const int64_t first = s->count[k], m = s->count[k + 1] - s->count[k];
        if (m == 0) continue;
        const struct keyed *r = radix_passes(s->a + first, s->b + first, m, s->top);
        for (int64_t i = 0; i < m; i++)
            s->sorted[first + i] = r[i].key, s->order[first + i] = r[i].index, s->rank[r[i].index] = first + i;
    }
}

/* Sorts n non-negative keys, n < 2^32, with the permutation that sorts them, as a stable sort
 * (torch.sort(keys, stable=True)) does: one counting pass on the highest byte that differs, then
 * radix_passes on the lower bytes within each of its buckets, which fit in the cache, the buckets
 * shared out among up to threads threads, the caller's and the crew's. sorted, order, rank: (n,)
 * out, rank the inverse permutation (the place of each key); scratch: 4n of the caller's. Returns
 * 0, or with nothing written -1 when a key is negative, -5 for threads out of [1, CREW_MAX + 1]. */
int o3dvis_sort_keys(int64_t n, const int64_t *keys, int64_t *sorted, int64_t *order, int64_t *rank,
                     int64_t *scratch, int32_t threads) {
    if (threads < 1 || threads > CREW_MAX + 1) return -5;
    int64_t any = 0, differ = 0;
    for (int64_t i = 0; i < n; i++) any |= keys[i], differ |= keys[i] ^ keys[0];
    if (any < 0) return -1;
    int top = 0; /* the highest byte in which keys differ */
    while (top < 7 && differ >> (8 * (top + 1))) top++;
    struct keyed *a = (struct keyed *)scratch; /* then b, n more, for radix_passes */
    uint32_t count[257] = {0};
    for (int64_t i = 0; i < n; i++) count[((keys[i] >> (8 * top)) & 255) + 1]++;
    for (int k = 0; k < 256; k++) count[k + 1] += count[k];
    uint32_t start[256];
    memcpy(start, count, sizeof start);
    for (int64_t i = 0; i < n; i++) {
        struct keyed *to = a + start[(keys[i] >> (8 * top)) & 255]++;
        to->key = keys[i], to->index = i;
    }
    struct sort_job job = {{sort_worker, 256, 0, crew_workers(threads, 256), 0}, a, a + n, count, top, sorted, order,
                           rank};
    crew_run(&job.crew);
    return 0;
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

/* The ascending eigenvalues of the symmetric 3x3 matrix [[a, b, c], [b, d, e], [c, e, f]], in closed
 * form: the trigonometric solution of the characteristic cubic for the largest and the smallest;
 * where the smallest is far below the two others, it is their determinant's share instead
 * (det / (largest x middle)), which keeps it to a few ulps of the largest as an iterative solver
 * does, where the cubic's angle would lose half the digits; the middle one from the trace. */
static void sym3_eigenvalues(double a, double b, double c, double d, double e, double f, double *out) {
    const double q = (a + d + f) / 3.0, off = b * b + c * c + e * e;
    const double p2 = (a - q) * (a - q) + (d - q) * (d - q) + (f - q) * (f - q) + 2.0 * off;
    if (!(p2 > 0.0)) {
        out[0] = out[1] = out[2] = q;
        return;
    }
    const double p = sqrt(p2 / 6.0);
    const double x = (a - q) / p, y = (d - q) / p, z = (f - q) / p, u = b / p, v = c / p, w = e / p;
    double r = (x * (y * z - w * w) - u * (u * z - w * v) + v * (u * w - y * v)) / 2.0;
    r = r < -1.0 ? -1.0 : (r > 1.0 ? 1.0 : r);
    const double phi = acos(r) / 3.0;
    const double high = q + 2.0 * p * cos(phi);
    double low = q + 2.0 * p * cos(phi + 2.0943951023931954923);
    double mid = 3.0 * q - high - low;
    if (low < 1e-3 * mid && mid > 1e-6 * high) {
        const double det = a * (d * f - e * e) - b * (b * f - e * c) + c * (b * e - d * c);
        low = det / (high * mid);
        mid = 3.0 * q - high - low;
    }
    out[0] = low, out[1] = mid, out[2] = high;
}

/* The noise cues' cell terms (o3dvis/nn/noise.py) of n points of [-1, 1]^3 sorted so that the
 * points of each cell of a 2^level grid (1 <= level <= 10) are contiguous (along a Morton curve):
 * for each cell with at least min_count points, in the points' order, the square root of the
 * smallest eigenvalue of its covariance (its moments about its centre, summed in double in the
 * points' order, over its count, less the mean's products; clamped at 0) times sqrt(count) times
 * 2^level / 2, into thickness; returns how many. A point's cell is as o3dvis_morton_keys finds it,
 * its offset from the cell's centre is in float32, as torch computes it. The sums of a cell are
 * kept in registers while its points run: no table of the grid's cells is made. */
int64_t o3dvis_cell_thickness(int64_t n, const float *points, int32_t level, int64_t min_count, double *thickness) {
    const int res = 1 << level;
    const float half = (float)(res / 2), top = (float)(res - 1), size = 2.0f / (float)res;
    int64_t run = -1, count = 0, k = 0;
    double s0 = 0, s1 = 0, s2 = 0, s3 = 0, s4 = 0, s5 = 0, s6 = 0, s7 = 0, s8 = 0;
    for (int64_t i = 0; i <= n; i++) {
        float q[3] = {0.0f, 0.0f, 0.0f};
        int64_t cell = -1;
        if (i < n) {
            int c[3];
            for (int a = 0; a < 3; a++) {
                float u = (points[3 * i + a] + 1.0f) * half;
                u = u >= 0.0f ? u : 0.0f;
                c[a] = (int)(u < top ? u : top);
                q[a] = points[3 * i + a] - (((float)c[a] + 0.5f) * size - 1.0f);
            }
            cell = ((int64_t)c[0] * res + c[1]) * res + c[2];
        }
        if (cell != run) {
            if (count >= min_count && count > 0) {
                const double m = (double)count, mx = s6 / m, my = s7 / m, mz = s8 / m;
                double values[3];
                sym3_eigenvalues(s0 / m - mx * mx, s1 / m - mx * my, s2 / m - mx * mz, s3 / m - my * my,
                                 s4 / m - my * mz, s5 / m - mz * mz, values);
                thickness[k++] = sqrt(values[0] > 0.0 ? values[0] : 0.0) * sqrt(m) * ((double)res / 2.0);
            }
            run = cell, count = 0, s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = 0.0;
        }
        count++;
        s0 += (double)(q[0] * q[0]), s1 += (double)(q[0] * q[1]), s2 += (double)(q[0] * q[2]);
        s3 += (double)(q[1] * q[1]), s4 += (double)(q[1] * q[2]), s5 += (double)(q[2] * q[2]);
        s6 += q[0], s7 += q[1], s8 += q[2];
    }
    return k;
}

/* The noise cues' run terms (o3dvis/nn/noise.py): for each of the runs of `run` points from starts[r]
 * (in the points' order), their scatter about their mean (in double), and the square root of its
 * smallest over its middle eigenvalue (each clamped at 0, the middle at the smallest positive
 * double), into flatness. */
void o3dvis_run_flatness(int64_t runs, const int64_t *starts, int32_t run, const float *points, double *flatness) {
    for (int64_t r = 0; r < runs; r++) {
        const float *p = points + 3 * starts[r];
        double mean[3] = {0.0, 0.0, 0.0}, s[6] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0}, values[3];
        for (int i = 0; i < run; i++)
            for (int a = 0; a < 3; a++) mean[a] += (double)p[3 * i + a];
        for (int a = 0; a < 3; a++) mean[a] /= (double)run;
        for (int i = 0; i < run; i++) {
            const double x = (double)p[3 * i] - mean[0], y = (double)p[3 * i + 1] - mean[1],
                         z = (double)p[3 * i + 2] - mean[2];
            s[0] += x * x, s[1] += x * y, s[2] += x * z, s[3] += y * y, s[4] += y * z, s[5] += z * z;
        }
        sym3_eigenvalues(s[0], s[1], s[2], s[3], s[4], s[5], values);
        const double low = values[0] > 0.0 ? values[0] : 0.0, mid = values[1] > 0.0 ? values[1] : 0.0;
        flatness[r] = sqrt(low / (mid > 2.2250738585072014e-308 ? mid : 2.2250738585072014e-308));
    }
}

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

/* Builds one view's projection of n points (n >= 1); returns 0, or -1 for more than
 * MAX_SCALES scales.
 *
 * points: (n, 3); camera: (3,) camera position, or NULL with direction: (3,)
 * unit viewing direction. sides: (scales,) the buffers' resolutions. Writes
 * dirs: (n, 3) unit vectors from the camera (camera only); depth: (n,); uv:
 * (n, 2) scratch; zbufs: each scale's min-depth buffer inside a border, rows
 * sides[s] + 2 apart, one after the other, NaN where empty and on the border;
 * corners: (n, scales) the index in zbufs of the top-left pixel of the 3x3
 * around each point's pixel (zbufs hold fewer than 2^31 values); rpix:
 * (scales,) 1 / pixel size. A residual's scale, -1 / (pixel size x footprint)
 * with the footprint the depth for a camera, else 1, is left to the readers
 * (a product per point and scale, where storing it cost a pass of memory).
 */
int o3dvis_project(int64_t n, const float *points, const float *camera, const float *direction,
                   int32_t scales, const int64_t *sides, float *dirs, float *depth, float *uv,
                   float *zbufs, int32_t *corners, float *rpix) {
    double forward[3], right[3], up[3];
    if (scales < 1 || scales > MAX_SCALES) return -1;
    if (camera) {
        for (int64_t i = 0; i < n; i++) { /* no reduction in this loop: it vectorises */
            float o[3], d2 = 0.0f;
            for (int a = 0; a < 3; a++) { o[a] = points[3 * i + a] - camera[a]; d2 += o[a] * o[a]; }
            float d = sqrtf(d2);
            d = d < 1e-12f ? 1e-12f : d;
            depth[i] = d;
            for (int a = 0; a < 3; a++) dirs[3 * i + a] = o[a] / d;
        }
        double sum[3] = {0.0, 0.0, 0.0};
        for (int64_t i = 0; i < n; i++)
            for (int a = 0; a < 3; a++) sum[a] += dirs[3 * i + a];
        double norm = sqrt(sum[0] * sum[0] + sum[1] * sum[1] + sum[2] * sum[2]);
        norm = norm < 1e-12 * n ? 1e-12 * n : norm;
        for (int a = 0; a < 3; a++) forward[a] = sum[a] / norm;
    } else {
        for (int a = 0; a < 3; a++) forward[a] = direction[a];
    }
    frame(forward, right, up);
    const float rf[3] = {(float)right[0], (float)right[1], (float)right[2]};
    const float uf[3] = {(float)up[0], (float)up[1], (float)up[2]};
    const float ff[3] = {(float)forward[0], (float)forward[1], (float)forward[2]};
    if (camera) { /* azimuthal-equidistant around forward */
        for (int64_t i = 0; i < n; i++) {
            const float *d = dirs + 3 * i;
            float a = d[0] * rf[0] + d[1] * rf[1] + d[2] * rf[2];
            float b = d[0] * uf[0] + d[1] * uf[1] + d[2] * uf[2];
            float z = d[0] * ff[0] + d[1] * ff[1] + d[2] * ff[2];
            float s = sqrtf(a * a + b * b + 1e-24f);
            float k = atan2_pos(s, z) / s;
            uv[2 * i] = a * k, uv[2 * i + 1] = b * k;
        }
    } else { /* parallel */
        for (int64_t i = 0; i < n; i++) {
            const float *p = points + 3 * i;
            uv[2 * i] = p[0] * rf[0] + p[1] * rf[1] + p[2] * rf[2];
            uv[2 * i + 1] = p[0] * uf[0] + p[1] * uf[1] + p[2] * uf[2];
            depth[i] = p[0] * ff[0] + p[1] * ff[1] + p[2] * ff[2];
        }
    }
    float lanes[16] = {0}, half = 0.0f; /* the largest |u|, |v|, in 16 lanes */
    int64_t i = 0;
#ifdef __AVX512F__
    __m512 largest = _mm512_setzero_ps(); /* max_ps keeps its second operand where one is NaN */
    for (; i + 16 <= 2 * n; i += 16) largest = _mm512_max_ps(_mm512_abs_ps(_mm512_loadu_ps(uv + i)), largest);
    _mm512_storeu_ps(lanes, largest);
#endif
    for (; i < 2 * n; i++) {
        const float m = fabsf(uv[i]);
        lanes[i % 16] = m > lanes[i % 16] ? m : lanes[i % 16];
    }
    for (int j = 0; j < 16; j++) half = lanes[j] > half ? lanes[j] : half;
    half = half * (1.0f + 1e-6f) + 1e-12f;
    for (int64_t i = 0; i < 2 * n; i++) uv[i] += half;
    int64_t start[MAX_SCALES], total = 0;
    for (int s = 0; s < scales; s++) {
        const int64_t res = sides[s], w = res + 2;
        start[s] = total, total += w * w;
        /* a product with the reciprocal instead of torch's division by the pixel size: no
           division per point (they are most of the pass), the same pixel but within an ulp */
        rpix[s] = (float)res / (2.0f * half);
        float *zbuf = zbufs + start[s];
        for (int64_t q = 0; q < w * w; q++) zbuf[q] = NAN;
        for (int64_t r = 1; r <= res; r++)
            for (int64_t c = 1; c <= res; c++) zbuf[r * w + c] = INFINITY;
    }
    i = 0;
#ifdef __AVX512F__
    /* the pixels of 16 points at a time in vectors, as the loop below computes them (max_ps gives
       0 for NaN and -0; the clamp by a mask), then their minima one by one, the scales side by
       side: consecutive points often fall into one pixel, and each minimum then waits on the last */
    const __m512i evens = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30),
                  odds = _mm512_add_epi32(evens, _mm512_set1_epi32(1));
    for (; i + 16 <= n; i += 16) {
        const __m512 a = _mm512_loadu_ps(uv + 2 * i), b = _mm512_loadu_ps(uv + 2 * i + 16);
        const __m512 u = _mm512_permutex2var_ps(a, evens, b), v = _mm512_permutex2var_ps(a, odds, b);
        int32_t corner[MAX_SCALES][16];
        for (int s = 0; s < scales; s++) {
            const __m512 scale = _mm512_set1_ps(rpix[s]), edge = _mm512_set1_ps((float)(sides[s] - 1));
            const __m512 fu = _mm512_max_ps(_mm512_mul_ps(u, scale), _mm512_setzero_ps());
            const __m512 fv = _mm512_max_ps(_mm512_mul_ps(v, scale), _mm512_setzero_ps());
            const __m512i top = _mm512_set1_epi32((int)(sides[s] - 1));
            const __m512i iu = _mm512_mask_blend_epi32(_mm512_cmp_ps_mask(fu, edge, _CMP_LT_OQ), top,
                                                       _mm512_cvttps_epi32(fu));
            const __m512i iv = _mm512_mask_blend_epi32(_mm512_cmp_ps_mask(fv, edge, _CMP_LT_OQ), top,
                                                       _mm512_cvttps_epi32(fv));
            const __m512i row = _mm512_mullo_epi32(iu, _mm512_set1_epi32((int)(sides[s] + 2)));
            const __m512i first = _mm512_set1_epi32((int)start[s]);
            _mm512_storeu_si512(corner[s], _mm512_add_epi32(first, _mm512_add_epi32(row, iv)));
        }
        for (int j = 0; j < 16; j++)
            for (int s = 0; s < scales; s++) {
                float *z = zbufs + corner[s][j] + sides[s] + 3;
                *z = depth[i + j] < *z ? depth[i + j] : *z;
                corners[(i + j) * scales + s] = corner[s][j];
            }
    }
#endif
    for (; i < n; i++)
        for (int s = 0; s < scales; s++) {
            const int64_t res = sides[s], w = res + 2;
            /* truncated and clamped to the image as torch's .long().clamp_(); NaN goes to 0 */
            float fu = uv[2 * i] * rpix[s], fv = uv[2 * i + 1] * rpix[s];
            fu = fu >= 0.0f ? fu : 0.0f, fv = fv >= 0.0f ? fv : 0.0f;
            const int64_t iu = fu < (float)(res - 1) ? (int64_t)fu : res - 1;
            const int64_t iv = fv < (float)(res - 1) ? (int64_t)fv : res - 1;
            float *z = zbufs + start[s] + (iu + 1) * w + iv + 1;
            *z = depth[i] < *z ? depth[i] : *z;
            corners[i * scales + s] = (int32_t)(start[s] + iu * w + iv);
        }
    for (int64_t q = 0; q < total; q++) zbufs[q] = zbufs[q] == INFINITY ? NAN : zbufs[q];
    return 0;
}

/* The unit eigenvector of the smallest eigenvalue of the symmetric 3x3 matrix a (row-major), as
 * o3dvis/nn/cues.py's _least_axis finds it: the trigonometric solution of the characteristic
 * cubic, then the longest cross product of two rows of a - lambda I; (0, 0, 1) where none. */
static double least_axis(const double *a, double *axis) {
    const double q = (a[0] + a[4] + a[8]) / 3.0;
    const double off = a[1] * a[1] + a[2] * a[2] + a[5] * a[5];
    const double p =
        sqrt(((a[0] - q) * (a[0] - q) + (a[4] - q) * (a[4] - q) + (a[8] - q) * (a[8] - q) + 2.0 * off) / 6.0);
    const double pp = p > 1e-300 ? p : 1e-300;
    double b[9];
    for (int k = 0; k < 9; k++) b[k] = (a[k] - (k % 4 == 0 ? q : 0.0)) / pp;
    double r = (b[0] * (b[4] * b[8] - b[5] * b[7]) - b[1] * (b[3] * b[8] - b[5] * b[6])
                + b[2] * (b[3] * b[7] - b[4] * b[6])) / 2.0;
    r = r < -1.0 ? -1.0 : (r > 1.0 ? 1.0 : r);
    const double smallest = q + 2.0 * p * cos(acos(r) / 3.0 + 2.0943951023931954923);
    double rows[9], best = 0.0;
    for (int k = 0; k < 9; k++) rows[k] = a[k] - (k % 4 == 0 ? smallest : 0.0);
    axis[0] = 0.0, axis[1] = 0.0, axis[2] = 1.0;
    static const int pairs[3][2] = {{0, 1}, {0, 2}, {1, 2}};
    for (int k = 0; k < 3; k++) {
        double c[3];
        cross(rows + 3 * pairs[k][0], rows + 3 * pairs[k][1], c);
        const double len = sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]);
        if (len > best) best = len, axis[0] = c[0] / len, axis[1] = c[1] / len, axis[2] = c[2] / len;
    }
    return smallest;
}

/* Each point's spacing to its neighbours and the normal of the plane of its cell
 * (o3dvis/nn/cues.py, point_surfels): points (n, 3) sorted by keys, their Morton keys at level
 * finest; each point takes the finest cell of levels coarsest .. finest that holds at least count
 * points, else its coarsest cell: spacing = cell side / sqrt(points in it), normal = the least
 * axis of their covariance (sums in double). surfels: (n, 4). areas: NULL, or (n,) the spacing
 * the points' spread gives: sqrt(12 sqrt(l1 l2) / points), l1 and l2 the two larger eigenvalues
 * of the covariance (the area of a uniformly covered rectangle), at least a tenth of the cell's
 * spacing. Returns -1 where its scratch memory could not be allocated, else 0. */
int o3dvis_surfels(int64_t n, const float *points, const int64_t *keys, int32_t finest, int32_t coarsest,
                   int64_t count, float *surfels, float *areas) {
    int64_t m = 0;
    for (int64_t i = 0; i < n; i++) m += i == 0 || keys[i] != keys[i - 1];
    int64_t *start = malloc((size_t)(m + 1) * sizeof(int64_t));
    double *sums = malloc((size_t)m * 10 * sizeof(double)), *chosen = malloc((size_t)m * 11 * sizeof(double));
    char *done = calloc((size_t)m, 1);
    if (!start || !sums || !chosen || !done) { free(start); free(sums); free(chosen); free(done); return -1; }
    for (int64_t i = 0, c = -1; i < n; i++) { /* per finest cell: count, x, y, z, xx, yy, zz, xy, xz, yz */
        if (i == 0 || keys[i] != keys[i - 1]) start[++c] = i, memset(sums + 10 * c, 0, 10 * sizeof(double));
        const double x = points[3 * i], y = points[3 * i + 1], z = points[3 * i + 2];
        double *t = sums + 10 * c;
        t[0] += 1.0, t[1] += x, t[2] += y, t[3] += z, t[4] += x * x, t[5] += y * y, t[6] += z * z;
        t[7] += x * y, t[8] += x * z, t[9] += y * z;
    }
    start[m] = n;
    for (int level = finest; level >= coarsest; level--) { /* fine to coarse: the finest that holds enough */
        const int shift = 3 * (finest - level);
        for (int64_t a = 0, b; a < m; a = b) {
            double total[10] = {0};
            for (b = a; b < m && (keys[start[b]] >> shift) == (keys[start[a]] >> shift); b++)
                for (int k = 0; k < 10; k++) total[k] += sums[10 * b + k];
            if (total[0] < (double)count && level != coarsest) continue;
            for (int64_t c = a; c < b; c++) {
                if (done[c]) continue;
                done[c] = 1;
                chosen[11 * c] = (2.0 / (double)(1 << level)) / sqrt(total[0]);
                memcpy(chosen + 11 * c + 1, total, 10 * sizeof(double));
            }
        }
    }
    for (int64_t c = 0; c < m; c++) {
        const double *t = chosen + 11 * c + 1, w = t[0];
        const double mx = t[1] / w, my = t[2] / w, mz = t[3] / w;
        const double xy = t[7] / w - mx * my, xz = t[8] / w - mx * mz, yz = t[9] / w - my * mz;
        const double cov[9] = {t[4] / w - mx * mx, xy, xz, xy, t[5] / w - my * my, yz, xz, yz, t[6] / w - mz * mz};
        double axis[3];
        const double least = least_axis(cov, axis);
        /* the product of the two larger eigenvalues, from the sum of the principal 2 x 2 minors */
        const double minors = cov[0] * cov[4] + cov[0] * cov[8] + cov[4] * cov[8] - xy * xy - xz * xz - yz * yz;
        const double product = minors - least * (cov[0] + cov[4] + cov[8] - least);
        const double area = sqrt(12.0 * sqrt(product > 0.0 ? product : 0.0) / w), floor = 0.1 * chosen[11 * c];
        for (int64_t i = start[c]; i < start[c + 1]; i++) {
            surfels[4 * i] = (float)chosen[11 * c];
            for (int k = 0; k < 3; k++) surfels[4 * i + 1 + k] = (float)axis[k];
            if (areas) areas[i] = (float)(area > floor ? area : floor);
        }
    }
    free(start), free(sums), free(chosen), free(done);
    return 0;
}

/* Footprint splats of a view's points as their planes (o3dvis/nn/cues.py, _splat_footprints,
 * whose torch ops this follows op for op): for each scale k >= 1, the nearest of the points
 * assigned to it (level[i] == k; the last of equals) in each of its pixels; then every pixel of
 * each finer scale j whose centre lies in such a pixel takes the smaller of its depth and the
 * depth of that point's plane along the pixel's centre ray, kept within slope times the ray's
 * distance from the point.
 *
 * points: (n, 3); surfels: (n, 4) the spacing (unused here) and unit normal of each point's
 * plane; depth, corners (n, scales) and sides as o3dvis_project writes them, firsts: (scales,)
 * each scale's first value in its buffers; level: (n,) each point's scale, 0 for none; out: the
 * bordered buffers of scales 0 .. scales - 2 to splat into, laid out as the plain ones (firsts);
 * frame: forward, right, up of the view's image; camera: (3,), or NULL for a viewing direction
 * (rays from the image plane through the origin); half: half the image's width.
 * Returns -1 where its scratch memory could not be allocated, else 0.
 */
int o3dvis_plane_splat(int64_t n, const float *points, const float *surfels, const float *depth,
                       const int8_t *level, int32_t scales, const int64_t *sides, const int32_t *corners,
                       const int64_t *firsts, const float *camera, const float *frame, float half, float slope,
                       float *out) {
    const float *f = frame, *rt = frame + 3, *up = frame + 6;
    for (int k = 1; k < scales; k++) {
        const int64_t res = sides[k], w = res + 2;
        int64_t *owner = malloc((size_t)(res * res) * sizeof(int64_t));
        float *nearest = malloc((size_t)(res * res) * sizeof(float));
        if (!owner || !nearest) { free(owner); free(nearest); return -1; }
        for (int64_t q = 0; q < res * res; q++) owner[q] = -1, nearest[q] = INFINITY;
        for (int64_t i = 0; i < n; i++) {
            if (level[i] != k) continue;
            const int64_t rel = corners[i * scales + k] - firsts[k], pix = rel / w * res + rel % w;
            if (depth[i] <= nearest[pix]) nearest[pix] = depth[i], owner[pix] = i;
        }
        for (int j = 0; j < k; j++) {
            const int64_t fine = sides[j], fw = fine + 2;
            const float size = 2.0f * half / (float)fine;
            float *buf = out + firsts[j];
            for (int64_t r = 0; r < fine; r++) {
                const int64_t *row = owner + (2 * r + 1) * res / (2 * fine) * res;
                const float u = ((float)r + 0.5f) * size - half;
                for (int64_t c = 0; c < fine; c++) {
                    const int64_t o = row[(2 * c + 1) * res / (2 * fine)];
                    if (o < 0) continue;
                    const float v = ((float)c + 0.5f) * size - half;
                    float d[3], offset[3];
                    if (camera) {
                        const float theta = sqrtf(u * u + v * v);
                        const float sinc = theta > 1e-12f ? sinf(theta) / theta : 1.0f, cs = cosf(theta);
                        for (int a = 0; a < 3; a++) {
                            d[a] = cs * f[a] + sinc * (u * rt[a] + v * up[a]);
                            offset[a] = points[3 * o + a] - camera[a];
                        }
                    } else {
                        for (int a = 0; a < 3; a++) {
                            d[a] = f[a];
                            offset[a] = points[3 * o + a] - (u * rt[a] + v * up[a]);
                        }
                    }
                    const float *nrm = surfels + 4 * o + 1;
                    const float along = offset[0] * d[0] + offset[1] * d[1] + offset[2] * d[2];
                    float perp2 = 0.0f;
                    for (int a = 0; a < 3; a++) {
                        const float e = offset[a] - along * d[a];
                        perp2 += e * e;
                    }
                    const float lateral = sqrtf(perp2) * slope;
                    float facing = nrm[0] * d[0] + nrm[1] * d[1] + nrm[2] * d[2];
                    facing = fabsf(facing) < 1e-9f ? 1e-9f : facing;
                    float plane = (offset[0] * nrm[0] + offset[1] * nrm[1] + offset[2] * nrm[2]) / facing;
                    const float lo = depth[o] - lateral, hi = depth[o] + lateral;
                    plane = plane > lo ? plane : lo;
                    plane = plane < hi ? plane : hi;
                    float *z = buf + (r + 1) * fw + c + 1;
                    *z = fminf(*z, plane);
                }
            }
        }
        free(owner);
        free(nearest);
    }
    return 0;
}

/* The surfel z-buffer of a camera (o3dvis/nn/zbuffer.py, surfel_zbuffer, whose torch ops this
 * follows): each point is a disc of radius its spacing in the plane of its normal, rendered
 * into a rows x 2 rows latitude-longitude depth buffer around the camera, over each pixel whose
 * centre ray meets the disc (and always over its own pixel; the nearest disc of a pixel, the
 * first of equals); then each point is compared with the plane of the disc in front at its own
 * pixel, along its own ray.
 *
 * points: (n, 3); surfels: (n, 5) spacing, unit normal and area spacing (point_surfels with
 * areas; the area spacing is the disc's radius and the unit of distances); camera: (3,); rows: the buffer's
 * rows; max_half: the largest half height of a disc's pixels, max_wide: the largest half
 * width. out: (n, 4) per point 1 where its own disc is in front (else 0), its distance beyond
 * the front plane in spacings (clipped to +-clip), its spacing in pixels, and |cos| of the
 * angle between its normal and its ray.
 * Returns -1 where its scratch memory could not be allocated, else 0.
 */
int o3dvis_surfel_zbuffer(int64_t n, const float *points, const float *surfels, const float *camera,
                          int32_t rows, int32_t max_half, int32_t max_wide, float clip, float *out) {
    const int64_t cols = 2 * (int64_t)rows, size = rows * cols;
    const float pixel = (float)M_PI / (float)rows, pi = (float)M_PI;
    float *zbuf = malloc((size_t)size * sizeof(float));
    int32_t *owner = malloc((size_t)size * sizeof(int32_t));
    float *table = malloc((size_t)(2 * rows + 2 * cols) * sizeof(float));
    float *geo = malloc((size_t)n * 4 * sizeof(float));
    int64_t *own = malloc((size_t)n * sizeof(int64_t));
    if (!zbuf || !owner || !table || !geo || !own) {
        free(zbuf), free(owner), free(table), free(geo), free(own);
        return -1;
    }
    float *rcos = table, *rsin = table + rows, *ccos = table + 2 * rows, *csin = ccos + cols;
    for (int64_t r = 0; r < rows; r++) {
        const float e = ((float)r + 0.5f) * pixel - pi / 2;
        rcos[r] = cosf(e), rsin[r] = sinf(e);
    }
    for (int64_t c = 0; c < cols; c++) {
        const float a = ((float)c + 0.5f) * pixel - pi;
        ccos[c] = cosf(a), csin[c] = sinf(a);
    }
    for (int64_t q = 0; q < size; q++) zbuf[q] = INFINITY, owner[q] = -1;
    for (int64_t i = 0; i < n; i++) {  /* each point's distance, offset and own pixel */
        const float x = points[3 * i] - camera[0], y = points[3 * i + 1] - camera[1], z = points[3 * i + 2] - camera[2];
        const float h = sqrtf(x * x + y * y), d = sqrtf(x * x + y * y + z * z);
        /* elevation + pi / 2 and azimuth + pi, by the polynomial atan2 */
        const float row = atan2_pos(h, -z) * (float)rows / pi;
        const float col = (y >= 0.0f ? pi + atan2_pos(y, x) : pi - atan2_pos(-y, x)) * (float)rows / pi;
        const int64_t c = (int64_t)col;
        int64_t r = (int64_t)row;
        r = r < rows - 1 ? r : rows - 1;
        geo[4 * i] = x, geo[4 * i + 1] = y, geo[4 * i + 2] = z, geo[4 * i + 3] = d;
        own[i] = r * cols + c % cols;
        /* the pixels whose centres the disc may cover: it reaches r sqrt(1 - (n.e)^2) / (d - r) radians
         * from the point along an image direction e (the small-angle extent of a tilted disc; the
         * margin covers what that neglects), along the meridian in rows, along the parallel in columns */
        const float radius = surfels[5 * i + 4], *nrm = surfels + 5 * i + 1;
        const float reach = radius < d ? radius / (d - radius) / pixel : (float)max_half;
        const float ez = h > 0.0f ? z / (h * d) : 0.0f;
        const float along_v = h > 0.0f ? -ez * (x * nrm[0] + y * nrm[1]) + h / d * nrm[2] : nrm[0];
        const float along_h = h > 0.0f ? (x * nrm[1] - y * nrm[0]) / h : nrm[1];
        const float fv = sqrtf(fmaxf(0.0f, 1.0f - along_v * along_v)) + 0.15f;
        const float fh = sqrtf(fmaxf(0.0f, 1.0f - along_h * along_h)) + 0.15f;
        float half_h = reach * (fv < 1.0f ? fv : 1.0f), half_a = reach * (fh < 1.0f ? fh : 1.0f);
        half_h = half_h < (float)max_half ? half_h : (float)max_half;
        half_a = half_a < (float)max_half ? half_a : (float)max_half;
        const float flat = d > 0.0f ? h / d : 1.0f;  /* the cosine of the elevation */
        float half_w = half_a / (flat > 1e-3f ? flat : 1e-3f);
        /* at most the whole circle of latitude, each of its pixels once */
        const float wide = 0.5f * (float)(cols - 1) < (float)max_wide ? 0.5f * (float)(cols - 1) : (float)max_wide;
        half_w = half_w < wide ? half_w : wide;
        int64_t r0 = (int64_t)ceilf(row - half_h - 0.5f), r1 = (int64_t)floorf(row + half_h - 0.5f);
        int64_t k0 = (int64_t)ceilf(col - half_w - 0.5f), k1 = (int64_t)floorf(col + half_w - 0.5f);
        r0 = r0 < r ? r0 : r, r1 = r1 > r ? r1 : r, k0 = k0 < c ? k0 : c, k1 = k1 > c ? k1 : c;
        r0 = r0 > 0 ? r0 : 0, r1 = r1 < rows - 1 ? r1 : rows - 1;
        const float plane = x * nrm[0] + y * nrm[1] + z * nrm[2], r2 = radius * radius;
        const int64_t c0 = (k0 % cols + cols) % cols, width = k1 - k0 + 1, own_k = c - k0;
        for (int64_t rr = r0; rr <= r1; rr++) {
            const float rc = rcos[rr], rs = rsin[rr], rz = rs * nrm[2];
            float *zrow = zbuf + rr * cols;
            int32_t *orow = owner + rr * cols;
            for (int64_t k = 0; k < width; k++) {
                int64_t cc = c0 + k;
                cc = cc >= cols ? cc - cols : cc;  /* the image wraps around in azimuth */
                const float ray[3] = {rc * ccos[cc], rc * csin[cc], rs};
                const float depth = plane / (ray[0] * nrm[0] + ray[1] * nrm[1] + rz);
                const float ex = ray[0] * depth - x, ey = ray[1] * depth - y, ez = ray[2] * depth - z;
                const int valid = depth > 0.0f && depth < INFINITY;
                /* a disc always covers its own pixel, at the point's distance where its plane misses the ray */
                const int hit = (valid & (ex * ex + ey * ey + ez * ez <= r2)) | ((rr == r) & (k == own_k));
                const float z0 = valid ? depth : d;
                const int take = hit & (z0 < zrow[cc]);
                zrow[cc] = take ? z0 : zrow[cc];
                orow[cc] = take ? (int32_t)i : orow[cc];
            }
        }
    }
    for (int64_t i = 0; i < n; i++) {
        const int64_t j = owner[own[i]];
        const float d = geo[4 * i + 3], *nrm = surfels + 5 * j + 1, radius = surfels[5 * j + 4];
        const float *o = geo + 4 * j;
        const float facing = (geo[4 * i] * nrm[0] + geo[4 * i + 1] * nrm[1] + geo[4 * i + 2] * nrm[2]) / d;
        float along = (o[0] * nrm[0] + o[1] * nrm[1] + o[2] * nrm[2]) / facing;
        along = isnan(along) ? INFINITY : along;
        const float lo = o[3] - 3.0f * radius, hi = o[3] + 3.0f * radius;
        along = along < lo ? lo : along > hi ? hi : along;
        float beyond = (d - along) / surfels[5 * i + 4];
        beyond = isnan(beyond) ? 0.0f : beyond < -clip ? -clip : beyond > clip ? clip : beyond;
        const float *mine = surfels + 5 * i + 1;
        const float cosine = (geo[4 * i] * mine[0] + geo[4 * i + 1] * mine[1] + geo[4 * i + 2] * mine[2]) / d;
        out[4 * i] = j == i ? 1.0f : 0.0f;
        out[4 * i + 1] = beyond;
        out[4 * i + 2] = surfels[5 * i + 4] / d / pixel;
        out[4 * i + 3] = isnan(cosine) ? 0.0f : fabsf(cosine);
    }
    free(zbuf), free(owner), free(table), free(geo), free(own);
    return 0;
}

/* What the kernels below read of a view and its points, filled by the caller (native.py, _View).
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

/* Writes the 3x3 depths around the pixels of m <= BLOCK points (rows idx) at every scale into
 * cue, channels first: row 9 s + 3 r + j holds the pixel at row r, column j of the 3x3 at scale s. */
static void gather_patches(const struct view *v, const int64_t *idx, int m, float *cue) {
    for (int s = 0; s < v->scales; s++) {
        const int64_t w = v->widths[s];
        float *c = cue + 9 * s * BLOCK;
#ifdef __AVX512F__
        /* 16 points a step: each row of a point's 3x3 in one load of three floats, expanded into
           a 128-bit lane (three only: the buffers' last pixel ends the tensor), four points a
           vector, then each lane transposed so that a vector holds one pixel of the 16 points */
        int32_t corner[BLOCK];
        int b = 0;
        for (; b < m; b++) corner[b] = v->corners[idx[b] * v->scales + s];
        for (; b % 16; b++) corner[b] = corner[0];
        for (b = 0; b < m; b += 16)
            for (int r = 0; r < 3; r++) {
                const float *z = v->zbufs + r * w;
                __m512 q[4];
                for (int k = 0; k < 4; k++) {
                    q[k] = _mm512_maskz_loadu_ps(0x7, z + corner[b + k]);
                    for (int l = 1; l < 4; l++)
                        q[k] = _mm512_mask_expandloadu_ps(q[k], (__mmask16)(0x7 << 4 * l), z + corner[b + 4 * l + k]);
                }
                const __m512d t0 = _mm512_castps_pd(_mm512_unpacklo_ps(q[0], q[1]));
                const __m512d t1 = _mm512_castps_pd(_mm512_unpacklo_ps(q[2], q[3]));
                const __m512d t2 = _mm512_castps_pd(_mm512_unpackhi_ps(q[0], q[1]));
                const __m512d t3 = _mm512_castps_pd(_mm512_unpackhi_ps(q[2], q[3]));
                float *row = c + 3 * r * BLOCK + b;
                _mm512_storeu_ps(row, _mm512_castpd_ps(_mm512_unpacklo_pd(t0, t1)));
                _mm512_storeu_ps(row + BLOCK, _mm512_castpd_ps(_mm512_unpackhi_pd(t0, t1)));
                _mm512_storeu_ps(row + 2 * BLOCK, _mm512_castpd_ps(_mm512_unpacklo_pd(t2, t3)));
            }
#else
        for (int b = 0; b < m; b++) {
            const float *z = v->zbufs + v->corners[idx[b] * v->scales + s];
            for (int r = 0; r < 3; r++)
                for (int j = 0; j < 3; j++) c[(3 * r + j) * BLOCK + b] = z[r * w + j];
        }
#endif
    }
}

/* Writes the first layer's inputs of the block of m <= BLOCK points from the b0-th, as rows of
 * BLOCK floats: the embedding times the feature (3 + 6 frequencies rows), the cues (9 scales
 * rows), then with normals the cosine of the normal and the reversed view direction. Rows past m
 * hold finite values of no meaning. */
static void block_inputs(const struct view *v, int64_t b0, int m, float *in) {
    const int ne = 3 + 6 * v->frequencies, nc = 9 * v->scales, scales = v->scales;
    float *cue = in + ne * BLOCK, dep[BLOCK], kd[BLOCK], k[BLOCK], px[BLOCK], py[BLOCK], pz[BLOCK];
    int32_t lf[BLOCK]; /* leaves number fewer than points (MAX_POINTS): 32 bits, for vector gathers */
    const float empty = v->empty; /* a local: the stores below could otherwise change it */
    int64_t idx[BLOCK];
    for (int b = 0; b < m; b++) idx[b] = v->rows ? v->rows[b0 + b] : v->start + b0 + b;
    /* the 3x3 depths around each point's pixels (channels first: the arithmetic below runs
       along contiguous rows), then its residuals to them in pixel footprints, clamped, with
       empty pixels marked */
    gather_patches(v, idx, m, cue);
    for (int b = 0; b < m; b++) dep[b] = v->depth[idx[b]];
    for (int b = 0; b < m; b++) kd[b] = v->perspective ? -1.0f / dep[b] : -1.0f;
    for (int s = 0; s < scales; s++) { /* -1 / (footprint x pixel size), as torch's cues compute it */
        for (int b = 0; b < m; b++) k[b] = kd[b] * v->rpix[s];
        for (int j = 0; j < 9; j++) {
            float *c = cue + (9 * s + j) * BLOCK;
            for (int b = 0; b < m; b++) {
                float r = (c[b] - dep[b]) * k[b];
                r = r < -50.0f ? -50.0f : r;
                r = r > 50.0f ? 50.0f : r;
                c[b] = r != r ? empty : r;
            }
        }
    }
    asinh_inplace(cue, (int64_t)BLOCK * nc);
    /* embedding [d, sin(pi d), cos(pi d), sin(2 pi d), ...], channels first */
    for (int a = 0; a < 3; a++) {
        float *d = in + a * BLOCK;
        for (int b = 0; b < m; b++) d[b] = v->dirs[idx[b] * v->dirs_stride + a];
        if (!v->frequencies) continue;
        for (int b = 0; b < m; b++) {
            const float t = d[b] > 0.5f ? 1.0f - d[b] : (d[b] < -0.5f ? -1.0f - d[b] : d[b]);
            in[(3 + a) * BLOCK + b] = sin_pi_half(t);
            in[(6 + a) * BLOCK + b] = sin_pi_half(0.5f - fabsf(d[b]));
        }
        for (int f = 1; f < v->frequencies; f++) {
            const float *s = in + (6 * f - 3 + a) * BLOCK, *c = in + (6 * f + a) * BLOCK;
            float *s2 = in + (6 * f + 3 + a) * BLOCK, *c2 = in + (6 * f + 6 + a) * BLOCK;
            for (int b = 0; b < m; b++) {
                s2[b] = s[b] * c[b] * 2.0f;
                c2[b] = s[b] * s[b] * -2.0f + 1.0f;
            }
        }
    }
    if (v->normals) { /* -(n . d), before the directions are multiplied by the features */
        float *c = in + (ne + nc) * BLOCK;
        for (int b = 0; b < m; b++) {
            const float *nrm = v->normals + 3 * idx[b];
            c[b] = -(nrm[0] * in[b] + nrm[1] * in[BLOCK + b] + nrm[2] * in[2 * BLOCK + b]);
        }
    }
    if (v->leaf) { /* each point's leaf and coordinates, for the features below */
        for (int b = 0; b < m; b++) {
            const float *q = v->points + 3 * idx[b];
            lf[b] = (int32_t)v->leaf[idx[b]], px[b] = q[0], py[b] = q[1], pz[b] = q[2];
        }
    }
#ifdef __AVX512F__
    /* per 16 points: their leaves as offsets from the first, and whether those fit 16 lanes (points
       along the Morton curve share few leaves), so that one load and a permute fetch them */
    __m512i offset[BLOCK / 16];
    int32_t first[BLOCK / 16];
    __mmask16 window[BLOCK / 16];
    if (v->leaf)
        for (int g = 0; 16 * g + 16 <= m; g++) {
            const __m512i leaves = _mm512_loadu_si512(lf + 16 * g);
            const int32_t lo = _mm512_reduce_min_epi32(leaves), hi = _mm512_reduce_max_epi32(leaves);
            const int64_t left = v->proj_ld - lo; /* leaves from lo to the end of the row */
            first[g] = lo, offset[g] = _mm512_sub_epi32(leaves, _mm512_set1_epi32(lo));
            window[g] = hi - lo >= 16 ? 0 : (left >= 16 ? 0xffff : (__mmask16)((1u << left) - 1));
        }
#endif
    for (int j = 0; j < ne; j++) {
        const float *p = v->proj + j * v->proj_ld;
        float *e = in + j * BLOCK;
        if (v->leaf) { /* the leaf's value plus the point's term, in the order of torch's addmm_ */
            const float *w = v->point_weight + 3 * j;
            int b = 0;
#ifdef __AVX512F__ /* the same, 16 points a step (compilers tuned for any x86-64 do not gather) */
            const __m512 w0 = _mm512_set1_ps(w[0]), w1 = _mm512_set1_ps(w[1]), w2 = _mm512_set1_ps(w[2]);
            for (; b + 16 <= m; b += 16) {
                const int g = b / 16;
                const __m512 leaf =
                    window[g] ? _mm512_permutexvar_ps(offset[g], _mm512_maskz_loadu_ps(window[g], p + first[g]))
                              : _mm512_i32gather_ps(_mm512_loadu_si512(lf + b), p, 4);
                __m512 t = _mm512_add_ps(_mm512_mul_ps(w0, _mm512_loadu_ps(px + b)),
                                         _mm512_mul_ps(w1, _mm512_loadu_ps(py + b)));
                t = _mm512_add_ps(leaf, _mm512_add_ps(t, _mm512_mul_ps(w2, _mm512_loadu_ps(pz + b))));
                _mm512_storeu_ps(e + b, _mm512_mul_ps(_mm512_loadu_ps(e + b), t));
            }
#endif
            for (; b < m; b++) e[b] *= p[lf[b]] + (w[0] * px[b] + w[1] * py[b] + w[2] * pz[b]);
        } else if (v->rows) {
            for (int b = 0; b < m; b++) e[b] *= p[idx[b]];
        } else { /* the next block's features fetched now: the CPU's own prefetcher follows
                    fewer streams than the 3 + 6 frequencies rows read side by side here */
            for (int l = 0; l < BLOCK; l += 16) __builtin_prefetch(p + v->start + b0 + BLOCK + l);
            for (int b = 0; b < m; b++) e[b] *= p[v->start + b0 + b];
        }
    }
}

/* The number of input channels of a view's points, or -1 when they exceed the buffers. */
static int channels_of(const struct view *v) {
    if (v->frequencies < 0 || v->scales < 1 || 3 + 6 * v->frequencies > MAX_EMBED || v->scales > MAX_SCALES)
        return -1;
    return 3 + 6 * v->frequencies + 9 * v->scales + (v->normals != NULL);
}

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

#ifdef __AMX_BF16__
#include <sys/syscall.h>
#include <unistd.h>

#define ROUND16(k) (((k) + 15) / 16 * 16)

/* Whether the operating system lets this process use the AMX tiles (Linux grants their state to a
   process that asks; kernels before 5.16 cannot): asked once a process, threads that race here
   ask twice and get the same answer. */
static int tiles_granted(void) {
    static int granted = -1;
    if (__atomic_load_n(&granted, __ATOMIC_RELAXED) < 0)
        __atomic_store_n(&granted, syscall(SYS_arch_prctl, 0x1023 /* ARCH_REQ_XCOMP_PERM */,
                                           18 /* XFEATURE_XTILEDATA */) == 0, __ATOMIC_RELAXED);
    return __atomic_load_n(&granted, __ATOMIC_RELAXED);
}

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

/* Eight tiles of 16 rows of 64 bytes. For the MLP, tiles 0-3: the sums of 16 outputs x 16 points of
   four groups (float32); 4: 16 outputs x 16 pairs of weights; 5 and 6: 16 pairs of inputs x 16
   points. For o3dvis_gather_conv, see conv_block. */
__attribute__((target("amx-tile"))) static void configure_tiles(void) {
    struct { uint8_t palette, start_row, reserved[14]; uint16_t colsb[16]; uint8_t rows[16]; } config = {1, 0, {0},
                                                                                                     {0}, {0}};
    for (int i = 0; i < 8; i++) config.colsb[i] = 64, config.rows[i] = 16;
    _tile_loadconfig(&config);
}

__attribute__((target("amx-tile"))) static void release_tiles(void) { _tile_release(); }

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
 * the weight as o3dvis/nn/native.py's pack_conv lays it out; outputs a multiple of 16; shift:
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
static int mlp_f32_fits(int32_t layers, const int32_t *sizes) {
    if (layers < 0) return 0;
    for (int l = 1; l <= layers + 1; l++)
        if (sizes[l] < 4 || sizes[l] % 4 || sizes[l] > MAX_WIDTH) return 0;
    return 1;
}

/* Runs a packed float32 MLP (see o3dvis_view_margin_f32) on a block of inputs (rows of BLOCK);
 * returns the row of its output, in h. */
static const float *mlp_f32(const float *in, int32_t layers, const int32_t *sizes, const float *weights,
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

#ifdef __AVX512F__
/* exp_neg of 16 lanes, each as exp_neg computes it */
static inline __m512 exp_neg16(__m512 y) {
    const __m512 magic = _mm512_set1_ps(12582912.0f);
    const __m512 k = _mm512_sub_ps(_mm512_add_ps(_mm512_mul_ps(y, _mm512_set1_ps(1.44269504088896341f)), magic), magic);
    const __m512 r = _mm512_add_ps(_mm512_sub_ps(y, _mm512_mul_ps(k, _mm512_set1_ps(0.693359375f))),
                                   _mm512_mul_ps(k, _mm512_set1_ps(2.12194440e-4f)));
    static const float c[] = {1.3888888889e-3f, 8.3333333333e-3f, 4.1666666667e-2f, 1.6666666667e-1f, 0.5f, 1.0f, 1.0f};
    __m512 p = _mm512_set1_ps(1.9841269841e-4f);
    for (int i = 0; i < 7; i++) p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(c[i]));
    const __m512i scale = _mm512_slli_epi32(_mm512_add_epi32(_mm512_cvttps_epi32(k), _mm512_set1_epi32(127)), 23);
    return _mm512_mul_ps(p, _mm512_castsi512_ps(scale));
}
#endif

/* tanh(x): below |x| = 1/16 its odd series to x^7 (error below 1e-12), else
   (1 - e) / (1 + e) with e = exp(-2 |x|), |x| clamped to 10 (where tanh rounds to 1) */
static inline float tanh_f(float x) {
    const float a = fabsf(x), a2 = a * a;
    float p = -5.3968253968e-2f;
    p = MADD(p, a2, 1.3333333333e-1f);
    p = MADD(p, a2, -3.3333333333e-1f);
    const float small = MADD(a * a2, p, a);
    const float e = exp_neg(-2.0f * (a < 10.0f ? a : 10.0f));
    return copysignf(a < 0.0625f ? small : (1.0f - e) / (1.0f + e), x);
}

#define FUSION_INPUTS 6 /* of a pair; the cloud's noise cues are in the first layer's biases */
#define FUSION_CLAMP 15.0f

/* The fused margins of n (point, camera) pairs (o3dvis/nn/fusion.py, ZBufferFusion): the MLP
 * (packed as for o3dvis_view_margin_f32, sizes[0] = 6) on each pair's margin clamped to +-15 and
 * its z-buffer answer (o3dvis_surfel_zbuffer's row of 4): the own-front flag, tanh of the
 * distance beyond over 2 and over 8, the log of the spacing in pixels (at least 1e-6) and |cos|.
 * Pair i is point rows[i], or start + i without rows; margin and out may be the same. Returns 0,
 * or -1 for an MLP that does not fit. */
int o3dvis_fuse_margin(int64_t n, const int64_t *rows, int64_t start, const float *zbuffer, const float *margin,
                       int32_t layers, const int32_t *sizes, const float *weights, const float *biases, float *out) {
    float in[FUSION_INPUTS * BLOCK] = {0}, h[2][MAX_WIDTH * BLOCK];
    if (sizes[0] != FUSION_INPUTS || !mlp_f32_fits(layers, sizes)) return -1;
    for (int64_t b0 = 0; b0 < n; b0 += BLOCK) {
        const int m = n - b0 < BLOCK ? (int)(n - b0) : BLOCK;
        for (int b = 0; b < m; b++) {
            const float *z = zbuffer + 4 * (rows ? rows[b0 + b] : start + b0 + b);
            const float t = margin[b0 + b], spacing = z[2] > 1e-6f ? z[2] : 1e-6f;
            in[b] = t < -FUSION_CLAMP ? -FUSION_CLAMP : (t > FUSION_CLAMP ? FUSION_CLAMP : t);
            in[BLOCK + b] = z[0];
            in[2 * BLOCK + b] = tanh_f(z[1] / 2.0f);
            in[3 * BLOCK + b] = tanh_f(z[1] / 8.0f);
            in[4 * BLOCK + b] = log_pos(spacing);
            in[5 * BLOCK + b] = z[3];
        }
        memcpy(out + b0, mlp_f32(in, layers, sizes, weights, biases, h), sizeof(float) * m);
    }
    return 0;
}

/* The unit eigenvector of the smallest eigenvalue of the symmetric matrix (xx xy xz; xy yy yz;
 * xz yz zz), as o3dvis/orientation.py's smallest_eigenvectors finds it: the eigenvalues from the
 * trigonometric solution of the characteristic cubic (entries scaled by the largest first); of
 * the largest and the smallest, the one farther from the middle eigenvalue gets its vector as the
 * longest cross product of two rows of A - lambda I, and the other two are those of A on the
 * plane normal to it, by an angle. Returns whether the middle eigenvalue exceeds 1e-12 times the
 * largest. */
static int smallest_eigenvector(const double *a, double *out) {
    double scale = 0.0;
    for (int i = 0; i < 6; i++) scale = fmax(scale, fabs(a[i]));
    const double r = scale > 0.0 ? scale : 1.0;
    const double xx = a[0] / r, xy = a[1] / r, xz = a[2] / r, yy = a[3] / r, yz = a[4] / r, zz = a[5] / r;
    const double third = (xx + yy + zz) / 3.0, dx = xx - third, dy = yy - third, dz = zz - third;
    const double spread = sqrt((dx * dx + dy * dy + dz * dz + 2.0 * (xy * xy + xz * xz + yz * yz)) / 6.0);
    const double det = dx * (dy * dz - yz * yz) - xy * (xy * dz - yz * xz) + xz * (xy * yz - dy * xz);
    const double sp = spread > 0.0 ? spread : 1.0;
    double half = det / (2.0 * sp * sp * sp);
    half = half < -1.0 ? -1.0 : (half > 1.0 ? 1.0 : half);
    const double angle = acos(half) / 3.0, largest = third + 2.0 * spread * cos(angle);
    const int low = half < 0.0; /* then the smallest eigenvalue is the one far from the middle */
    const double far = low ? third + 2.0 * spread * cos(angle + 2.0 * M_PI / 3.0) : largest;
    const double rows[3][3] = {{xx - far, xy, xz}, {xy, yy - far, yz}, {xz, yz, zz - far}};
    const int pairs[3][2] = {{0, 1}, {0, 2}, {1, 2}};
    double best[3] = {0.0, 0.0, 0.0}, longest2 = -1.0;
    for (int c = 0; c < 3; c++) { /* the first of equally long cross products, as argmax takes it */
        const double *p = rows[pairs[c][0]], *q = rows[pairs[c][1]];
        const double v[3] = {p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]};
        const double l2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
        if (l2 > longest2) longest2 = l2, best[0] = v[0], best[1] = v[1], best[2] = v[2];
    }
    const double longest = sqrt(longest2);
    double axis[3] = {0.0, 0.0, 1.0};
    if (longest > 0.0) axis[0] = best[0] / longest, axis[1] = best[1] / longest, axis[2] = best[2] / longest;
    /* an orthonormal basis (u, v) of the plane normal to the axis, and the matrix on it */
    const int tilted = fabs(axis[0]) < 0.9;
    const double t[3] = {tilted ? 1.0 : 0.0, tilted ? 0.0 : 1.0, 0.0};
    double u[3] = {axis[1] * t[2] - axis[2] * t[1], axis[2] * t[0] - axis[0] * t[2],
                   axis[0] * t[1] - axis[1] * t[0]};
    const double ul = sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
    u[0] /= ul, u[1] /= ul, u[2] /= ul;
    const double v[3] = {axis[1] * u[2] - axis[2] * u[1], axis[2] * u[0] - axis[0] * u[2],
                         axis[0] * u[1] - axis[1] * u[0]};
#define FORM(p, q) ((p)[0] * (xx * (q)[0] + xy * (q)[1] + xz * (q)[2]) \
                    + (p)[1] * (xy * (q)[0] + yy * (q)[1] + yz * (q)[2]) \
                    + (p)[2] * (xz * (q)[0] + yz * (q)[1] + zz * (q)[2]))
    const double uu = FORM(u, u), uv = FORM(u, v), vv = FORM(v, v);
#undef FORM
    const double turn = atan2(2.0 * uv, uu - vv) / 2.0, c = cos(turn), s = sin(turn);
    const double mean = (uu + vv) / 2.0, radius = hypot((uu - vv) / 2.0, uv);
    const double middle = low ? mean - radius : mean + radius;
    for (int i = 0; i < 3; i++) out[i] = low ? axis[i] : c * v[i] - s * u[i];
    return middle > 1e-12 * largest;
}

/* Unit normals of weighted least-squares planes through m rows of k neighbours (o3dvis/orientation.py,
 * fit_planes, whose numpy ops this follows): the scatter of each row's points about their weighted
 * mean, summed in double as offsets from the row's first neighbour, and its smallest eigenvector.
 * points: (n, 3); neighbours: (m, k) rows of indices in [0, n] (checked by the caller), n standing
 * for no point: as the numpy ops' padding column, a point at the origin whose homogeneous
 * coordinate is 0 (callers give it weight 0); weight: (m, k), or NULL for all 1. Writes normals
 * (m, 3) and planar (m,): at least three neighbours of positive weight, not all on one line. */
void o3dvis_fit_planes(int64_t n, int64_t m, int32_t k, const double *points, const int64_t *neighbours,
                       const double *weight, double *normals, uint8_t *planar) {
    static const double origin[3] = {0.0, 0.0, 0.0};
    for (int64_t r = 0; r < m; r++) {
        const int64_t *row = neighbours + r * k;
        const double *w = weight ? weight + r * k : NULL, *o = row[0] < n ? points + 3 * row[0] : origin;
        double sums[10] = {0}; /* xx xy xz yy yz zz, x y z, w */
        int positive = 0;
        for (int j = 0; j < k; j++) {
            const double *p = row[j] < n ? points + 3 * row[j] : origin, h = row[j] < n ? 1.0 : 0.0;
            const double x = p[0] - o[0], y = p[1] - o[1], z = p[2] - o[2], wj = w ? w[j] : 1.0, wh = wj * h;
            sums[0] += wj * x * x, sums[1] += wj * x * y, sums[2] += wj * x * z;
            sums[3] += wj * y * y, sums[4] += wj * y * z, sums[5] += wj * z * z;
            sums[6] += wh * x, sums[7] += wh * y, sums[8] += wh * z, sums[9] += wh * h;
            positive += wj > 0.0;
        }
        const double mass = sums[9] > 1e-300 ? sums[9] : 1e-300;
        const double scatter[6] = {sums[0] - sums[6] * sums[6] / mass, sums[1] - sums[6] * sums[7] / mass,
                                   sums[2] - sums[6] * sums[8] / mass, sums[3] - sums[7] * sums[7] / mass,
                                   sums[4] - sums[7] * sums[8] / mass, sums[5] - sums[8] * sums[8] / mass};
        const int spans = smallest_eigenvector(scatter, normals + 3 * r); /* more than a line */
        planar[r] = (uint8_t)(spans && positive >= 3);
    }
}

/* The weights of rows of neighbours in their plane fits by how alike the cameras see them
 * (o3dvis/orientation.py, visibility_affinity): exp(-d2 * rate), at least floor, with d2 the mean
 * over the v cameras of the squared difference between the answers of the row's point and of the
 * neighbour. table: (n, stride) each point's answers, padded with zeros to a stride of a multiple
 * of 16 (whole vectors); neighbours: (m, k) rows of indices in [0, n) (checked by the caller), row r
 * that of point first + r. Writes weight (m, k). */
void o3dvis_visibility_affinity(int64_t m, int32_t k, int32_t v, int32_t stride, int64_t first, const float *table,
                                const int64_t *neighbours, float rate, float floor, double *weight) {
    const float per_camera = rate / (float)v, lowest = -20.0f; /* exp_neg's range; exp(-20) < floor */
#ifdef __AVX512F__
    if (stride <= 32) { /* 16 neighbours at a time: their sums in vectors, their exponentials side by side */
        for (int64_t r = 0; r < m; r++) {
            const float *a = table + (first + r) * stride;
            const __m512 a0 = _mm512_loadu_ps(a), a1 = stride > 16 ? _mm512_loadu_ps(a + 16) : _mm512_setzero_ps();
            for (int j0 = 0; j0 < k; j0 += 16) {
                const int count = k - j0 < 16 ? k - j0 : 16;
                float sums[16] = {0}, w[16];
                for (int j = 0; j < count; j++) {
                    const float *b = table + neighbours[r * k + j0 + j] * stride;
                    const __m512 d0 = _mm512_sub_ps(a0, _mm512_loadu_ps(b));
                    __m512 squares = _mm512_mul_ps(d0, d0);
                    if (stride > 16) {
                        const __m512 d1 = _mm512_sub_ps(a1, _mm512_loadu_ps(b + 16));
                        squares = _mm512_add_ps(squares, _mm512_mul_ps(d1, d1));
                    }
                    sums[j] = _mm512_reduce_add_ps(squares);
                }
                const __m512 y = _mm512_max_ps(_mm512_mul_ps(_mm512_loadu_ps(sums), _mm512_set1_ps(-per_camera)),
                                               _mm512_set1_ps(lowest));
                _mm512_storeu_ps(w, _mm512_max_ps(exp_neg16(y), _mm512_set1_ps(floor)));
                for (int j = 0; j < count; j++) weight[r * k + j0 + j] = w[j];
            }
        }
        return;
    }
#endif
    for (int64_t r = 0; r < m; r++) {
        const float *a = table + (first + r) * stride;
        for (int j = 0; j < k; j++) {
            const float *b = table + neighbours[r * k + j] * stride;
            float lanes[16] = {0};
            for (int c0 = 0; c0 < stride; c0 += 16)
                for (int c = 0; c < 16; c++) {
                    const float d = a[c0 + c] - b[c0 + c];
                    lanes[c] += d * d;
                }
            float sum = 0.0f;
            for (int c = 0; c < 16; c++)
                sum += lanes[c];
            const float y = -sum * per_camera, w = exp_neg(y > lowest ? y : lowest);
            weight[r * k + j] = w > floor ? w : floor;
        }
    }
}

/* The slot of key in an open-addressing table of size (a power of two) slots, by multiplicative hashing
 * and linear probing: where it is, or the empty slot (-1) where it would go. */
static inline int64_t key_slot(const int64_t *table, int64_t size, const int64_t *keys, int64_t key) {
    const int bits = __builtin_ctzll((unsigned long long)size);
    int64_t slot = bits ? (int64_t)(((uint64_t)key * 0x9E3779B97F4A7C15ull) >> (64 - bits)) : 0;
    while (table[slot] >= 0 && keys[table[slot]] != key) slot = (slot + 1) & (size - 1);
    return slot;
}

/* Fills table (size slots, a power of two above m, all -1) with the indices of the m distinct keys. */
void o3dvis_key_table(int64_t m, const int64_t *keys, int64_t size, int64_t *table) {
    for (int64_t j = 0; j < m; j++) table[key_slot(table, size, keys, keys[j])] = j;
}

#define KNN_CHUNK 512 /* candidates gathered at once (the cell's points run over them while in cache) */

/* The 27 cells around a cell, its own first, then those sharing a face, an edge, a corner */
static const int8_t KNN_STEPS[27][3] = {
    {0, 0, 0}, {-1, 0, 0}, {1, 0, 0}, {0, -1, 0}, {0, 1, 0}, {0, 0, -1}, {0, 0, 1},
    {-1, -1, 0}, {-1, 1, 0}, {1, -1, 0}, {1, 1, 0}, {-1, 0, -1}, {-1, 0, 1}, {1, 0, -1}, {1, 0, 1},
    {0, -1, -1}, {0, -1, 1}, {0, 1, -1}, {0, 1, 1},
    {-1, -1, -1}, {-1, -1, 1}, {-1, 1, -1}, {-1, 1, 1}, {1, -1, -1}, {1, -1, 1}, {1, 1, -1}, {1, 1, 1}};

/* The orienting votes of the points first .. first + m - 1 (o3dvis/orientation.py, _votes): for
 * each, over the v cameras, the cosine between its normal and the direction to the camera
 * (n . (c - p) over |c - p|, the distance from |c|^2 - 2 p . c + |p|^2 as the numpy ops take it,
 * at least 1e-300), weighted by max(0, 2 q - 1) of the camera's probability q of seeing it
 * (visibility: (v, n_all) float32), summed into vote; agreement = |vote| over the sum of the
 * terms' absolute values (at least 1e-300). points, normals: (n_all, 3); cameras: (v, 3). */
void o3dvis_votes(int64_t first, int64_t m, int64_t n_all, int32_t v, const double *points, const double *normals,
                  const double *cameras, const float *visibility, double *vote, double *agreement) {
    for (int64_t i = 0; i < m; i++) vote[i] = 0.0, agreement[i] = 0.0; /* agreement: the absolute sums */
    for (int32_t j = 0; j < v; j++) {
        const double *c = cameras + 3 * j, cc = c[0] * c[0] + c[1] * c[1] + c[2] * c[2];
        const float *q = visibility + j * n_all + first;
        for (int64_t i = 0; i < m; i++) {
            const double *p = points + 3 * (first + i), *nrm = normals + 3 * (first + i);
            const double reach = (nrm[0] * c[0] + nrm[1] * c[1] + nrm[2] * c[2]) -
                                 (nrm[0] * p[0] + nrm[1] * p[1] + nrm[2] * p[2]);
            double d2 = cc - 2.0 * (p[0] * c[0] + p[1] * c[1] + p[2] * c[2]) +
                        (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
            d2 = d2 > 1e-300 ? d2 : 1e-300;
            const double w = 2.0 * (double)q[i] - 1.0, term = (w > 0.0 ? w : 0.0) * (reach / sqrt(d2));
            vote[i] += term, agreement[i] += fabs(term);
        }
    }
    for (int64_t i = 0; i < m; i++) agreement[i] = fabs(vote[i]) / (agreement[i] > 1e-300 ? agreement[i] : 1e-300);
}

/* Inserts the count candidates of squared distances d and indices index into the found (of k) nearest
 * so far, best (their squared distances) and row (their indices), nearest first; ties keep the earlier.
 * Blocks of 16 none of which is nearer than the k-th are passed at once. Returns how many are found. */
static int insert_nearest(const double *restrict d, const int64_t *restrict index, int count, int k,
                          double *restrict best, int64_t *restrict row, int found) {
    for (int t0 = 0; t0 < count; t0 += 16) {
        const int end = t0 + 16 < count ? t0 + 16 : count;
        if (found == k) {
            const double worst = best[k - 1];
            int any = 0;
            for (int t = t0; t < end; t++) any |= d[t] < worst;
            if (!any) continue;
        }
        for (int t = t0; t < end; t++) {
            const double dt = d[t];
            if (found == k && dt >= best[k - 1]) continue;
            int s = found < k ? found++ : k - 1;
            for (; s > 0 && best[s - 1] > dt; s--) best[s] = best[s - 1], row[s] = row[s - 1];
            best[s] = dt, row[s] = index[t];
        }
    }
    return found;
}

/* The k nearest of the n points (n, 3) to each of the m points rows, itself included, nearest first
 * (o3dvis/orientation.py, _nearest_by_search), among all points: k <= min(n, 64), ties keep the
 * point of the lower index. neighbours: (m, k). */
void o3dvis_brute_knn(int64_t n, const double *points, int64_t m, const int64_t *rows, int32_t k,
                      int64_t *neighbours) {
    for (int64_t r = 0; r < m; r++) {
        const double *p = points + 3 * rows[r];
        double best[64], d[KNN_CHUNK];
        int64_t row[64], index[KNN_CHUNK];
        int found = 0;
        for (int64_t j0 = 0; j0 < n; j0 += KNN_CHUNK) {
            const int count = n - j0 < KNN_CHUNK ? (int)(n - j0) : KNN_CHUNK;
            for (int t = 0; t < count; t++) {
                const double *q = points + 3 * (j0 + t);
                const double u = q[0] - p[0], v = q[1] - p[1], w = q[2] - p[2];
                d[t] = u * u + v * v + w * w, index[t] = j0 + t;
            }
            found = insert_nearest(d, index, count, k, best, row, found);
        }
        memcpy(neighbours + r * k, row, (size_t)k * sizeof(int64_t));
    }
}

/* The k nearest points to each point of the cells first..last - 1, itself included, nearest first
 * (o3dvis/orientation.py, nearest_neighbours), among the points of its cell and the 26 around it.
 * points: (n, 3) sorted by cell, the cells of a 2^level grid of side `side` from the corner lo;
 * cells: (m, 3) the integer coordinates of the occupied cells, keys their Morton keys, starts
 * (m + 1) where each cell's points begin, table their o3dvis_key_table of size slots. A point's
 * answer is exact when it has k candidates and its k-th is nearer than the border of the 27
 * cells, less slack (a side on the grid's border has nothing beyond it; points may lie up to slack
 * outside the cell they are put in): exact is set to 0 elsewhere, for the caller to search again.
 * The cells are visited nearest first (the point's own, then those sharing a face, an edge, a
 * corner with it: fewer candidates after them are nearer than the k-th so far); ties keep the
 * point visited first. k <= 64 (checked by the caller). list: NULL, or the cells to visit, of
 * which entries first..last - 1 are visited; wanted: NULL, or (n,) nonzero for the points whose
 * rows are written (the others' rows are left as they are). */
void o3dvis_grid_knn(const double *points, const int64_t *cells, const int64_t *keys, const int64_t *starts,
                     int64_t size, const int64_t *table, int32_t level, const double *lo, double side,
                     double slack, int32_t k, int64_t first, int64_t last, const int64_t *list,
                     const uint8_t *wanted, int64_t *neighbours, uint8_t *exact) {
    const int64_t top = ((int64_t)1 << level) - 1;
    for (int64_t at = first; at < last; at++) {
        const int64_t c = list ? list[at] : at;
        const int64_t *cell = cells + 3 * c;
        int64_t from[27], to[27];
        int runs = 0;
        for (int t = 0; t < 27; t++) { /* nearest cells first: few candidates after them are inserted */
            const int dx = KNN_STEPS[t][0], dy = KNN_STEPS[t][1], dz = KNN_STEPS[t][2];
            const int64_t x = cell[0] + dx, y = cell[1] + dy, z = cell[2] + dz;
            if (x < 0 || y < 0 || z < 0 || x > top || y > top || z > top) continue;
            const int64_t key = (int64_t)(spread_bits((uint64_t)x) << 2 | spread_bits((uint64_t)y) << 1 |
                                          spread_bits((uint64_t)z));
            const int64_t j = table[key_slot(table, size, keys, key)];
            if (j >= 0) from[runs] = starts[j], to[runs++] = starts[j + 1];
        }
        double low[3], high[3]; /* the block's faces, infinitely far on the grid's border */
        for (int a = 0; a < 3; a++) {
            low[a] = cell[a] > 0 ? lo[a] + (double)(cell[a] - 1) * side : -INFINITY;
            high[a] = cell[a] < top ? lo[a] + (double)(cell[a] + 2) * side : INFINITY;
        }
        int64_t total = 0;
        for (int r = 0; r < runs; r++) total += to[r] - from[r];
        for (int64_t chunk = 0; chunk < total; chunk += KNN_CHUNK) { /* the candidates, a chunk at a time */
            double x[KNN_CHUNK], y[KNN_CHUNK], z[KNN_CHUNK], d[KNN_CHUNK];
            int64_t index[KNN_CHUNK];
            int count = 0;
            int64_t skip = 0;
            for (int r = 0; r < runs && count < KNN_CHUNK; r++) {
                const int64_t length = to[r] - from[r];
                if (skip + length <= chunk) { skip += length; continue; }
                for (int64_t j = from[r] + (chunk > skip ? chunk - skip : 0); j < to[r] && count < KNN_CHUNK; j++)
                    x[count] = points[3 * j], y[count] = points[3 * j + 1], z[count] = points[3 * j + 2],
                    index[count++] = j;
                skip += length;
            }
            for (int64_t i = starts[c]; i < starts[c + 1]; i++) {
                if (wanted && !wanted[i]) continue;
                const double *p = points + 3 * i;
                double best[64];
                int64_t row[64];
                int found = chunk < k ? (int)chunk : k;
                for (int s = 0; s < found; s++) { /* the nearest of the chunks before */
                    const double *q = points + 3 * (row[s] = neighbours[i * k + s]);
                    const double u = q[0] - p[0], v = q[1] - p[1], w = q[2] - p[2];
                    best[s] = u * u + v * v + w * w;
                }
                for (int t = 0; t < count; t++) {
                    const double u = x[t] - p[0], v = y[t] - p[1], w = z[t] - p[2];
                    d[t] = u * u + v * v + w * w;
                }
                found = insert_nearest(d, index, count, k, best, row, found);
                for (int s = found; s < k; s++) row[s] = i;
                memcpy(neighbours + i * k, row, (size_t)k * sizeof(int64_t));
                if (chunk + count < total) continue;
                double margin = INFINITY;
                for (int a = 0; a < 3; a++) {
                    const double below = p[a] - low[a], above = high[a] - p[a];
                    margin = fmin(margin, fmin(below, above));
                }
                margin = fmax(margin - slack, 0.0); /* points up to slack off their cell may lie beyond */
                exact[i] = (uint8_t)(found == k && best[k - 1] < margin * margin * (1.0 - 1e-9));
            }
        }
    }
}

/* The number of nodes of each level 0 .. depth of the octree of one cloud (o3dvis.nn.octree.Octree)
 * from its points' cell keys at depth, sorted: 8^level for the levels up to full_depth, the distinct
 * leading bits of the keys below. Returns 0, or -1 (nothing written) for keys out of [0, 8^depth) or
 * out of order. */
int o3dvis_octree_counts(int64_t n, const int64_t *keys, int32_t depth, int32_t full_depth, int64_t *counts) {
    int64_t first[22] = {0}; /* first[l]: the points whose keys first differ from the previous one's at level l */
    int bad = n > 0 && (keys[0] < 0 || keys[n - 1] >> 3 * depth != 0);
    for (int64_t i = 1; i < n; i++) {
        const uint64_t diff = (uint64_t)(keys[i] ^ keys[i - 1]);
        const int at = diff ? depth - (63 - __builtin_clzll(diff)) / 3 : 0;
        bad |= keys[i] < keys[i - 1] || at < 0;
        first[at < 0 ? 0 : at] += diff != 0;
    }
    if (bad) return -1;
    int64_t nodes = n > 0;
    for (int l = 0; l <= depth; l++) {
        nodes += first[l];
        counts[l] = l <= full_depth ? (int64_t)1 << 3 * l : nodes;
    }
    return 0;
}

/* Fills the levels of the octree of o3dvis_octree_counts (counts from it) and the leaf of each point.
 * out holds, level after level (0 .. depth), its counts[l] keys, parents (-1 at the root), octant rows
 * (8 parent + octant) and, but at depth, its (counts[l], 8) children (-1 where empty) and child rows
 * (counts[l + 1] where empty); point_leaf: (n,). */
void o3dvis_octree_fill(int64_t n, const int64_t *keys, int32_t depth, int32_t full_depth, const int64_t *counts,
                        int64_t *point_leaf, int64_t *out) {
    int64_t *key[22], *parent[22], *octant[22], *children[22], *rows[22];
    for (int l = 0; l <= depth; l++) {
        key[l] = out, parent[l] = out + counts[l], octant[l] = out + 2 * counts[l];
        out += 3 * counts[l];
        if (l < depth) children[l] = out, rows[l] = out + 8 * counts[l], out += 16 * counts[l];
    }
    int64_t leaves = 0;
    for (int64_t i = 0; i < n; i++) {
        leaves += i > 0 && keys[i] != keys[i - 1];
        key[depth][leaves] = keys[i];
        point_leaf[i] = leaves;
    }
    for (int l = depth - 1; l > full_depth; l--) { /* a sparse level: the distinct parents of the one below */
        int64_t j = -1;
        for (int64_t c = 0; c < counts[l + 1]; c++) {
            if (c == 0 || key[l + 1][c] >> 3 != key[l + 1][c - 1] >> 3) key[l][++j] = key[l + 1][c] >> 3;
            parent[l + 1][c] = j;
        }
    }
    for (int l = 0; l <= full_depth; l++)
        for (int64_t c = 0; c < counts[l]; c++) key[l][c] = c;
    for (int64_t c = 0; c < counts[full_depth + 1]; c++) parent[full_depth + 1][c] = key[full_depth + 1][c] >> 3;
    for (int l = 1; l <= full_depth; l++)
        for (int64_t c = 0; c < counts[l]; c++) parent[l][c] = c >> 3;
    parent[0][0] = -1;
    for (int l = 0; l <= depth; l++)
        for (int64_t c = 0; c < counts[l]; c++) octant[l][c] = 8 * parent[l][c] + (key[l][c] & 7);
    for (int l = 0; l < depth; l++) {
        for (int64_t c = 0; c < 8 * counts[l]; c++) children[l][c] = -1, rows[l][c] = counts[l + 1];
        for (int64_t c = 0; c < counts[l + 1]; c++) children[l][octant[l + 1][c]] = rows[l][octant[l + 1][c]] = c;
    }
}

/* The 3x3x3 neighbours of the n nodes of an octree level below its full ones, from those of their
 * parents (o3dvis.nn.octree.Octree._neighbours_from_parents): node i, of octant keys[i] & 7 and parent
 * parent[i], has at offset t the child offset_octant[o][t] of the parent level's node
 * above[27 parent[i] + parent_offset[o][t]] (m where missing), children (m, 8) the parent level's
 * children (-1 where empty). Writes (n, 27) indices into out, n where missing, and returns 0; or -1
 * (nothing written) for a parent out of [0, m) or offsets out of range. */
int o3dvis_child_neighbours(int64_t n, const int64_t *keys, const int64_t *parent, const int64_t *above,
                            int64_t m, const int64_t *children, const int64_t *parent_offset,
                            const int64_t *offset_octant, int64_t *out) {
    int outside = 0;
    for (int64_t i = 0; i < n; i++) outside |= (parent[i] < 0) | (parent[i] >= m);
    for (int t = 0; t < 8 * 27; t++)
        outside |= (parent_offset[t] < 0) | (parent_offset[t] >= 27) | (offset_octant[t] < 0) | (offset_octant[t] >= 8);
    if (outside) return -1;
    for (int64_t i = 0; i < n; i++) {
        const int o = (int)(keys[i] & 7);
        const int64_t *holders = above + 27 * parent[i];
        for (int t = 0; t < 27; t++) {
            const int64_t h = holders[parent_offset[27 * o + t]];
            const int64_t c = h >= 0 && h < m ? children[8 * h + offset_octant[27 * o + t]] : -1;
            out[27 * i + t] = c < 0 ? n : c;
        }
    }
    return 0;
}
