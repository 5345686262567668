r"""Exact point-to-surface queries on triangle meshes (numpy, float64, no spatial-index package).

:func:`closest_points_on_mesh` returns, for each query, the closest point on the triangles (not
the closest vertex). Candidates come from a :class:`scipy.spatial.cKDTree` on the triangle
centroids: the ``k`` nearest centroids are tested exactly (Ericson's closest point on a
triangle); the answer is certified when its distance :math:`D` satisfies
:math:`D \le d_k - r_{\max}` (:math:`d_k` the k-th centroid distance, :math:`r_{\max}` the largest
centroid-to-corner distance, so no untested triangle can come closer). Uncertified queries test
every triangle whose centroid lies within :math:`D + r_{\max}`, which is exact.

:func:`intersect_lines_along_z` intersects the line through each query parallel to the z axis
with the mesh, through a uniform grid over the triangles' xy bounding boxes.
"""

from __future__ import annotations

import numpy as np

from facenormals.core.check import check_integer

__all__ = ["closest_points_on_mesh", "closest_points_on_triangles", "intersect_lines_along_z"]


def _check_query(points: object, vertices: object, faces: object) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Queries ``(Q, 3)``, vertices ``(N, 3)`` (finite, as float64) and triangles ``(F, 3)``, F >= 1, indexing them."""
    arrays = {}
    for name, value in (("points", points), ("vertices", vertices)):
        x = np.asarray(value)
        if x.ndim != 2 or x.shape[1] != 3:
            raise ValueError(f"{name}: expected shape (N, 3), got {tuple(x.shape)}")
        if not np.issubdtype(x.dtype, np.number) or np.iscomplexobj(x):
            raise ValueError(f"{name}: expected real numbers, got dtype {x.dtype}")
        x = x.astype(np.float64, copy=False)
        if not np.isfinite(x).all():
            raise ValueError(f"{name}: expected finite values, got NaN or infinite entries")
        arrays[name] = x
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise ValueError(f"faces: expected shape (F, 3) with F >= 1, got {tuple(f.shape)}")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces: expected integer vertex indices, got dtype {f.dtype}")
    n = len(arrays["vertices"])
    if int(f.min()) < 0 or int(f.max()) >= n:
        raise ValueError(f"faces: expected vertex indices in [0, {n}), got values in [{int(f.min())}, {int(f.max())}]")
    return arrays["points"], arrays["vertices"], f


def closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest point to ``p[i]`` on triangle ``(a[i], b[i], c[i])`` (all ``(K, 3)``), Ericson §5.1.5.

    Degenerate triangles (collinear or coincident corners, zero area) are treated as the union of
    their three edges: the closest point of the three segments.

    Example:
        >>> tri = [np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]]), np.array([[0.0, 1, 0]])]
        >>> closest_points_on_triangles(np.array([[0.2, 0.2, 5.0]]), *tri)
        array([[0.2, 0.2, 0. ]])
    """

    def dot(u, v):
        return np.einsum("ij,ij->i", u, v)

    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        out = a + ab * (vb * denom)[:, None] + ac * (vc * denom)[:, None]  # interior
        w_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        region = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        out = np.where(region[:, None], b + (c - b) * w_bc[:, None], out)
        w_ac = d2 / (d2 - d6)
        region = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        out = np.where(region[:, None], a + ac * w_ac[:, None], out)
        region = (d6 >= 0) & (d5 <= d6)
        out = np.where(region[:, None], c, out)
        v_ab = d1 / (d1 - d3)
        region = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        out = np.where(region[:, None], a + ab * v_ab[:, None], out)
        region = (d3 >= 0) & (d4 <= d3)
        out = np.where(region[:, None], b, out)
        region = (d1 <= 0) & (d2 <= 0)
        out = np.where(region[:, None], a, out)
    # Near-zero area (sin² of the angle at a below 1e-8) or a non-finite result: Ericson's regions
    # assume a proper triangle and lose their precision on slivers (up to tens of mm too far at
    # sin² ~ 1e-22), never coming out too near: keep the nearer of his point and the best edge point.
    area2 = np.square(np.cross(ab, ac)).sum(1)
    thin = (area2 <= 1e-8 * dot(ab, ab) * dot(ac, ac)) | ~np.isfinite(out).all(axis=1)
    if thin.any():
        pf, af, bf, cf = p[thin], a[thin], b[thin], c[thin]
        candidates = np.stack([_closest_on_segments(pf, af, bf), _closest_on_segments(pf, bf, cf),
                               _closest_on_segments(pf, cf, af), out[thin]], axis=1)
        distance = ((candidates - pf[:, None]) ** 2).sum(-1)
        best = np.argmin(np.where(np.isfinite(distance), distance, np.inf), axis=1)
        out[thin] = candidates[np.arange(len(best)), best]
    return out


