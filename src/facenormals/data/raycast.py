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

__all__ = ["blocked_rays"]

#: Most grid cells along a side; a finer grid (tiny triangles, points far apart) gets coarser cells.
_MAX_CELLS = 1024


def blocked_rays(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                 tolerance: float | np.ndarray = 0.0) -> np.ndarray:
    r"""Whether the segment from the camera centre to each point crosses a triangle before it.

    A crossing counts when it lies more than ``tolerance`` (along the ray) in front of the point,
    so a point on a surface is not blocked by its own triangles, nor by folds of that surface
    shallower than the tolerance. Triangles are double-sided; crossings behind the point never count.

    Args:
        points: ``(P, 3)`` camera-frame points, in front of the camera (``z > 0``).
        vertices: ``(V, 3)`` camera-frame vertices of the triangles, in the points' unit.
        faces: ``(F, 3)`` integer vertex indices of the triangles.
        tolerance: a length ``>= 0``, or ``(P,)`` lengths, one per point.

    Returns:
        ``(P,)`` bool, ``True`` where the point is hidden.

    Raises:
        ValueError: on shapes, non-finite values, points with ``z <= 0``, out-of-range face indices
            or a negative tolerance.

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
    z = vertices[:, 2]
    front = z > 0
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    faces_front = front[a] & front[b] & front[c]
    crossing = (front[a] | front[b] | front[c]) & ~faces_front  # straddles the camera plane: no projected box
    front_index = np.flatnonzero(faces_front)
    a, b, c = a[front_index], b[front_index], c[front_index]
    depth = np.where(front, z, 1.0)
    bounds = []
    for image in (vertices[:, 0] / depth, vertices[:, 1] / depth):  # per axis: 3-wide reductions are slow
        ia, ib, ic = image[a], image[b], image[c]
        bounds.append((np.minimum(np.minimum(ia, ib), ic), np.maximum(np.maximum(ia, ib), ic)))
    low = np.stack([bounds[0][0], bounds[1][0]], axis=1)
    high = np.stack([bounds[0][1], bounds[1][1]], axis=1)
    target = points[:, :2] / points[:, 2:3]

    extent = np.maximum(high[:, 0] - low[:, 0], high[:, 1] - low[:, 1])
    cell = 2.0 * float(np.median(extent)) if len(extent) else 1.0
    span = float((target.max(0) - target.min(0)).max())
    cell = max(cell, span / (_MAX_CELLS - 4), 1e-12)
    large = extent >= cell
    # small boxes live in at most 2 x 2 cells, starting at the cell of their low corner
    origin = target.min(0) - cell
    size = int(np.floor(span / cell)) + 3
    start = np.floor((low - origin) / cell).astype(np.int64)
    wanted = np.zeros((size, size), dtype=bool)
    cells = np.floor((target - origin) / cell).astype(np.int64)
    for du in (0, 1):
        for dv in (0, 1):
            wanted[cells[:, 0] - du, cells[:, 1] - dv] = True
    on_grid = ~large & (start[:, 0] >= 0) & (start[:, 1] >= 0) & (start[:, 0] < size) & (start[:, 1] < size)
    near = np.zeros(len(front_index), dtype=bool)
    near[on_grid] = wanted[start[on_grid, 0], start[on_grid, 1]]
    candidates = np.flatnonzero(near | large)

    # (point, triangle) pairs whose box holds the point's image, plus every triangle crossing z = 0
    slack = 1e-9 * max(1.0, float(np.abs(target).max()))
    inside = np.ones((len(candidates), len(points)), dtype=bool)
    for k in (0, 1):  # per axis: 2-wide reductions are slow
        inside &= (low[candidates, k, None] - slack <= target[:, k]) & (target[:, k] <= high[candidates, k, None] + slack)
    pair_triangle, pair_point = np.nonzero(inside)
    pair_triangle = front_index[candidates[pair_triangle]]
    straddling = np.flatnonzero(crossing)
    if len(straddling):
        pair_point = np.concatenate([pair_point, np.repeat(np.arange(len(points)), len(straddling))])
        pair_triangle = np.concatenate([pair_triangle, np.tile(straddling, len(points))])
    if len(pair_point) == 0:
        return blocked
    hit_at = _segment_hits(points[pair_point], vertices[faces[pair_triangle]])
    limit = 1.0 - tolerance[pair_point] / np.linalg.norm(points[pair_point], axis=1)
    hit = hit_at < limit
    blocked[pair_point[hit]] = True
    return blocked


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
    arrays = {}
    for name, value in (("points", points), ("vertices", vertices)):
        array = np.asarray(value)
        if array.ndim != 2 or array.shape[1] != 3 or not np.issubdtype(array.dtype, np.number):
            raise ValueError(f"{name}: expected a numeric array of shape (N, 3), got shape {array.shape}")
        array = array.astype(np.float64)
        if not np.isfinite(array).all():
            raise ValueError(f"{name}: expected finite values, got NaN or infinity")
        arrays[name] = array
    points, vertices = arrays["points"], arrays["vertices"]
    if (points[:, 2] <= 0).any():
        raise ValueError(f"points: expected points in front of the camera (z > 0), got z = {points[:, 2].min():g}")
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"faces: expected an integer array of shape (F, 3), got {faces.dtype} of shape {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(f"faces: expected indices in [0, {len(vertices)}), got {faces.min()}..{faces.max()}")
    tolerance = np.asarray(tolerance)
    if tolerance.shape not in ((), (len(points),)) or not np.issubdtype(tolerance.dtype, np.number):
        raise ValueError(f"tolerance: expected a number or shape ({len(points)},), got shape {tolerance.shape}")
    tolerance = np.broadcast_to(tolerance.astype(np.float64), (len(points),))
    if not (np.isfinite(tolerance) & (tolerance >= 0)).all():
        raise ValueError("tolerance: expected finite lengths >= 0")
    return points, vertices, faces.astype(np.int64), tolerance
