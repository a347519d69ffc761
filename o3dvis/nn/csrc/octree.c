/* The octree of the encoding (o3dvis/nn/octree.py): a cloud's bounds and its normalisation into
 * [-1, 1]^3 with its Morton keys in two passes, the keys' radix sort, an octree's levels from its
 * sorted keys in two passes and a level's 3x3x3 neighbours from its parents'. */

#include "kernels.h"

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
