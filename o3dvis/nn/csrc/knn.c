/* The nearest neighbours that the normals' plane fits take (o3dvis/neighbours.py): sought in the
 * cells of a grid (o3dvis_key_table hashes the cells), or among all points for the few the grid
 * cannot answer (o3dvis_brute_knn). */

#include "kernels.h"

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
 * (o3dvis/neighbours.py, _nearest_by_search), among all points: k <= min(n, 64), ties keep the
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
 * (o3dvis/neighbours.py, nearest_neighbours), among the points of its cell and the 26 around it.
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
