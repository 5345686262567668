"""Small NumPy mesh builders for the synthetic scenes: primitives, ring strips, boundary loops.

Faces are counter-clockwise seen from outside (``docs/conventions.md``), so that the face normal
:math:`(v_1 - v_0) \\times (v_2 - v_0)` points outwards.
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.sparse

__all__ = [
    "boundary_loops",
    "box_mesh",
    "cylinder_mesh",
    "face_normals",
    "neighbour_average",
    "ring_strip",
    "sphere_mesh",
    "smooth_vertex_normals",
]


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unnormalised face normals ``(F, 3)`` (twice the area along the normal)."""
    p0, p1, p2 = (vertices[faces[:, k]] for k in range(3))
    return np.cross(p1 - p0, p2 - p0)


def smooth_vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals ``(N, 3)`` of a small mesh (float32)."""
    fn = face_normals(vertices.astype(np.float64), faces)
    out = np.zeros((vertices.shape[0], 3))
    for k in range(3):
        np.add.at(out, faces[:, k], fn)
    out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)
    return out.astype(np.float32)


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Ordered boundary loops of a manifold triangle mesh, each a vertex index array.

    A boundary edge belongs to one face only; each loop follows the faces' winding, so for an
    outward-wound mesh the hole is traversed clockwise seen from outside.
    """
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = np.sort(edges, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = edges[counts[inverse.ravel()] == 1]
    following = {int(a): int(b) for a, b in boundary}
    loops, seen = [], set()
    for start in following:
        if start in seen:
            continue
        loop, v = [], start
        while v not in seen:
            seen.add(v)
            loop.append(v)
            v = following[v]
        loops.append(np.asarray(loop, dtype=np.int64))
    return loops


def neighbour_average(faces: np.ndarray, num_vertices: int) -> scipy.sparse.csr_matrix:
    """Row-stochastic ``(N, N)`` matrix averaging each vertex's one-ring neighbours."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    rows = np.concatenate([edges[:, 0], edges[:, 1]])
    cols = np.concatenate([edges[:, 1], edges[:, 0]])
    adjacency = scipy.sparse.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(num_vertices, num_vertices))
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    degree[degree == 0] = 1.0
    return (scipy.sparse.diags(1.0 / degree) @ adjacency).tocsr()


def ring_strip(first: np.ndarray, second: np.ndarray, closed: bool = True) -> np.ndarray:
    """Triangles ``(2K, 3)`` joining two rings of vertex indices of equal length ``K``."""
    k = len(first)
    i = np.arange(k if closed else k - 1)
    j = (i + 1) % k
    upper = np.stack([first[i], first[j], second[j]], axis=1)
    lower = np.stack([first[i], second[j], second[i]], axis=1)
    return np.concatenate([upper, lower]).astype(np.int64)


@functools.lru_cache(maxsize=16)
def _sphere_topology(rings: int, segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Faces and ring index of a UV sphere with ``rings`` latitude rings (poles included)."""
    inner = rings - 2
    index = 1 + np.arange(inner * segments).reshape(inner, segments)
    last = inner * segments + 1
    s = np.arange(segments)
    faces = [np.stack([np.zeros(segments, np.int64), index[0, s], index[0, (s + 1) % segments]], 1)]
    faces += [ring_strip(index[r], index[r + 1]) for r in range(inner - 1)]
    faces.append(np.stack([np.full(segments, last), index[-1, (s + 1) % segments], index[-1, s]], 1))
    faces = np.concatenate(faces).astype(np.int64)
    ring = np.concatenate([[0], np.repeat(np.arange(1, inner + 1), segments), [inner + 1]])
    vertices = _sphere_vertices(np.linspace(0.0, np.pi, rings), segments)
    flip = np.sum(face_normals(vertices, faces) * vertices[faces].mean(1), axis=1) < 0  # orient outwards
    faces[flip] = faces[flip][:, ::-1]
    faces.setflags(write=False)
    ring.setflags(write=False)
    return faces, ring


def _sphere_vertices(polar_angles: np.ndarray, segments: int) -> np.ndarray:
    inner = np.asarray(polar_angles, dtype=np.float64)[1:-1]
    phi = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    st, ct = np.sin(inner)[:, None], np.cos(inner)[:, None]
    rings = np.stack([st * np.cos(phi), st * np.sin(phi), ct * np.ones_like(phi)], -1)
    return np.concatenate([[[0.0, 0.0, 1.0]], rings.reshape(-1, 3), [[0.0, 0.0, -1.0]]])


def sphere_mesh(polar_angles: np.ndarray, segments: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A unit sphere around the +z axis with latitude rings at ``polar_angles`` (increasing, radians
    from +z, starting at 0 and ending at π).

    Returns ``(vertices, faces, ring)``: one vertex per pole, ``segments`` per inner ring, and
    the ring index of every vertex (0 = the +z pole).
    """
    faces, ring = _sphere_topology(len(polar_angles), int(segments))
    return _sphere_vertices(polar_angles, segments), faces, ring


def box_mesh() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A unit cube ``[-1, 1]^3`` with flat faces: ``(vertices (24, 3), faces (12, 3), normals (24, 3))``."""
    vertices, faces, normals = [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = np.zeros(3)
            n[axis] = sign
            u, w = np.eye(3)[(axis + 1) % 3], np.eye(3)[(axis + 2) % 3]
            corners = [n + a * u + b * w for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
            base = len(vertices)
            vertices.extend(corners)
            normals.extend([n] * 4)
            quad = np.array([[base, base + 1, base + 2], [base, base + 2, base + 3]])
            if np.dot(np.cross(u, w), n) < 0:
                quad = quad[:, ::-1]
            faces.extend(quad)
    return np.asarray(vertices), np.asarray(faces, dtype=np.int64), np.asarray(normals)


def cylinder_mesh(segments: int = 24) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A capped unit cylinder (radius 1, z in ``[-1, 1]``) with flat caps: ``(vertices, faces, normals)``."""
    phi = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    circle = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], 1)
    bottom, top = circle + [0, 0, -1.0], circle + [0, 0, 1.0]
    side_v = np.concatenate([bottom, top])
    side_n = np.concatenate([circle, circle])
    s = np.arange(segments)
    side_f = ring_strip(s, s + segments)
    caps_v = np.concatenate([[[0, 0, -1.0]], bottom, [[0, 0, 1.0]], top])
    caps_n = np.concatenate([np.tile([0, 0, -1.0], (segments + 1, 1)), np.tile([0, 0, 1.0], (segments + 1, 1))])
    o = 2 * segments
    bottom_f = np.stack([np.full(segments, o), o + 1 + (s + 1) % segments, o + 1 + s], 1)
    o2 = o + segments + 1
    top_f = np.stack([np.full(segments, o2), o2 + 1 + s, o2 + 1 + (s + 1) % segments], 1)
    vertices = np.concatenate([side_v, caps_v])
    normals = np.concatenate([side_n, caps_n])
    faces = np.concatenate([side_f, bottom_f, top_f]).astype(np.int64)
    fn = face_normals(vertices, faces)
    flip = np.sum(fn * normals[faces].mean(1), axis=1) < 0
    faces[flip] = faces[flip][:, ::-1]
    return vertices, faces, normals
