/* A view's projection (o3dvis/nn/cues.py, ViewProjection): view directions, depths and the
 * multi-scale min-depth buffers in a few passes over the points instead of some sixty torch ops;
 * the points' planes (point_surfels) and their footprints splatted into the buffers. */

#include "kernels.h"

/* Two unit vectors orthogonal to the unit vector forward, as cues.py's _frame */
static void frame(const double *forward, double *right, double *up) {
    double helper[3] = {0.0, 0.0, 1.0};
    if (fabs(forward[2]) > 0.9) { helper[0] = 1.0; helper[2] = 0.0; }
    cross(forward, helper, right);
    double norm = sqrt(right[0] * right[0] + right[1] * right[1] + right[2] * right[2]);
    for (int a = 0; a < 3; a++) right[a] /= norm;
    cross(forward, right, up);
}

/* The view's forward direction: from a camera (3,), the mean of the unit directions from it to the
 * points, summed in double, having written them into dirs (n, 3) and each point's distance into
 * depth (n,); else the unit viewing direction (3,). */
static void view_forward(int64_t n, const float *points, const float *camera, const float *direction, float *dirs,
                         float *depth, double *forward) {
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
}

/* Each point's image position (n, 2) in uv, in the frame around forward: azimuthal-equidistant
 * from a camera (its directions dirs), else parallel (then its depth along forward too). */
static void image_positions(int64_t n, const float *points, const float *camera, const float *dirs,
                            const double *forward, float *depth, float *uv) {
    double right[3], up[3];
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
}

/* Half the image's width, the largest |u| or |v| of the n points' positions uv widened a little;
 * moves every position by it, to the image's corner. */
static float to_image_corner(int64_t n, float *uv) {
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
    for (i = 0; i < 2 * n; i++) uv[i] += half;
    return half;
}

/* Lays out the bordered buffers of the scales of sides in zbufs, each scale's from start[s]: NaN on
 * the border, +inf inside; and each scale's 1 / pixel size in rpix, for an image 2 half wide.
 * Returns how many values the buffers hold. */
static int64_t clear_buffers(int32_t scales, const int64_t *sides, float half, float *zbufs, float *rpix,
                             int64_t *start) {
    int64_t total = 0;
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
    return total;
}

/* Each point's pixel at every scale from its image position uv: the index in zbufs of the 3x3
 * around it into corners (n, scales), and its depth into the pixel's minimum. */
static void nearest_depths(int64_t n, const float *uv, const float *depth, int32_t scales, const int64_t *sides,
                           const int64_t *start, const float *rpix, float *zbufs, int32_t *corners) {
    int64_t i = 0;
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
    double forward[3];
    if (scales < 1 || scales > MAX_SCALES) return -1;
    view_forward(n, points, camera, direction, dirs, depth, forward);
    image_positions(n, points, camera, dirs, forward, depth, uv);
    const float half = to_image_corner(n, uv);
    int64_t start[MAX_SCALES];
    const int64_t total = clear_buffers(scales, sides, half, zbufs, rpix, start);
    nearest_depths(n, uv, depth, scales, sides, start, rpix, zbufs, corners);
    for (int64_t q = 0; q < total; q++) zbufs[q] = zbufs[q] == INFINITY ? NAN : zbufs[q];
    return 0;
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
        const double xx = t[4] / w - mx * mx, yy = t[5] / w - my * my, zz = t[6] / w - mz * mz;
        const double xy = t[7] / w - mx * my, xz = t[8] / w - mx * mz, yz = t[9] / w - my * mz;
        const double cov[6] = {xx, xy, xz, yy, yz, zz};
        double values[3], axis[3];
        sym3_eigen(cov, values, axis);
        const double least = values[0];
        /* the product of the two larger eigenvalues, from the sum of the principal 2 x 2 minors */
        const double minors = xx * yy + xx * zz + yy * zz - xy * xy - xz * xz - yz * yz;
        const double product = minors - least * (xx + yy + zz - least);
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
