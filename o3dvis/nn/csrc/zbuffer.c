/* The surfel z-buffer of a camera (o3dvis/nn/zbuffer.py): each point's disc rendered into a
 * latitude-longitude depth buffer, then each point compared with the disc in front of it. */

#include "kernels.h"

/* A camera's latitude-longitude depth buffer, rows x cols pixels of pixel radians, and the nearest
 * disc of each pixel (-1: none); the cosines and sines of its rows' elevations and of its columns'
 * azimuths; the largest half height and half width of a disc's pixels. */
struct zbuffer {
    int32_t rows, max_half, max_wide;
    int64_t cols;
    float pixel;
    const float *rcos, *rsin, *ccos, *csin;
    float *depth;
    int32_t *owner;
};

/* The rows window[0]..window[1] and the columns window[2]..window[3] (not wrapped around) of the
 * pixels whose centres a point's disc may cover, its own pixel (r, c) among them: the disc of
 * radius and unit normal nrm around the point at (x, y, z) from the camera, h from its axis, d
 * from it, at (row, col) in the image. It reaches r sqrt(1 - (n.e)^2) / (d - r) radians from the
 * point along an image direction e (the small-angle extent of a tilted disc; the margin covers
 * what that neglects), along the meridian in rows, along the parallel in columns. */
static void disc_window(const struct zbuffer *zb, float x, float y, float z, float h, float d, float radius,
                        const float *nrm, float row, float col, int64_t r, int64_t c, int64_t *window) {
    const float pixel = zb->pixel;
    const int32_t rows = zb->rows, max_half = zb->max_half, max_wide = zb->max_wide;
    const int64_t cols = zb->cols;
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
    window[0] = r0, window[1] = r1, window[2] = k0, window[3] = k1;
}

/* Renders point i's disc (see disc_window) into the buffer over its window: each pixel whose
 * centre ray meets the disc, and always its own pixel (r, c), at the point's distance d where its
 * plane misses the ray, takes the disc's depth where nearer (the first of equals). */
static void render_disc(struct zbuffer *zb, int64_t i, float x, float y, float z, float d, float radius,
                        const float *nrm, int64_t r, int64_t c, const int64_t *window) {
    const int64_t cols = zb->cols, r0 = window[0], r1 = window[1], k0 = window[2], k1 = window[3];
    const float plane = x * nrm[0] + y * nrm[1] + z * nrm[2], r2 = radius * radius;
    const int64_t c0 = (k0 % cols + cols) % cols, width = k1 - k0 + 1, own_k = c - k0;
    for (int64_t rr = r0; rr <= r1; rr++) {
        const float rc = zb->rcos[rr], rs = zb->rsin[rr], rz = rs * nrm[2];
        float *zrow = zb->depth + rr * cols;
        int32_t *orow = zb->owner + rr * cols;
        for (int64_t k = 0; k < width; k++) {
            int64_t cc = c0 + k;
            cc = cc >= cols ? cc - cols : cc;  /* the image wraps around in azimuth */
            const float ray[3] = {rc * zb->ccos[cc], rc * zb->csin[cc], rs};
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

/* Renders every point's disc: each point's offset from the camera and distance into geo (n, 4), the
 * index of its own pixel into own (n,). */
static void render_discs(struct zbuffer *zb, int64_t n, const float *points, const float *surfels,
                         const float *camera, float *geo, int64_t *own) {
    const float pi = (float)M_PI;
    const int32_t rows = zb->rows;
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
        own[i] = r * zb->cols + c % zb->cols;
        const float radius = surfels[5 * i + 4], *nrm = surfels + 5 * i + 1;
        int64_t window[4];
        disc_window(zb, x, y, z, h, d, radius, nrm, row, col, r, c, window);
        render_disc(zb, i, x, y, z, d, radius, nrm, r, c, window);
    }
}

/* Each point compared with the plane of the disc in front at its own pixel (owner), along its own
 * ray: out as o3dvis_surfel_zbuffer writes it. */
static void compare_with_front(int64_t n, const float *surfels, const float *geo, const int64_t *own,
                               const int32_t *owner, float pixel, float clip, float *out) {
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
    struct zbuffer zb = {rows, max_half, max_wide, cols, pixel, rcos, rsin, ccos, csin, zbuf, owner};
    render_discs(&zb, n, points, surfels, camera, geo, own);
    compare_with_front(n, surfels, geo, own, owner, pixel, clip, out);
    free(zbuf), free(owner), free(table), free(geo), free(own);
    return 0;
}
