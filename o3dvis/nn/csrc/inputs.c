/* The first layer's inputs of the predictor's MLP, a block of points at a time: the view embedding
 * times the projected feature, then the asinh of the depth residuals to the 3x3 pixels around
 * each point at every cue scale, which o3dvis/nn/cues.py (ViewProjection.cues) and
 * o3dvis/nn/predictor.py (ViewEmbedding, the product with the features) compute in a dozen eager
 * torch ops, each a pass over memory; mlp.c runs the MLP on them while they are in the L1 cache. */

#include "kernels.h"

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

/* The cues of m <= BLOCK points (rows idx) into cue, 9 rows of BLOCK floats a scale: the 3x3
 * depths around each point's pixels (channels first: the arithmetic below runs along contiguous
 * rows), then its residuals to them in pixel footprints, clamped, with empty pixels marked, then
 * their asinh. */
static void cue_inputs(const struct view *v, const int64_t *idx, int m, float *cue) {
    const int nc = 9 * v->scales, scales = v->scales;
    float dep[BLOCK], kd[BLOCK], k[BLOCK];
    const float empty = v->empty; /* a local: the stores below could otherwise change it */
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
}

/* The view embedding [d, sin(pi d), cos(pi d), sin(2 pi d), ...] of the directions of m <= BLOCK
 * points (rows idx) into the first 3 + 6 frequencies rows of BLOCK floats of in, channels first. */
static void embed_directions(const struct view *v, const int64_t *idx, int m, float *in) {
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
}

/* Multiplies the embedding (the first 3 + 6 frequencies rows of in) of m <= BLOCK points, rows idx
 * from the b0-th, by their projected features: read per point, or per leaf with each point's term
 * added (struct view). */
static void times_features(const struct view *v, const int64_t *idx, int64_t b0, int m, float *in) {
    const int ne = 3 + 6 * v->frequencies;
    float px[BLOCK], py[BLOCK], pz[BLOCK];
    int32_t lf[BLOCK]; /* leaves number fewer than points (MAX_POINTS): 32 bits, for vector gathers */
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

/* Writes the first layer's inputs of the block of m <= BLOCK points from the b0-th, as rows of
 * BLOCK floats: the embedding times the feature (3 + 6 frequencies rows), the cues (9 scales
 * rows), then with normals the cosine of the normal and the reversed view direction. Rows past m
 * hold finite values of no meaning. */
void block_inputs(const struct view *v, int64_t b0, int m, float *in) {
    const int ne = 3 + 6 * v->frequencies, nc = 9 * v->scales;
    int64_t idx[BLOCK];
    for (int b = 0; b < m; b++) idx[b] = v->rows ? v->rows[b0 + b] : v->start + b0 + b;
    cue_inputs(v, idx, m, in + ne * BLOCK);
    embed_directions(v, idx, m, in);
    if (v->normals) { /* -(n . d), before the directions are multiplied by the features */
        float *c = in + (ne + nc) * BLOCK;
        for (int b = 0; b < m; b++) {
            const float *nrm = v->normals + 3 * idx[b];
            c[b] = -(nrm[0] * in[b] + nrm[1] * in[BLOCK + b] + nrm[2] * in[2 * BLOCK + b]);
        }
    }
    times_features(v, idx, b0, m, in);
}

/* The number of input channels of a view's points, or -1 when they exceed the buffers. */
int channels_of(const struct view *v) {
    if (v->frequencies < 0 || v->scales < 1 || 3 + 6 * v->frequencies > MAX_EMBED || v->scales > MAX_SCALES)
        return -1;
    return 3 + 6 * v->frequencies + 9 * v->scales + (v->normals != NULL);
}
