/* The Delaunay triangulation of points in the plane, by a sweep: the points are added in order of
 * their distance from the circumcentre of a seed triangle, each joined to the edges of the convex
 * hull it sees, and the new triangles' edges flipped until they are Delaunay (Lawson).
 *
 * The coordinates are first snapped to a grid of at most 2^26 steps over their bounding box, so that the two
 * predicates (orientation, in-circle) are exact in integers: the flips then always end, and no
 * triangle comes out folded. Points that fall on one grid node are triangulated once. A point that
 * the sweep finds inside the hull (only where rounding misorders two distances) is left out, as
 * Qhull leaves out "coplanar" ones.
 *
 * Half-edges: edge k of triangle t = k / 3 goes from tri[k] to tri[next(k)], with the triangle on its
 * left (every triangle counter-clockwise); twin[k] is the same edge in the triangle across, or -1 on
 * the hull. The hull is a ring of points, counter-clockwise, with hull_edge[p] the half-edge that
 * leaves p along it; points off the hull have hull_next[p] == p.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#define GRID 67108864.0 /* 2^26: differences of two coordinates and their squares fit int64 */

typedef struct {
    const int64_t *x, *y;
    int32_t *tri, *twin, *hull_next, *hull_prev, *hull_edge;
    int32_t *stack;
    int64_t stack_size, triangles;
} mesh;

/* > 0 when a, b, c turn counter-clockwise, 0 on one line (exact: |coordinates| < 2^26) */
static inline int64_t orient(const mesh *m, int32_t a, int32_t b, int32_t c) {
    return (m->x[b] - m->x[a]) * (m->y[c] - m->y[a]) - (m->y[b] - m->y[a]) * (m->x[c] - m->x[a]);
}

/* whether d lies strictly inside the circle through a, b, c (counter-clockwise), exactly */
static inline int in_circle(const mesh *m, int32_t a, int32_t b, int32_t c, int32_t d) {
    int64_t ax = m->x[a] - m->x[d], ay = m->y[a] - m->y[d];
    int64_t bx = m->x[b] - m->x[d], by = m->y[b] - m->y[d];
    int64_t cx = m->x[c] - m->x[d], cy = m->y[c] - m->y[d];
    __int128 det = (__int128)(ax * ax + ay * ay) * (bx * cy - cx * by)
                 - (__int128)(bx * bx + by * by) * (ax * cy - cx * ay)
                 + (__int128)(cx * cx + cy * cy) * (ax * by - bx * ay);
    return det > 0;
}

static inline int32_t next_edge(int32_t k) { return k % 3 == 2 ? k - 2 : k + 1; }
static inline int32_t prev_edge(int32_t k) { return k % 3 == 0 ? k + 2 : k - 1; }

static inline void link(mesh *m, int32_t a, int32_t b) {
    m->twin[a] = b;
    if (b >= 0) m->twin[b] = a;
}

/* a new triangle a, b, c (counter-clockwise); returns its first half-edge (a -> b) */
static int32_t add_triangle(mesh *m, int32_t a, int32_t b, int32_t c, int32_t twin_ab, int32_t twin_bc,
                            int32_t twin_ca) {
    int32_t k = (int32_t)(3 * m->triangles++);
    m->tri[k] = a, m->tri[k + 1] = b, m->tri[k + 2] = c;
    link(m, k, twin_ab), link(m, k + 1, twin_bc), link(m, k + 2, twin_ca);
    return k;
}

/* Flips edge e (opposite the newly added point) and the edges it exposes until all are Delaunay.
 * Returns 0, or -1 when the stack could not grow. */
