r"""Exact point visibility by ray casting: does a triangle lie between the camera centre and a point?

The synthetic generator labels a landmark visible when the segment from the camera centre to it
crosses no triangle of the scene (head, eyes, mouth, hair, headwear, clothing, occluders) more than a
tolerance before it. Reading the rendered z-buffer at the nearest pixel instead mislabels landmarks
next to occluding edges and under sloped hair (``docs/synthetic_data.md``).

A ray from the camera centre projects to one image point, so only triangles whose projected bounding
box contains that point can cross it. Triangles are binned by their projected boxes on a grid of
cells about twice the median triangle's size, and each point is tested exactly (Möller-Trumbore, in
float64) against the triangles of its cell's neighbourhood plus the few large ones.
"""

from __future__ import annotations

import numpy as np

from facenormals.data.render import _check_finite, _check_shape

__all__ = ["blocked_rays"]

#: Most grid cells along a side; a finer grid (tiny triangles, points far apart) gets coarser cells.
_MAX_CELLS = 1024
#: Points per query: the (candidate triangle, point) box test of a chunk is a dense matrix.
_CHUNK = 64
#: Crossings within this fraction of the distance to the point count as the point itself, however
#: small the tolerance: float64 rounding puts a point's own triangle at s = 1 - 1e-16 or so.
_SELF = 1e-9


