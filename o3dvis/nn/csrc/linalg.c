/* The symmetric 3x3 eigen-solver of every kernel that needs one: the noise cues' patch terms
 * (noise.c), the points' planes (views.c, o3dvis_surfels) and the plane fits of the normals'
 * orientation (orientation.c). */

#include "kernels.h"

/* The unit vector along the longest of the cross products of two rows of the symmetric matrix
 * s = (xx, xy, xz, yy, yz, zz) less lambda I (the first of equals) into axis: the eigenvector of
 * lambda where lambda is a single eigenvalue of s; (0, 0, 1) where every product is zero. */
static void longest_cross(const double *s, double lambda, double *axis) {
    const double rows[9] = {s[0] - lambda, s[1], s[2], s[1], s[3] - lambda, s[4], s[2], s[4], s[5] - lambda};
    static const int pairs[3][2] = {{0, 1}, {0, 2}, {1, 2}};
    double best = 0.0;
    axis[0] = 0.0, axis[1] = 0.0, axis[2] = 1.0;
    for (int k = 0; k < 3; k++) {
        double c[3];
        cross(rows + 3 * pairs[k][0], rows + 3 * pairs[k][1], c);
        const double len = sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]);
        if (len > best) best = len, axis[0] = c[0] / len, axis[1] = c[1] / len, axis[2] = c[2] / len;
    }
}

/* The two eigenvalues of s = (xx, xy, xz, yy, yz, zz) on the plane normal to its unit eigenvector
 * far, by an angle (stable however close the two are): the smaller and the larger into values[0]
 * and values[1], the smaller's unit eigenvector into axis. */
static void plane_eigen(const double *s, const double *far, double *values, double *axis) {
    const double xx = s[0], xy = s[1], xz = s[2], yy = s[3], yz = s[4], zz = s[5];
    const int tilted = fabs(far[0]) < 0.9; /* an orthonormal basis (u, v) of the plane */
    const double t[3] = {tilted ? 1.0 : 0.0, tilted ? 0.0 : 1.0, 0.0};
    double u[3], v[3];
    cross(far, t, u);
    const double ul = sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
    u[0] /= ul, u[1] /= ul, u[2] /= ul;
    cross(far, u, v);
#define FORM(p, q) ((p)[0] * (xx * (q)[0] + xy * (q)[1] + xz * (q)[2]) \
                    + (p)[1] * (xy * (q)[0] + yy * (q)[1] + yz * (q)[2]) \
                    + (p)[2] * (xz * (q)[0] + yz * (q)[1] + zz * (q)[2]))
    const double uu = FORM(u, u), uv = FORM(u, v), vv = FORM(v, v);
#undef FORM
    const double turn = atan2(2.0 * uv, uu - vv) / 2.0, c = cos(turn), sn = sin(turn);
    const double mean = (uu + vv) / 2.0, radius = hypot((uu - vv) / 2.0, uv);
    values[0] = mean - radius, values[1] = mean + radius;
    for (int i = 0; i < 3; i++) axis[i] = c * v[i] - sn * u[i]; /* the minor axis: normal to cos u + sin v */
}

/* The eigenvalues of the symmetric matrix a = (xx, xy, xz, yy, yz, zz) into values, ascending, and
 * where axis is not NULL the unit eigenvector of the smallest into axis ((0, 0, 1) where the
 * three are equal).
 *
 * The entries are scaled by a power of two (exactly) so that neither their squares nor their
 * cubes leave the range of doubles. The largest and the smallest eigenvalues come from the
 * trigonometric solution of the characteristic cubic; of the two, the one farther from the
 * middle is accurate (the cubic's angle loses half the digits of the two that lie close), and
 * the others follow from it, each to a few ulps of the largest eigenvalue, as an iterative solver
 * finds them. Where the far one is the smallest, its eigenvector is the longest cross product of
 * two rows of a - smallest I, the middle eigenvalue comes from the trace, and where the smallest
 * is far below the two others it is their determinant's share instead (det / (largest x
 * middle)). Where the far one is the largest, the two others and the smallest's eigenvector are
 * those of a on the plane normal to the largest's eigenvector (plane_eigen), however close, the
 * eigenvector turned to the side of that longest cross product (one sign for every matrix, that
 * of the torch ops of o3dvis/nn/cues.py, _least_axis). */
void sym3_eigen(const double *a, double *values, double *axis) {
    double largest = 0.0, s[6], unused[3], far[3];
    for (int k = 0; k < 6; k++) largest = fmax(largest, fabs(a[k]));
    int exponent = 0;
    if (largest > 0.0 && largest < INFINITY) frexp(largest, &exponent);
    for (int k = 0; k < 6; k++) s[k] = ldexp(a[k], -exponent);
    axis = axis != NULL ? axis : unused;
    const double xx = s[0], xy = s[1], xz = s[2], yy = s[3], yz = s[4], zz = s[5];
    const double q = (xx + yy + zz) / 3.0, off = xy * xy + xz * xz + yz * yz;
    const double p2 = (xx - q) * (xx - q) + (yy - q) * (yy - q) + (zz - q) * (zz - q) + 2.0 * off;
    double low = q, mid = q, high = q;
    axis[0] = 0.0, axis[1] = 0.0, axis[2] = 1.0;
    if (p2 > 0.0) {
        const double p = sqrt(p2 / 6.0);
        const double x = (xx - q) / p, y = (yy - q) / p, z = (zz - q) / p, u = xy / p, v = xz / p, w = yz / p;
        double r = (x * (y * z - w * w) - u * (u * z - w * v) + v * (u * w - y * v)) / 2.0;
        r = r < -1.0 ? -1.0 : (r > 1.0 ? 1.0 : r);
        const double phi = acos(r) / 3.0;
        high = q + 2.0 * p * cos(phi);
        low = q + 2.0 * p * cos(phi + 2.0943951023931954923);
        mid = 3.0 * q - high - low;
        if (r >= 0.0) { /* the largest is the far one: the two others on the plane normal to it */
            double pair[2], sign[3];
            longest_cross(s, high, far);
            plane_eigen(s, far, pair, axis);
            low = pair[0], mid = pair[1];
            longest_cross(s, low, sign); /* the sign the far smallest's eigenvector takes */
            if (axis[0] * sign[0] + axis[1] * sign[1] + axis[2] * sign[2] < 0.0)
                axis[0] = -axis[0], axis[1] = -axis[1], axis[2] = -axis[2];
        } else {
            if (low < 1e-3 * mid && mid > 1e-6 * high) {
                low = (xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz)) / (high * mid);
                mid = 3.0 * q - high - low;
            }
            longest_cross(s, low, axis);
        }
    }
    values[0] = ldexp(low, exponent), values[1] = ldexp(mid, exponent), values[2] = ldexp(high, exponent);
}