static int legalize(mesh *m, int32_t e) {
    int64_t top = 0;
    for (;;) {
        int32_t a = e, b = m->twin[a];
        int flipped = 0;
        if (b >= 0) {
            /* triangle 1: a = pr -> pl, then pl -> p0, p0 -> pr; triangle 2: b = pl -> pr, br, bl */
            int32_t al = next_edge(a), ar = prev_edge(a), br = next_edge(b), bl = prev_edge(b);
            int32_t p0 = m->tri[ar], pr = m->tri[a], pl = m->tri[al], p1 = m->tri[bl];
            if (in_circle(m, pr, pl, p0, p1)) {
                /* the edge pr - pl becomes p0 - p1: triangles p1, pl, p0 and p0, pr, p1 */
                int32_t twin_bl = m->twin[bl], twin_ar = m->twin[ar];
                m->tri[a] = p1, m->tri[b] = p0;
                /* a hull edge that moved to another slot: p1 -> pl is now a, p0 -> pr now b */
                if (twin_bl < 0) m->hull_edge[p1] = a;
                if (twin_ar < 0) m->hull_edge[p0] = b;
                link(m, a, twin_bl), link(m, b, twin_ar), link(m, ar, bl);
                if (top == m->stack_size) {
                    int64_t size = 2 * m->stack_size + 64;
                    int32_t *grown = realloc(m->stack, (size_t)size * sizeof(int32_t));
                    if (!grown) return -1;
                    m->stack = grown, m->stack_size = size;
                }
                m->stack[top++] = br;
                flipped = 1;
            }
        }
        if (!flipped) {
            if (top == 0) return 0;
            e = m->stack[--top];
        }
    }
}

typedef struct {
    double distance;
    int32_t index;
} keyed;

static int by_distance(const void *p, const void *q) {
    double a = ((const keyed *)p)->distance, b = ((const keyed *)q)->distance;
    return (a > b) - (a < b);
}

/* a monotone stand-in for the angle of (dx, dy), in [0, 1) */
static inline double pseudo_angle(double dx, double dy) {
    if (dx == 0 && dy == 0) return 0;
    double p = dx / (fabs(dx) + fabs(dy));
    return (dy > 0 ? 3 - p : 1 + p) / 4;
}

static inline int64_t hash_key(double dx, double dy, int64_t size) {
    int64_t k = (int64_t)floor(pseudo_angle(dx, dy) * (double)size);
    return k < 0 ? 0 : k >= size ? size - 1 : k;
}

static double circumradius2(const mesh *m, int32_t a, int32_t b, int32_t c) {
    double dx = (double)(m->x[b] - m->x[a]), dy = (double)(m->y[b] - m->y[a]);
    double ex = (double)(m->x[c] - m->x[a]), ey = (double)(m->y[c] - m->y[a]);
    double bl = dx * dx + dy * dy, cl = ex * ex + ey * ey, d = 0.5 / (dx * ey - dy * ex);
    double x = (ey * bl - dy * cl) * d, y = (dx * cl - ex * bl) * d;
    return x * x + y * y;
}

/* The triangles of the Delaunay triangulation of n points xy (n, 2) doubles, written to out
 * (at most 2 n - 5 rows of three int32 indices, counter-clockwise). Returns their count: 0 when the
 * points are fewer than three distinct or all on one line; -1 when memory ran out; -2 for a
 * coordinate that is not finite; -3 when their extent or its inverse overflows a double. */
