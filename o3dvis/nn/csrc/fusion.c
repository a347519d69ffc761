/* The fusion of a view's margins with the surfel z-buffer's answers (o3dvis/nn/fusion.py,
 * ZBufferFusion) in one pass, on the float32 MLP of mlp.c. */

#include "kernels.h"

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
