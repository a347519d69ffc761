/* The normals' orientation by the cameras (o3dvis/orientation.py): weighted plane fits, the
 * neighbours' weights by how alike the cameras see them, and the cameras' votes. */

#include "kernels.h"

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

/* Unit normals of weighted least-squares planes through m rows of k neighbours (o3dvis/orientation.py,
 * fit_planes, whose numpy ops this follows): the scatter of each row's points about their weighted
 * mean, summed in double as offsets from the row's first neighbour, and its smallest eigenvector
 * (linalg.c: the numpy ops solve the same cubic, but take the eigenvector by another route, the
 * same to rounding where the smallest eigenvalue is single).
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
        double values[3];
        sym3_eigen(scatter, values, normals + 3 * r);
        planar[r] = (uint8_t)(values[1] > 1e-12 * values[2] && positive >= 3); /* more than a line */
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
