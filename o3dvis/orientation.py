"""Oriented normals from visibility: plane fits, the cameras' vote, propagation along the surface.

A point that a camera sees faces it, so the cameras that see a point vote on
the side of its normal; where they split, as on the two faces of a wall
thinner than the points' spacing, or none votes, the side of its neighbours a
point lies on decides; points without a plane of their own take their side
from where they join oriented ones along the surface; and neighbours that the
cameras see alike lie on one side of a wall and one face of an edge, so they
weigh most in a point's plane fit. NumPy and SciPy on (N, 3) arrays (the plane fits and their
weights in one pass of C where the package's kernels are built), shared by the
two-pass encoding of :class:`o3dvis.NeuralVisibility` (normals from a plane
fit to each point's nearest neighbours, :func:`oriented_planes`) and the normal
estimation of :mod:`o3dvis.apps.normals`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree
from scipy.spatial import cKDTree

from .neighbours import NeighbourSearch, nearest_neighbours
from .nn import native
from .threads import PARALLEL_ROWS, plan_threads, side_by_side

__all__ = ["voted_normals", "oriented_planes", "fit_planes", "smallest_eigenvectors", "vote", "facing_away",
           "visibility_affinity", "layer_sides", "surface_variation", "orient_by_vote", "complete_orientation",
           "row_chunks"]

_GRAPH_NEIGHBOURS = 10  # neighbours of a point in the graph that propagates orientation
# the scale of the visibility differences that weigh a plane fit's neighbours (visibility_affinity):
# the best of the scales tried on the validation meshes, where weighted fits beat unweighted ones
_AFFINITY_SCALE = 0.1
# the least weight of a neighbour: a point whose neighbours all look different to the cameras (as
# with exact visibility, where each camera's horizon falls) keeps a well-conditioned fit
_AFFINITY_FLOOR = 0.01
# a vote whose agreement is below this leaves the normal to the plane through LAYER_NEIGHBOURS
# points and its side to layer_sides: the cameras split on thin walls (bowls, cups, chairs), where
# the side of the point's layer is the surer guide
_WEAK_AGREEMENT = 0.6
LAYER_NEIGHBOURS = 16


_CHUNK = 4096  # rows of neighbourhoods handled at once


def row_chunks(count: int, size: int = _CHUNK, start: int = 0) -> list[slice]:
    """Slices of ``size`` rows covering ``start..count``: per-neighbour temporaries of a chunk stay in cache."""
    return [slice(first, min(first + size, count)) for first in range(start, count, size)]


def _on_threads(fn: Callable[[slice], object], count: int) -> Iterator:
    """``fn`` of a share of ``count`` rows on each of the threads the load allows (one below
    :data:`~o3dvis.threads.PARALLEL_ROWS` rows), in order: for C kernels and numpy ops, which let go
    of the GIL."""
    workers = plan_threads(count, PARALLEL_ROWS)
    return side_by_side(fn, row_chunks(count, -(-count // workers) if count else 1), workers)


def fit_planes(points: np.ndarray, neighbours: np.ndarray, weight: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (M, 3) of weighted least-squares planes through rows of neighbours (M, K), and
    (M,) whether each is defined: three neighbours of positive weight, not all on one line. One
    pass of C where the kernels are built (``native.fit_planes``), else these numpy ops.
    ``weight``: (M, K), None for all 1."""
    if not len(neighbours):
        return np.empty((0, 3)), np.empty(0, dtype=bool)
    if native.available():
        points, neighbours = (torch.from_numpy(np.ascontiguousarray(a, dtype=t)) for a, t in (
            (points, np.float64), (neighbours, np.int64)))
        weight = None if weight is None else torch.from_numpy(np.ascontiguousarray(weight, dtype=np.float64))
        parts = list(_on_threads(lambda rows: native.fit_planes(
            points, neighbours[rows], None if weight is None else weight[rows]), len(neighbours)))
        return torch.cat([n for n, _ in parts]).numpy(), torch.cat([p for _, p in parts]).numpy()
    weight = np.ones(neighbours.shape) if weight is None else weight
    # homogeneous coordinates, so that one product per neighbourhood gives the weighted sums of
    # the offsets, of their outer products and of the weights: [[S, s], [s^T, w]]; components
    # first, so that elementwise passes run along the neighbours
    padded = np.zeros((4, len(points) + 1))
    padded[:3, :-1], padded[3, :-1] = points.T, 1
    normals, planar = np.empty((len(neighbours), 3)), np.empty(len(neighbours), dtype=bool)
    for rows in row_chunks(len(neighbours)):
        near = padded[:, neighbours[rows]]  # (4, rows, K)
        near[:3] -= near[:3, :, :1].copy()  # offsets from one of the neighbours: no cancellation
        sums = np.matmul((near * weight[rows]).transpose(1, 0, 2), near.transpose(1, 2, 0))
        total, mass = sums[:, :3, 3], np.maximum(sums[:, 3, 3], 1e-300)
        scatter = sums[:, :3, :3] - total[:, :, None] * total[:, None, :] / mass[:, None, None]
        normals[rows], planar[rows] = smallest_eigenvectors(scatter)
    return normals, (np.count_nonzero(weight > 0, axis=1) >= 3) & planar