int64_t o3dvis_delaunay(int64_t n, const double *xy, int32_t *out) {
    if (n < 3) return 0;
    double lo[2] = {INFINITY, INFINITY}, hi[2] = {-INFINITY, -INFINITY};
    for (int64_t i = 0; i < 2 * n; i++) {
        if (!isfinite(xy[i])) return -2;
        lo[i & 1] = fmin(lo[i & 1], xy[i]), hi[i & 1] = fmax(hi[i & 1], xy[i]);
    }
    double extent = fmax(hi[0] - lo[0], hi[1] - lo[1]);
    if (!(extent > 0)) return 0;
    /* a power of two, so that points given on a line or a lattice stay on it */
    double scale = ldexp(1.0, ilogb(GRID / extent));
    if (!isfinite(extent) || !isfinite(scale) || !(scale > 0)) return -3; /* beyond a double's range */
    int64_t max_edges = 3 * (2 * n - 5 > 1 ? 2 * n - 5 : 1), hash_size = (int64_t)ceil(sqrt((double)n));
    int64_t *x = malloc((size_t)(2 * n) * sizeof(int64_t));
    int32_t *ring = malloc((size_t)(3 * n + hash_size) * sizeof(int32_t));
    int32_t *twin = malloc((size_t)max_edges * sizeof(int32_t));
    keyed *order = malloc((size_t)n * sizeof(keyed));
    mesh m = {0};
    int64_t result = -1;
    if (!x || !ring || !twin || !order) goto done;
    m = (mesh){x, x + n, out, twin, ring, ring + n, ring + 2 * n, NULL, 0, 0};
    for (int64_t i = 0; i < n; i++) {
        x[i] = (int64_t)llround((xy[2 * i] - lo[0]) * scale);
        x[n + i] = (int64_t)llround((xy[2 * i + 1] - lo[1]) * scale);
    }
    int32_t *hash = ring + 3 * n;

    /* the seed: the point nearest the box's centre, its nearest distinct point, and the point that
     * makes the smallest circle with the two */
    double cx = 0.5 * scale * (hi[0] - lo[0]), cy = 0.5 * scale * (hi[1] - lo[1]);
    int32_t i0 = 0, i1 = -1, i2 = -1;
    double best = INFINITY;
    for (int32_t i = 0; i < n; i++) {
        double dx = (double)x[i] - cx, dy = (double)m.y[i] - cy, d = dx * dx + dy * dy;
        if (d < best) best = d, i0 = i;
    }
    best = INFINITY;
    for (int32_t i = 0; i < n; i++) {
        double dx = (double)(x[i] - x[i0]), dy = (double)(m.y[i] - m.y[i0]), d = dx * dx + dy * dy;
        if (d > 0 && d < best) best = d, i1 = i;
    }
    if (i1 < 0) { result = 0; goto done; } /* all on one grid node */
    best = INFINITY;
    for (int32_t i = 0; i < n; i++) {
        if (orient(&m, i0, i1, i) == 0) continue;
        double r = circumradius2(&m, i0, i1, i);
        if (r < best) best = r, i2 = i;
    }
    if (i2 < 0) { result = 0; goto done; } /* all on one line */
    if (orient(&m, i0, i1, i2) < 0) { int32_t t = i1; i1 = i2, i2 = t; }

    /* the seed's circumcentre; the points by their distance from it */
    {
        double ax = (double)x[i0], ay = (double)m.y[i0];
        double dx = (double)x[i1] - ax, dy = (double)m.y[i1] - ay, ex = (double)x[i2] - ax, ey = (double)m.y[i2] - ay;
        double bl = dx * dx + dy * dy, cl = ex * ex + ey * ey, d = 0.5 / (dx * ey - dy * ex);
        cx = ax + (ey * bl - dy * cl) * d, cy = ay + (dx * cl - ex * bl) * d;
    }
    for (int32_t i = 0; i < n; i++) {
        double dx = (double)x[i] - cx, dy = (double)m.y[i] - cy;
        order[i].distance = dx * dx + dy * dy, order[i].index = i;
    }
    qsort(order, (size_t)n, sizeof(keyed), by_distance);

    for (int64_t i = 0; i < n; i++) m.hull_next[i] = (int32_t)i;
    for (int64_t k = 0; k < hash_size; k++) hash[k] = -1;
    m.hull_next[i0] = i1, m.hull_next[i1] = i2, m.hull_next[i2] = i0;
    m.hull_prev[i1] = i0, m.hull_prev[i2] = i1, m.hull_prev[i0] = i2;
    m.hull_edge[i0] = 0, m.hull_edge[i1] = 1, m.hull_edge[i2] = 2;
    add_triangle(&m, i0, i1, i2, -1, -1, -1);
    hash[hash_key((double)x[i0] - cx, (double)m.y[i0] - cy, hash_size)] = i0;
    hash[hash_key((double)x[i1] - cx, (double)m.y[i1] - cy, hash_size)] = i1;
    hash[hash_key((double)x[i2] - cx, (double)m.y[i2] - cy, hash_size)] = i2;

    int32_t last = -1;
    for (int64_t k = 0; k < n; k++) {
        int32_t p = order[k].index;
        if (p == i0 || p == i1 || p == i2) continue;
        if (last >= 0 && x[p] == x[last] && m.y[p] == m.y[last]) continue; /* on the node just added */
        last = p;
        /* a hull point near p's angle, then the first hull edge p sees from the one before it */
        double dx = (double)x[p] - cx, dy = (double)m.y[p] - cy;
        int64_t key = hash_key(dx, dy, hash_size);
        int32_t start = -1;
        for (int64_t j = 0; j < hash_size; j++) {
            start = hash[(key + j) % hash_size];
            if (start >= 0 && m.hull_next[start] != start) break;
        }
        start = m.hull_prev[start];
        int32_t e = start, q;
        while (q = m.hull_next[e], orient(&m, e, q, p) >= 0) {
            e = q;
            if (e == start) { e = -1; break; }
        }
        if (e < 0) continue; /* inside the hull or on its edge: a duplicate or a tie in distance */

        /* p joins the edge e -> n it sees, then the edges it sees after it, then before it */
        int32_t t = add_triangle(&m, e, p, m.hull_next[e], -1, -1, m.hull_edge[e]);
        m.hull_edge[e] = t, m.hull_edge[p] = t + 1;
        if (legalize(&m, t + 2)) goto done;
        int32_t nx = m.hull_next[e];
        while (q = m.hull_next[nx], orient(&m, nx, q, p) < 0) {
            t = add_triangle(&m, nx, p, q, m.hull_edge[p], -1, m.hull_edge[nx]);
            m.hull_edge[p] = t + 1;
            if (legalize(&m, t + 2)) goto done;
            m.hull_next[nx] = nx;
            nx = q;
        }
        if (e == start) {
            while (q = m.hull_prev[e], orient(&m, q, e, p) < 0) {
                t = add_triangle(&m, q, p, e, -1, m.hull_edge[e], m.hull_edge[q]);
                m.hull_edge[q] = t;
                if (legalize(&m, t + 2)) goto done;
                m.hull_next[e] = e;
                e = q;
            }
        }
        m.hull_prev[p] = e, m.hull_next[e] = p, m.hull_prev[nx] = p, m.hull_next[p] = nx;
        hash[hash_key(dx, dy, hash_size)] = p;
        hash[hash_key((double)x[e] - cx, (double)m.y[e] - cy, hash_size)] = e;
    }
    result = m.triangles;
done:
    free(x), free(ring), free(twin), free(order), free(m.stack);
    return result;
}

