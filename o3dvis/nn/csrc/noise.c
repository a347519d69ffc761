/* The noise cues' patch terms (o3dvis/nn/noise.py): the thickness of a cloud's cells and the
 * flatness of its runs of points, each from the eigenvalues of a covariance (linalg.c). */

#include "kernels.h"

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
                const double cov[6] = {s0 / m - mx * mx, s1 / m - mx * my, s2 / m - mx * mz,
                                       s3 / m - my * my, s4 / m - my * mz, s5 / m - mz * mz};
                double values[3];
                sym3_eigen(cov, values, NULL);
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
        sym3_eigen(s, values, NULL);
        const double low = values[0] > 0.0 ? values[0] : 0.0, mid = values[1] > 0.0 ? values[1] : 0.0;
        flatness[r] = sqrt(low / (mid > 2.2250738585072014e-308 ? mid : 2.2250738585072014e-308));
    }
}