def blocked_rays(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                 tolerance: float | np.ndarray = 0.0) -> np.ndarray:
    r"""Whether the segment from the camera centre to each point crosses a triangle before it.

    A crossing counts when it lies more than ``tolerance`` (along the ray) in front of the point,
    so a point on a surface is not blocked by its own triangles, nor by folds of that surface
    shallower than the tolerance; crossings within a relative 1e-9 of the point's distance count as
    the point itself even at zero tolerance. Triangles are double-sided; crossings behind the point
    never count.

    Args:
        points: ``(P, 3)`` camera-frame points, in front of the camera (``z > 0``).
        vertices: ``(V, 3)`` camera-frame vertices of the triangles, in the points' unit.
        faces: ``(F, 3)`` integer vertex indices of the triangles.
        tolerance: a length ``>= 0``, or ``(P,)`` lengths, one per point.

    Returns:
        ``(P,)`` bool, ``True`` where the point is hidden.

    Raises:
        ValueError: on shapes or dtypes, non-finite values, points with ``z <= 0`` or whose
            projection ``(x / z, y / z)`` overflows, out-of-range face indices or a negative tolerance.

    Example:
        >>> square = np.array([[-1.0, -1, 5], [1, -1, 5], [1, 1, 5], [-1, 1, 5]])
        >>> faces = np.array([[0, 1, 2], [0, 2, 3]])
        >>> blocked_rays(np.array([[0.0, 0, 10], [0, 0, 4], [3, 0, 10], [0, 0, 5.5]]), square, faces, 1.0)
        array([ True, False, False, False])
    """
    points, vertices, faces, tolerance = _check(points, vertices, faces, tolerance)
    blocked = np.zeros(len(points), dtype=bool)
    if len(points) == 0 or len(faces) == 0:
        return blocked
    boxes = _TriangleBoxes(vertices, faces)
    target = points[:, :2] / points[:, 2:3]
    # chunks of nearby points (sorted along x) keep each chunk's candidate triangles few
    order = np.argsort(target[:, 0], kind="stable")
    for chunk in np.array_split(order, -(-len(points) // _CHUNK)):
        pair_triangle, pair_point = boxes.pairs(target[chunk])
        if len(pair_point) == 0:
            continue
        pair_point = chunk[pair_point]
        hit_at = _segment_hits(points[pair_point], vertices[faces[pair_triangle]])
        limit = 1.0 - tolerance[pair_point] / np.linalg.norm(points[pair_point], axis=1) - _SELF
        blocked[pair_point[hit_at < limit]] = True
    return blocked


class _TriangleBoxes:
    """The triangles' projected bounding boxes on the plane ``z = 1``, for :func:`blocked_rays`.

    Triangles behind the camera are dropped (no segment from it to a point in front reaches them);
    those straddling its plane, or whose projection overflows, have no usable box and are paired
    with every point.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        z = vertices[:, 2]
        front = z > 0
        a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
        faces_front = front[a] & front[b] & front[c]
        partly_front = (front[a] | front[b] | front[c]) & ~faces_front
        index = np.flatnonzero(faces_front)
        a, b, c = a[index], b[index], c[index]
        depth = np.where(front, z, 1.0)
        bounds = []
        with np.errstate(over="ignore"):  # an overflow to inf is caught below
            for image in (vertices[:, 0] / depth, vertices[:, 1] / depth):  # per axis: 3-wide reductions are slow
                ia, ib, ic = image[a], image[b], image[c]
                bounds.append((np.minimum(np.minimum(ia, ib), ic), np.maximum(np.maximum(ia, ib), ic)))
        low = np.stack([bounds[0][0], bounds[1][0]], axis=1)
        high = np.stack([bounds[0][1], bounds[1][1]], axis=1)
        self.everywhere = np.flatnonzero(partly_front)
        finite = np.logical_and.reduce([np.isfinite(bound) for pair in bounds for bound in pair])
        if not finite.all():
            self.everywhere = np.concatenate([self.everywhere, index[~finite]])
            index, low, high = index[finite], low[finite], high[finite]
        self.index, self.low, self.high = index, low, high
        self.extent = np.maximum(self.high[:, 0] - self.low[:, 0], self.high[:, 1] - self.low[:, 1])
        self.median = float(np.median(self.extent)) if len(self.extent) else 0.0

    def pairs(self, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(triangle, point)`` index pairs whose box holds the point's projection ``target``
        ``(P, 2)``, plus every triangle without a box with every point."""
        span = float((target.max(0) - target.min(0)).max())
        cell = max(2.0 * self.median, span / (_MAX_CELLS - 4), 1e-12)
        large = self.extent >= cell
        # boxes smaller than a cell lie in at most 2 x 2 cells, from the cell of their low corner
        origin = target.min(0) - cell
        size = int(np.floor(span / cell)) + 3
        start = np.floor((self.low - origin) / cell).astype(np.int64)
        wanted = np.zeros((size, size), dtype=bool)
        cells = np.floor((target - origin) / cell).astype(np.int64)
        for du in (0, 1):
            for dv in (0, 1):
                wanted[cells[:, 0] - du, cells[:, 1] - dv] = True
        on_grid = ~large & (start[:, 0] >= 0) & (start[:, 1] >= 0) & (start[:, 0] < size) & (start[:, 1] < size)
        near = np.zeros(len(self.index), dtype=bool)
        near[on_grid] = wanted[start[on_grid, 0], start[on_grid, 1]]
        candidates = np.flatnonzero(near | large)
        slack = 1e-9 * max(1.0, float(np.abs(target).max()))
        inside = np.ones((len(candidates), len(target)), dtype=bool)
        for k in (0, 1):  # per axis: 2-wide reductions are slow
            inside &= ((self.low[candidates, k, None] - slack <= target[:, k])
                       & (target[:, k] <= self.high[candidates, k, None] + slack))
        pair_triangle, pair_point = np.nonzero(inside)
        pair_triangle = self.index[candidates[pair_triangle]]
        if len(self.everywhere):
            pair_point = np.concatenate([pair_point, np.repeat(np.arange(len(target)), len(self.everywhere))])
            pair_triangle = np.concatenate([pair_triangle, np.tile(self.everywhere, len(target))])
        return pair_triangle, pair_point


def _segment_hits(ends: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Möller-Trumbore: the fraction ``s`` in ``(0, inf)`` along each segment from the origin to
    ``ends`` ``(K, 3)`` at which it crosses its triangle ``(K, 3, 3)``, ``inf`` where it misses."""
    v0 = triangles[:, 0]
    e1, e2 = triangles[:, 1] - v0, triangles[:, 2] - v0
    p = np.cross(ends, e2)
    det = np.einsum("ki,ki->k", e1, p)
    usable = det != 0.0
    inverse = 1.0 / np.where(usable, det, 1.0)
    t = -v0  # origin minus the first corner
    u = np.einsum("ki,ki->k", t, p) * inverse
    q = np.cross(t, e1)
    v = np.einsum("ki,ki->k", ends, q) * inverse
    s = np.einsum("ki,ki->k", e2, q) * inverse
    hits = usable & (u >= 0) & (v >= 0) & (u + v <= 1) & (s > 0)
    return np.where(hits, s, np.inf)


def _check(points, vertices, faces, tolerance) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    for name, value in (("points", points), ("vertices", vertices)):
        _check_shape(value, (None, 3), name)
        _check_finite(value, name)
    points, vertices = np.asarray(points, np.float64), np.asarray(vertices, np.float64)
    if (points[:, 2] <= 0).any():
        raise ValueError(f"points: expected points in front of the camera (z > 0), got z = {points[:, 2].min():g}")
    with np.errstate(over="ignore"):
        if not np.isfinite(points[:, :2] / points[:, 2:3]).all():
            raise ValueError("points: expected projections x / z, y / z within float64's range, got an overflow "
                             f"(z down to {points[:, 2].min():g})")
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"faces: expected an integer array of shape (F, 3), got {faces.dtype} of shape {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(f"faces: expected indices in [0, {len(vertices)}), got {faces.min()}..{faces.max()}")
    _check_finite(tolerance, "tolerance")
    tolerance = np.asarray(tolerance, np.float64)
    if tolerance.shape not in ((), (len(points),)):
        raise ValueError(f"tolerance: expected a number or shape ({len(points)},), got shape {tolerance.shape}")
    tolerance = np.broadcast_to(tolerance, (len(points),))
    if (tolerance < 0).any():
        raise ValueError(f"tolerance: expected finite lengths >= 0, got {tolerance.min()}")
    return points, vertices, faces.astype(np.int64), tolerance