/* The surface one camera sees: the Delaunay triangles of the points' image coordinates xy (n, 2)
 * whose edges, in 3D (xyz (n, 3)), are each no longer than the larger max_edge of their two ends,
 * turned to face the camera (3,), with their unit normals; triangles of zero area in 3D are
 * dropped. Writes tri (as o3dvis_delaunay) and normal (rows of 3 doubles, as many as triangles);
 * returns the count kept, or o3dvis_delaunay's error. Each step rounds as the numpy fallback does
 * (built without contraction into fused multiply-adds). */
int64_t o3dvis_view_surface(int64_t n, const double *xy, const double *xyz, const double *max_edge,
                            const double *camera, int32_t *tri, double *normal) {
    int64_t count = o3dvis_delaunay(n, xy, tri), kept = 0;
    for (int64_t t = 0; t < count; t++) {
        int32_t a = tri[3 * t], b = tri[3 * t + 1], c = tri[3 * t + 2];
        const double *pa = xyz + 3 * (int64_t)a, *pb = xyz + 3 * (int64_t)b, *pc = xyz + 3 * (int64_t)c;
        double ab[3], ac[3], bc[3];
        for (int k = 0; k < 3; k++) ab[k] = pb[k] - pa[k], ac[k] = pc[k] - pa[k], bc[k] = pc[k] - pb[k];
        double lab = fmax(max_edge[a], max_edge[b]), lbc = fmax(max_edge[b], max_edge[c]);
        double lca = fmax(max_edge[c], max_edge[a]);
        if (ab[0] * ab[0] + ab[1] * ab[1] + ab[2] * ab[2] > lab * lab
            || bc[0] * bc[0] + bc[1] * bc[1] + bc[2] * bc[2] > lbc * lbc
            || ac[0] * ac[0] + ac[1] * ac[1] + ac[2] * ac[2] > lca * lca)
            continue;
        double m[3] = {ab[1] * ac[2] - ab[2] * ac[1], ab[2] * ac[0] - ab[0] * ac[2], ab[0] * ac[1] - ab[1] * ac[0]};
        double length = sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2]);
        if (!(length > 0)) continue;
        double facing = m[0] * (camera[0] - pa[0]) + m[1] * (camera[1] - pa[1]) + m[2] * (camera[2] - pa[2]);
        if (facing < 0) { /* the other winding, whose normal is the opposite */
            int32_t swap = b; b = c, c = swap;
            m[0] = -m[0], m[1] = -m[1], m[2] = -m[2];
        }
        tri[3 * kept] = a, tri[3 * kept + 1] = b, tri[3 * kept + 2] = c;
        for (int k = 0; k < 3; k++) normal[3 * kept + k] = m[k] / length;
        kept++;
    }
    return count < 0 ? count : kept;
}