def smallest_eigenvectors(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit eigenvectors of the smallest eigenvalues of symmetric 3x3 matrices, in closed form.

    Faster than ``np.linalg.eigh`` on many small matrices. The eigenvalues come from the trigonometric solution of the characteristic
    cubic. Of the largest and the smallest, the one farther from the middle
    eigenvalue is well separated, so its eigenvector is found accurately as
    the longest cross product of two rows of ``A - lambda I``; the other two
    eigenvectors are those of the 2x2 restriction of ``A`` to its orthogonal
    complement, solved by an angle (stable however close the two are).

    Args:
        matrices: (M, 3, 3) symmetric.

    Returns:
        (M, 3) unit vectors (arbitrary where the smallest eigenvalue is not
        simple) and (M,) bool: whether the middle eigenvalue exceeds 1e-12
        times the largest (for a scatter matrix: the points are not all on one line).
    """
    scale = np.abs(matrices).max(axis=(1, 2))
    # the six distinct entries as arrays of their own: elementwise passes over (M,) arrays are
    # what numpy does fast, not reductions over axes of 3
    xx, xy, xz, yy, yz, zz = (matrices[:, i, j] / np.where(scale > 0, scale, 1)
                              for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)))
    largest, smallest, low = _outer_eigenvalues(xx, xy, xz, yy, yz, zz)
    far = np.where(low, smallest, largest)
    rows = ((xx - far, xy, xz), (xy, yy - far, yz), (xz, yz, zz - far))
    crosses = np.stack([_cross(rows[i], rows[j]) for i, j in ((0, 1), (0, 2), (1, 2))])  # (3, 3, M)
    length = np.sqrt((crosses ** 2).sum(axis=1))
    best = np.take_along_axis(crosses, length.argmax(axis=0)[None, None], axis=0)[0]
    longest = np.sqrt((best ** 2).sum(axis=0))
    axis = best / np.where(longest > 0, longest, 1)
    axis[2, longest == 0] = 1  # every eigenvalue equal: any direction
    # an orthonormal basis (u, v) of the plane normal to that axis, and the matrix on it
    tilted = np.abs(axis[0]) < 0.9
    u = np.stack(_cross(axis, (tilted, ~tilted, np.zeros_like(tilted))))
    u /= np.sqrt((u ** 2).sum(axis=0))
    v = np.stack(_cross(axis, u))

    def form(p: np.ndarray, q: np.ndarray) -> np.ndarray:  # p^T A q, (M,)
        return (p[0] * (xx * q[0] + xy * q[1] + xz * q[2]) + p[1] * (xy * q[0] + yy * q[1] + yz * q[2])
                + p[2] * (xz * q[0] + yz * q[1] + zz * q[2]))

    uu, uv, vv = form(u, u), form(u, v), form(v, v)
    turn = np.arctan2(2 * uv, uu - vv) / 2  # the major axis in the plane is cos(turn) u + sin(turn) v
    minor = np.cos(turn) * v - np.sin(turn) * u
    mean, radius = (uu + vv) / 2, np.hypot((uu - vv) / 2, uv)
    middle = np.where(low, mean - radius, mean + radius)
    return np.where(low, axis, minor).T, middle > 1e-12 * largest


def _outer_eigenvalues(xx, xy, xz, yy, yz, zz) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The largest and the smallest eigenvalues of symmetric 3x3 matrices given as their six
    distinct entries (M,) each, by the trigonometric solution of the characteristic cubic, and
    whether the smallest is the one farther from the middle eigenvalue (then it is the accurate one
    of the two; the other is off by a few ulps of the largest)."""
    third = (xx + yy + zz) / 3
    dx, dy, dz = xx - third, yy - third, zz - third
    spread = np.sqrt((dx * dx + dy * dy + dz * dz + 2 * (xy * xy + xz * xz + yz * yz)) / 6)
    det = dx * (dy * dz - yz * yz) - xy * (xy * dz - yz * xz) + xz * (xy * yz - dy * xz)
    half_det = np.clip(det / (2 * np.where(spread > 0, spread, 1) ** 3), -1, 1)
    angle = np.arccos(half_det) / 3
    return (third + 2 * spread * np.cos(angle), third + 2 * spread * np.cos(angle + 2 * np.pi / 3),
            half_det < 0)


def _cross(p, q) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cross product of vectors given as three component arrays each (np.cross is slow on these)."""
    return p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]


def vote(points: np.ndarray, normals: np.ndarray, cameras: np.ndarray, visibility: np.ndarray
          ) -> np.ndarray:
    """Each point's vote on the side of its normal, (N,): the sum over the cameras of cos(normal,
    direction to the camera), each weighted by ``max(0, 2 p - 1)`` of the probability ``p`` that
    the camera sees the point (``visibility``, (V, N); bool: 1 where it does, else 0). A camera
    that sees a point barely, as both sides of a thin wall are seen, votes little, and one more
    likely not to see it than to see it does not vote."""
    return _votes(points, normals, cameras, visibility)[0]


def facing_away(points: np.ndarray, normals: np.ndarray, cameras: np.ndarray, visibility: np.ndarray) -> float:
    """How much of the cameras' vote (:func:`vote`) on the points' normals is against them: the sum of
    the negative votes' magnitudes over that of all votes, in [0, 1] (0 where none votes).

    Oriented normals face the cameras that see their points: near 0. Normals that point either way
    (as ``estimate_normals`` leaves them) or face one sensor split the vote: near 0.5.
    """
    votes = vote(points, normals, cameras, visibility)
    total = float(np.abs(votes).sum())
    return float(np.clip(-votes, 0, None).sum()) / total if total > 0 else 0.0


def _votes(points: np.ndarray, normals: np.ndarray, cameras: np.ndarray, visibility: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`vote`, and its agreement (N,): the vote over the sum of the absolute values of its
    terms, 1 where every camera that votes sees the point's normal side, 0 where none votes or
    the cameras on the two sides weigh the same."""
    if native.available() and len(cameras):  # one pass of C over the points, a camera at a time
        tensors = [torch.from_numpy(np.ascontiguousarray(a, dtype=t)) for a, t in (
            (points, np.float64), (normals, np.float64), (cameras, np.float64), (visibility, np.float32))]
        parts = list(_on_threads(lambda rows: native.votes(*tensors, rows), len(points)))
        return tuple(torch.cat([part[k] for part in parts]).numpy() if parts else np.empty(0) for k in (0, 1))
    vote, agreement = np.empty(len(points)), np.empty(len(points))

    def chunk(rows: slice) -> None:  # (points, views) products, no per-view pass
        p, n = points[rows], normals[rows]
        reach = n @ cameras.T - np.einsum("ij,ij->i", n, p)[:, None]  # n . (camera - p)
        distance = np.sqrt(np.maximum((cameras ** 2).sum(axis=1) - 2 * p @ cameras.T
                                      + (p ** 2).sum(axis=1)[:, None], 1e-300))
        seen = visibility[:, rows].T
        weight = seen if seen.dtype == bool else np.maximum(2 * seen - 1, 0)
        terms = weight * (reach / distance)
        vote[rows] = terms.sum(axis=1)
        agreement[rows] = np.abs(vote[rows]) / np.maximum(np.abs(terms).sum(axis=1), 1e-300)

    for _ in _on_threads(lambda rows: [chunk(part) for part in row_chunks(rows.stop, start=rows.start)],
                         len(points)):
        pass
    return vote, agreement