def _closest_on_segments(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Closest point to ``p[i]`` on the segment ``a[i]b[i]`` (a point where ``a[i] == b[i]``)."""
    ab = b - a
    length2 = np.einsum("ij,ij->i", ab, ab)
    t = np.einsum("ij,ij->i", p - a, ab) / np.where(length2 > 0, length2, 1.0)
    return a + ab * np.clip(t, 0.0, 1.0)[:, None]


def _best_per_query(query: np.ndarray, dist2: np.ndarray, num_queries: int) -> np.ndarray:
    """Position (into ``query``/``dist2``) of the smallest ``dist2`` of each query index."""
    order = np.lexsort((dist2, query))
    first = np.ones(len(order), dtype=bool)
    first[1:] = query[order][1:] != query[order][:-1]
    return order[first]


def _exact_subset(points, tri, q, f):
    """Closest points and squared distances of the query/triangle pairs ``(q[i], f[i])``."""
    close = closest_points_on_triangles(points[q], tri[f, 0], tri[f, 1], tri[f, 2])
    return close, ((close - points[q]) ** 2).sum(1)


def closest_points_on_mesh(
    points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, k: int = 16
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact closest points on a triangle mesh.

    Args:
        points: ``(Q, 3)`` queries.
        vertices: ``(N, 3)`` mesh vertices.
        faces: ``(F, 3)`` triangles (F ≥ 1).
        k: nearest centroids tested before the certification step.

    Returns:
        ``(closest (Q, 3), distance (Q,), triangle (Q,))``.

    Raises:
        ValueError: naming ``points``, ``vertices`` or ``faces`` when one is badly shaped, not finite,
            or (faces) not integer indices of the vertices.

    Example:
        >>> v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
        >>> queries = np.array([[0.5, 0.5, 2.0], [2.0, 2.0, 0.0]])
        >>> q, d, f = closest_points_on_mesh(queries, v, np.array([[0, 1, 2], [1, 3, 2]]))
        >>> q, d.round(4)
        (array([[0.5, 0.5, 0. ],
               [1. , 1. , 0. ]]), array([2.    , 1.4142]))
    """
    from scipy.spatial import cKDTree

    points, vertices, faces = _check_query(points, vertices, faces)
    k = check_integer(k, "k", minimum=1)
    tri = vertices[faces]
    centroid = tri.mean(axis=1)
    radius = np.sqrt(((tri - centroid[:, None]) ** 2).sum(-1)).max(axis=1)
    num_q, num_f = len(points), len(tri)
    k = min(k, num_f)
    tree = cKDTree(centroid)
    cdist, cand = tree.query(points, k=k)
    cdist, cand = cdist.reshape(num_q, k), cand.reshape(num_q, k)
    flat_f = cand.reshape(-1)
    close, dist2 = _exact_subset(points, tri, np.repeat(np.arange(num_q), k), flat_f)
    pick = np.arange(num_q) * k + dist2.reshape(num_q, k).argmin(axis=1)
    out, out_d2, out_f = close[pick], dist2[pick], flat_f[pick]
    if k == num_f:
        return out, np.sqrt(out_d2), out_f
    margin = 1e-9 * (1.0 + float(radius.max()))
    unsure = np.nonzero(np.sqrt(out_d2) > cdist[:, -1] - radius.max() - margin)[0]
    if len(unsure) == 0:
        return out, np.sqrt(out_d2), out_f
    # Refine by classes of triangle size (radius <= r0, <= 2 r0, <= 4 r0, ...): each class
    # certifies with its own largest radius, so a few large triangles do not widen every search.
    r0 = float(np.median(radius)) or float(radius.max()) or 1.0
    level = np.ceil(np.log2(np.maximum(radius / r0, 1.0))).astype(np.int64)
    for c in np.unique(level):
        members = np.nonzero(level == c)[0]
        r_c = float(radius[members].max()) + margin
        sub = cKDTree(centroid[members])
        d1, _ = sub.query(points[unsure], k=1)
        need = unsure[np.sqrt(out_d2[unsure]) > d1 - r_c]
        if len(need) == 0:
            continue
        lists = sub.query_ball_point(points[need], np.sqrt(out_d2[need]) + r_c)
        lengths = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
        if lengths.sum() == 0:
            continue
        q2 = np.repeat(need, lengths)
        f2 = members[np.concatenate([np.asarray(x, dtype=np.int64) for x in lists])]
        c2, d2 = _exact_subset(points, tri, q2, f2)
        sel = _best_per_query(q2, d2, num_q)
        better = d2[sel] < out_d2[q2[sel]]
        sel, who = sel[better], q2[sel[better]]
        out[who], out_d2[who], out_f[who] = c2[sel], d2[sel], f2[sel]
    return out, np.sqrt(out_d2), out_f


def _pairs_in_cells(query_xy: np.ndarray, lo: np.ndarray, hi: np.ndarray, cell: float,
                    members: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(query, triangle)`` pairs whose xy cells of side ``cell`` match: each triangle (bounding box
    ``lo``–``hi``, index ``members``) is entered in the cells its box covers, each query in its own."""
    origin = lo.min(axis=0)
    shape = np.floor((hi.max(axis=0) - origin) / cell).astype(np.int64) + 1
    c0 = np.floor((lo - origin) / cell).astype(np.int64)
    span = np.floor((hi - origin) / cell).astype(np.int64) - c0 + 1
    count = span[:, 0] * span[:, 1]
    tri_id = np.repeat(np.arange(len(lo)), count)
    offset = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    key = (c0[tri_id, 0] + offset // span[tri_id, 1]) * shape[1] + c0[tri_id, 1] + offset % span[tri_id, 1]
    order = np.argsort(key, kind="stable")
    key, tri_id = key[order], tri_id[order]
    qc = np.floor((query_xy - origin) / cell).astype(np.int64)
    inside = (qc >= 0).all(axis=1) & (qc < shape).all(axis=1)
    qkey = np.where(inside, qc[:, 0] * shape[1] + qc[:, 1], -1)
    start = np.searchsorted(key, qkey, side="left")
    n = np.where(inside, np.searchsorted(key, qkey, side="right"), start) - start
    q = np.repeat(np.arange(len(query_xy)), n)
    return q, members[tri_id[np.repeat(start, n) + np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)]]


def intersect_lines_along_z(
    points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, front_facing: bool = False
) -> np.ndarray:
    """z of the mesh point on the line through each query parallel to z, nearest to the query's z.

    The line is infinite in both directions; among its intersections with the triangles the one
    closest to the query's own z is returned, NaN where the line misses the mesh. Triangles
    seen edge-on (zero area in xy) are skipped; edges and corners count as hits.

    Args:
        points: ``(Q, 3)`` queries.
        vertices: ``(N, 3)``; faces: ``(F, 3)``.
        front_facing: only intersect triangles facing a viewer that looks along +z, i.e. whose
            outward normal (counter-clockwise winding) has a negative z component.

    Returns:
        ``(Q,)`` z values.

    Example:
        >>> v = np.array([[0.0, 0, 5], [1, 0, 5], [0, 1, 6]])
        >>> intersect_lines_along_z(np.array([[0.25, 0.5, 0.0], [3.0, 3.0, 0.0]]), v, np.array([[0, 1, 2]]))
        array([5.5, nan])
    """
    points, vertices, faces = _check_query(points, vertices, faces)
    tri = vertices[faces]
    xy = tri[..., :2]
    lo, hi = xy.min(axis=1), xy.max(axis=1)
    num_q = len(points)
    result = np.full(num_q, np.nan)
    extent = (hi - lo).max(axis=1)
    positive = extent[extent > 0]
    base = float(np.median(positive)) if len(positive) else 1.0
    # Classes of triangle size (extent <= 2 base, <= 4 base, <= 8 base, ...), each on a grid of a quarter
    # of its largest extent: a triangle enters at most 25 cells, however much larger than the median.
    level = np.ceil(np.log2(np.maximum(extent / base, 2.0))).astype(np.int64)
    pairs = []
    for lv in np.unique(level):  # at least one: _check_query refuses an empty face list
        members = np.flatnonzero(level == lv)
        pairs.append(_pairs_in_cells(points[:, :2], lo[members], hi[members], base * 2.0 ** (lv - 2), members))
    q, f = (np.concatenate(column) for column in zip(*pairs))
    a, b, c = tri[f, 0], tri[f, 1], tri[f, 2]
    p = points[q]
    e1, e2, d = (b - a)[:, :2], (c - a)[:, :2], (p - a)[:, :2]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    scale = np.abs(e1).sum(1) * np.abs(e2).sum(1)
    ok = np.abs(det) > 1e-12 * np.maximum(scale, 1e-300)
    if front_facing:
        ok &= det < 0  # det is the z component of (b - a) x (c - a)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (d[:, 0] * e2[:, 1] - d[:, 1] * e2[:, 0]) / det
        v = (e1[:, 0] * d[:, 1] - e1[:, 1] * d[:, 0]) / det
        eps = 1e-9
        hit = ok & (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps)  # inf + -inf where det = 0 (not ok)
    q, a, b, c, u, v = q[hit], a[hit], b[hit], c[hit], u[hit], v[hit]
    z = a[:, 2] + u * (b[:, 2] - a[:, 2]) + v * (c[:, 2] - a[:, 2])
    if len(q):
        sel = _best_per_query(q, np.abs(z - points[q, 2]), num_q)
        result[q[sel]] = z[sel]
    return result