def layer_sides(points: np.ndarray, neighbours: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(M,) the side of its neighbours' centroid on which each point lies, along its normal: +1 the
    normal's side, -1 the other, 0 on the centroid's plane.

    In a wall thinner than the points' spacing, the points of its two faces mingle in every
    neighbourhood and each face's lie on its own side of the centroid; on a single curved face,
    the point lies on the convex side.

    Args:
        points: (N, 3) points.
        neighbours: (M, K) rows of indices into ``points``, nearest first, as
            :func:`nearest_neighbours` gives them: a row's first is its point (or one at its place).
        normals: (M, 3) the rows' normals.
    """
    sides = np.empty(len(neighbours))
    for rows in row_chunks(len(neighbours)):
        near = points[neighbours[rows]]
        sides[rows] = np.sign(np.einsum("ij,ij->i", near[:, 0] - near.mean(axis=1), normals[rows]))
    return sides


def visibility_affinity(visibility: np.ndarray, neighbours: np.ndarray, scale: float = _AFFINITY_SCALE
                        ) -> np.ndarray:
    """(N, K) weights of each point's neighbours in its plane fit: ``exp(-d^2 / scale^2)``, with
    ``d^2`` the mean over the cameras of the squared difference between the probabilities that
    each sees the point and the neighbour (``visibility``, (V, N), bool or in [0, 1]), and at
    least :data:`_AFFINITY_FLOOR`. One pass of C where the kernels are built
    (``native.visibility_affinity``), else numpy ops.

    Neighbours the cameras see alike lie on the point's side of a thin wall and on its face of
    an edge; the others, on the far side or the next face, barely tilt the plane.

    Raises:
        ValueError: ``scale`` is not positive.
    """
    if not scale > 0:
        raise ValueError(f"scale must be positive, got {scale}")
    if not len(visibility):  # no camera tells any two points apart
        return np.ones(neighbours.shape)
    if native.available():
        table = native.affinity_table(torch.from_numpy(np.asarray(visibility, dtype=np.float32)))
        near = torch.from_numpy(np.ascontiguousarray(neighbours, dtype=np.int64))
        return torch.cat(list(_on_threads(lambda rows: native.visibility_affinity(
            table, len(visibility), near[rows], rows.start, scale, _AFFINITY_FLOOR), len(neighbours)))).numpy()
    table = np.ascontiguousarray(visibility.T, dtype=np.float32)  # (N, V): a point's answers together
    weight = np.empty(neighbours.shape, dtype=np.float64)

    def chunk(rows: slice) -> None:
        squared = np.square(table[neighbours[rows]] - table[rows, None]).mean(axis=2)
        weight[rows] = np.maximum(np.exp(squared * (-1.0 / scale ** 2)), _AFFINITY_FLOOR)

    for _ in _on_threads(lambda rows: [chunk(part) for part in row_chunks(rows.stop, start=rows.start)],
                         len(neighbours)):
        pass
    return weight


def orient_by_vote(points: np.ndarray, normals: np.ndarray, defined: np.ndarray, votes: np.ndarray,
                   tree: cKDTree | None = None, neighbours: np.ndarray | None = None) -> np.ndarray:
    """``normals`` turned to the side their votes give, the unvoted ones completed by :func:`complete_orientation`.

    Args:
        points: (N, 3) points.
        normals: (N, 3) unit normals, of either side.
        defined: (N,) bool: where ``normals`` means something (elsewhere the nearest
            voted defined point's normal replaces it).
        votes: (N,) from :func:`vote`; 0: no camera voted.
        tree: a ``cKDTree`` of ``points`` to reuse (None: built if needed).
        neighbours: see :func:`complete_orientation`.

    Returns:
        (N, 3) oriented unit normals.
    """
    normals = np.where(votes[:, None] < 0, -normals, normals)
    return complete_orientation(points, normals, (votes != 0) & defined, defined, tree, neighbours)


def complete_orientation(points: np.ndarray, normals: np.ndarray, oriented: np.ndarray,
                         defined: np.ndarray, tree: cKDTree | None, neighbours: np.ndarray | None = None
                         ) -> np.ndarray:
    """``normals`` completed from the ``oriented`` ones, (N, 3).

    Rows neither oriented nor ``defined`` take the nearest oriented point's normal;
    the defined ones keep their own, turned to the side :func:`_propagate` gives,
    or, with no path to an oriented point, to the side of the nearest oriented one.
    ``neighbours``: (N, K) each point's nearest points, itself included, found already: the
    propagation's graph joins each loose point to them (None: to its 10 nearest, searched here).
    """
    nearest = _nearest_among(points, oriented)
    normals = normals.copy()
    filled = ~oriented & ~defined
    normals[filled] = normals[nearest(filled)]
    normals, unreached = _propagate(points, normals, oriented | ~defined, tree, neighbours)
    away = np.einsum("ij,ij->i", normals[unreached], normals[nearest(unreached)]) < 0
    normals[np.flatnonzero(unreached)[away]] *= -1
    return normals


def _nearest_among(points: np.ndarray, chosen: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """A lookup of the nearest ``chosen`` point (its index) of each row a boolean mask selects.

    The k-d tree of the chosen points is built at the first lookup of any row, so
    clouds with nothing to look up never pay for it. With none chosen, each row is its own.
    """
    index = np.flatnonzero(chosen)
    tree = functools.cache(lambda: cKDTree(points[index], balanced_tree=False))

    def nearest(rows: np.ndarray) -> np.ndarray:
        if not rows.any() or not len(index):
            return np.flatnonzero(rows)
        return index[tree().query(points[rows], workers=-1)[1]]

    return nearest


def _propagate(points: np.ndarray, normals: np.ndarray, oriented: np.ndarray, tree: cKDTree | None,
               neighbours: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``normals`` with the rows not ``oriented`` flipped to agree with the oriented ones, (N, 3),
    and which of those rows have no path to an oriented one (left as they were), (N,) bool.

    The propagation of Open3D's ``orient_normals_consistent_tangent_plane``,
    seeded: a minimum spanning tree of the nearest-neighbour graph of the
    loose points (an edge costs ``1 - |n_i . n_j|``, low along a smooth surface)
    is rooted at all oriented points at once, and each loose point takes the
    side of its parent. A surface seen nowhere thus takes its side from where
    it joins a seen one, not from the nearest seen point, which may lie across
    a gap and face the other way. ``tree``: a ``cKDTree`` of ``points`` (None:
    built here when there is something to propagate); ``neighbours``: as in
    :func:`complete_orientation`.
    """
    loose = np.flatnonzero(~oriented)
    count = len(points)
    if not len(loose) or len(loose) == count:
        return normals, np.zeros(count, dtype=bool)
    if neighbours is None:
        k = min(_GRAPH_NEIGHBOURS + 1, count)
        near = (cKDTree(points) if tree is None else tree).query(points[loose], k=k, workers=-1)[1].reshape(-1, k)
    else:
        near = neighbours[loose]
    a, b = np.repeat(loose, near.shape[1]), near.ravel()
    pairs = np.sort(np.minimum(a, b) * count + np.maximum(a, b))  # np.unique is 20x slower here
    a, b = np.divmod(pairs[np.append(True, pairs[1:] != pairs[:-1])], count)
    a, b = a[a != b], b[a != b]  # no loops (a point is its own nearest neighbour)
    cost = 1 + 1e-6 - np.abs(np.einsum("ij,ij->i", normals[a], normals[b]))
    joined = np.zeros(count, dtype=bool)
    joined[a] = joined[b] = True
    seeds = np.flatnonzero(joined & oriented)  # each joined to a root past the points, at (almost) no cost
    graph = coo_matrix((np.concatenate([cost, np.full(len(seeds), 1e-9)]),
                        (np.concatenate([a, seeds]), np.concatenate([b, np.full(len(seeds), count)]))),
                       shape=(count + 1, count + 1))
    _, parent = breadth_first_order(minimum_spanning_tree(graph), count, directed=False)
    parent = parent[:count]
    top = (parent < 0) | (parent == count)  # not reached, or oriented
    parent = np.where(top, np.arange(count), parent)
    side = np.where(top | (np.einsum("ij,ij->i", normals, normals[parent]) >= 0), 1, -1)
    while (parent[parent] != parent).any():  # products of the sides along each path to its top
        side, parent = side * side[parent], parent[parent]
    return normals * side[:, None], top & ~oriented


def voted_normals(points: np.ndarray, cameras: np.ndarray, visibility: np.ndarray, neighbours: int = 8,
                  affinity: float | None = _AFFINITY_SCALE) -> np.ndarray:
    """Oriented unit normals: planes through each point's nearest neighbours, voted by the cameras.

    Each normal is that of the least-squares plane through the point's
    ``neighbours`` nearest points (as Open3D's ``estimate_normals`` with a KNN
    search fits it), each neighbour weighted by how alike the cameras see it
    and the point (:func:`visibility_affinity`), turned to face the cameras
    that see the point (:func:`vote`). Where those cameras split or none
    votes (on a wall thinner than the points' spacing, both faces look seen
    from both sides), the normal is the unweighted plane through the point's
    16 nearest points (or ``neighbours``, if more), turned to the side of
    their centroid that the point lies on (:func:`layer_sides`); where no
    plane fits, the side is taken along the surface
    (:func:`complete_orientation`).

    Args:
        points: (N, 3) points.
        cameras: (V, 3) camera positions.
        visibility: (V, N) which points each camera sees (bool), or the probabilities that it does.
        neighbours: points per plane fit, the point included (at least 3).
        affinity: the scale of :func:`visibility_affinity`; None: every neighbour weighs the same.

    Returns:
        (N, 3) unit normals.

    Raises:
        ValueError: fewer than 3 neighbours, or no plane fits anywhere (the
            points are fewer than 3 or all on one line).
    """
    if neighbours < 3:
        raise ValueError(f"a plane needs at least 3 neighbours, got {neighbours}")
    near = nearest_neighbours(points, min(max(neighbours, LAYER_NEIGHBOURS), len(points)))
    return oriented_planes(points, near, cameras, visibility, affinity, fit=min(neighbours, len(points)))


def oriented_planes(points: np.ndarray, neighbours: np.ndarray, cameras: np.ndarray, visibility: np.ndarray,
                    affinity: float | None = _AFFINITY_SCALE, fit: int | None = None,
                    search: NeighbourSearch | None = None) -> np.ndarray:
    """:func:`voted_normals` of points whose neighbours are found already: (N, K) indices, nearest
    first, as :func:`nearest_neighbours` gives them. The weighted planes fit the first ``fit`` of
    them (None: all K); where the vote is weak, the plane through all K decides, or with the
    cloud's ``search`` the plane through the :data:`LAYER_NEIGHBOURS` it finds for those points."""
    near = neighbours if fit is None else neighbours[:, :fit]
    weight = None if affinity is None else visibility_affinity(visibility, near, affinity)
    normals, defined = fit_planes(points, near, weight)
    if not defined.any():
        raise ValueError("no plane fits the points: they are fewer than 3 or all on one line")
    votes, agreement = _votes(points, normals, cameras, visibility)
    normals = np.where(votes[:, None] < 0, -normals, normals)
    oriented = (votes != 0) & defined
    # where the cameras split (both faces of a wall thinner than the spacing look seen) or none
    # votes, a plane through all K neighbours, unweighted, turned to the side of their centroid
    # that the point lies on, tells the faces apart
    weak = np.flatnonzero(agreement < _WEAK_AGREEMENT)
    wide = neighbours[weak] if search is None else search.query(min(LAYER_NEIGHBOURS, len(points)), weak)
    planes, fitted = fit_planes(points, wide)
    sides = layer_sides(points, wide, planes)
    turned = fitted & (sides != 0)
    normals[weak[turned]] = planes[turned] * sides[turned, None]
    oriented[weak[turned]] = True
    return complete_orientation(points, normals, oriented, defined | oriented, None, near)


def surface_variation(points: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """(M,) the surface variation of rows of neighbours (M, K): the least eigenvalue of their
    covariance over the sum of the three, 0 where they lie on a plane and 1/3 where they scatter
    alike in every direction. Noise raises it everywhere, curvature and edges only where they are.

    Raises:
        ValueError: fewer than 3 neighbours a row.
    """
    if neighbours.shape[1] < 3:
        raise ValueError(f"a surface variation needs at least 3 neighbours, got {neighbours.shape[1]}")
    x, y, z = (c - c.mean(axis=1, keepdims=True) for c in np.moveaxis(points[neighbours], 2, 0))
    sums = [(p * q).sum(axis=1) for p, q in ((x, x), (x, y), (x, z), (y, y), (y, z), (z, z))]
    trace = sums[0] + sums[3] + sums[5]
    # the scatter over its trace, whose eigenvalues sum to 1 (and stay far from under- and overflow)
    _, smallest, _ = _outer_eigenvalues(*(v / np.where(trace > 0, trace, 1) for v in sums))
    return np.maximum(smallest, 0)
