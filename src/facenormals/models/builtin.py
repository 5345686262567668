"""A procedural head model that ships with the package: no download, no data files.

The surface is a subdivided icosphere pushed out to a head-shaped radius function, with eye sockets
and eyeballs, brow ridges, cheekbones, a nose with alae, lips, a chin and ears added as smooth
radial displacements. Every feature is driven by an anthropometric parameter in millimetres; the
shape components are the derivatives of the surface with respect to these parameters (central
differences over ±1σ), so coefficient ``y_k`` is the deviation of parameter ``k`` from its mean in mm and
``shape_std`` holds its standard deviation. The model is deterministic and built in a fraction of
a second. It is a stand-in for a scanned model (ICT-FaceKit), not a replacement.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch

from facenormals.models.morphable import FACE_CROP_RADIUS_MM, MorphableModel, check_model_dtype

__all__ = ["BUILTIN_PARAMETERS", "builtin_head_model", "builtin_head_surface"]


@dataclass(frozen=True)
class HeadParameter:
    name: str
    mean: float
    std: float
    description: str


#: The anthropometric parameters of the built-in head: name, mean and standard deviation in mm.
BUILTIN_PARAMETERS: tuple[HeadParameter, ...] = (
    HeadParameter("head_length", 192.0, 7.0, "glabella to opisthocranion"),
    HeadParameter("head_breadth", 152.0, 6.0, "maximum breadth of the cranium"),
    HeadParameter("cranium_height", 118.0, 7.0, "eye level to vertex"),
    HeadParameter("face_height", 118.0, 6.0, "eye level to menton"),
    HeadParameter("jaw_width", 108.0, 6.0, "bigonial breadth"),
    HeadParameter("cheekbone_width", 132.0, 5.0, "bizygomatic breadth"),
    HeadParameter("forehead_slope", 10.0, 4.0, "backward slope of the forehead"),
    HeadParameter("occiput", 8.0, 4.0, "prominence of the back of the head"),
    HeadParameter("nose_length", 50.0, 4.0, "nasion to nose tip, vertically"),
    HeadParameter("nose_projection", 22.0, 3.0, "protrusion of the nose tip"),
    HeadParameter("nose_width", 34.0, 2.5, "alar breadth"),
    HeadParameter("nasal_bridge", 6.0, 2.0, "height of the nasal bridge"),
    HeadParameter("eye_separation", 64.0, 3.0, "distance between the pupils"),
    HeadParameter("eye_depth", 9.0, 2.0, "depth of the eye sockets"),
    HeadParameter("brow_ridge", 4.0, 1.5, "prominence of the brow ridges"),
    HeadParameter("mouth_width", 50.0, 3.5, "distance between the mouth corners"),
    HeadParameter("lip_thickness", 5.0, 1.5, "protrusion of the lips"),
    HeadParameter("mouth_level", 74.0, 3.0, "eye level to the mouth line"),
    HeadParameter("chin_projection", 6.0, 2.5, "protrusion of the chin"),
    HeadParameter("cheek_fullness", 4.0, 2.0, "fullness of the cheeks"),
    HeadParameter("ear_length", 62.0, 4.0, "superaurale to subaurale"),
    HeadParameter("ear_protrusion", 20.0, 4.0, "how far the ear stands out"),
    HeadParameter("ear_level", 20.0, 3.0, "ear centre below eye level"),
    HeadParameter("ear_position", 8.0, 3.0, "ear centre behind the head's centre"),
)

_SUBDIVISIONS = 5  # 10,242 vertices, 20,480 triangles


def _gauss(*terms: tuple[np.ndarray, float, float]) -> np.ndarray:
    """exp(-Σ (x - c)² / 2s²) for (x, c, s) terms."""
    total = np.zeros_like(terms[0][0])
    for x, c, s in terms:
        total = total + (x - c) ** 2 / (2.0 * s * s)
    return np.exp(-total)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    t = np.clip(x, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _icosphere(subdivisions: int = _SUBDIVISIONS) -> tuple[np.ndarray, np.ndarray]:
    """The unit icosphere: vertices ``(V, 3)`` float64 and outward faces ``(F, 3)`` int64.

    Each step splits every triangle into four at its edge midpoints and pushes the vertices back
    onto the sphere. The vertex order is part of the model (saved meshes, vertex indices), so it is
    fixed here rather than left to a library: the midpoints are appended in the order of their
    edges sorted by (larger, smaller) vertex index, which is also trimesh 4-5's order, so
    ``trimesh.creation.icosphere`` gives the same array (tested) without its 0.5 s import.
    """
    phi = (1.0 + np.sqrt(5.0)) / 2.0
    a, b = 1.0 / np.sqrt(1.0 + phi * phi), phi / np.sqrt(1.0 + phi * phi)
    vertices = np.array([[-a, b, 0], [a, b, 0], [-a, -b, 0], [a, -b, 0], [0, -a, b], [0, a, b],
                         [0, -a, -b], [0, a, -b], [b, 0, -a], [b, 0, a], [-b, 0, -a], [-b, 0, a]])
    faces = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                      [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                      [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    for _ in range(subdivisions):
        count = len(vertices)
        edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        _, first, inverse = np.unique(edges[:, 1] * count + edges[:, 0], return_index=True, return_inverse=True)
        mid = inverse.reshape(-1, 3) + count  # the midpoints of each face's edges (01, 12, 20)
        corner = faces.T
        faces = np.stack([corner[0], mid[:, 0], mid[:, 2], mid[:, 0], corner[1], mid[:, 1],
                          mid[:, 2], mid[:, 1], corner[2], mid[:, 0], mid[:, 1], mid[:, 2]], axis=1).reshape(-1, 3)
        vertices = np.vstack((vertices, vertices[edges[first]].mean(axis=1)))
        norm = np.sqrt(np.dot(vertices**2, [1.0, 1.0, 1.0]))[:, None]
        vertices = vertices + (vertices / norm) * (1.0 - norm)
    return vertices, faces


def _base_surface(directions: np.ndarray, p: dict[str, float]) -> np.ndarray:
    """The skull-like base surface before facial features, ``(N, 3)`` mm."""
    dx, dy, dz = directions.T
    up, fwd = -dy, -dz  # anatomical up and forward
    # Base: an egg-shaped ellipsoid, narrower at the jaw, with a sloping forehead and an occiput.
    half_breadth = 0.5 * p["head_breadth"]
    jaw = 0.5 * p["jaw_width"] / half_breadth
    taper = 1.0 - (1.0 - jaw) * _smoothstep(-up / 0.85)
    ax = half_breadth * taper
    a_up = np.where(up > 0, p["cranium_height"], p["face_height"])
    a_fwd = np.where(fwd > 0, 0.5 * p["head_length"] - 0.1 * p["forehead_slope"] * np.clip(up, 0, 1) * 4,
                     0.5 * p["head_length"] + p["occiput"] * _gauss((up, 0.2, 0.35)))
    a_fwd = np.where(fwd > 0, a_fwd * (1.0 - 0.12 * _smoothstep(-up / 0.9)), a_fwd)  # chin recedes less than jaw
    e = 2.4  # a superellipsoid: boxier than an ellipsoid, like a skull
    radius = ((np.abs(dx) / ax) ** e + (np.abs(up) / a_up) ** e + (np.abs(fwd) / a_fwd) ** e) ** (-1.0 / e)
    return radius[:, None] * directions


def builtin_head_surface(directions: np.ndarray, params: np.ndarray, anchor: np.ndarray | None = None) -> np.ndarray:
    """Head surface points for unit ``directions`` ``(N, 3)`` (model frame) and parameter values ``(P,)``.

    Facial features are radial displacements placed by the coordinates of ``anchor`` (default: this
    head's own base surface). The model uses the mean head's base as the anchor, so that changing
    the skull's proportions scales the features' surroundings without sliding the features.

    Returns ``(N, 3)`` points in mm in the model frame (x to image right, y down, face along −z).
    """
    p = {spec.name: float(v) for spec, v in zip(BUILTIN_PARAMETERS, params)}
    base = _base_surface(directions, p)
    if anchor is None:
        anchor = base
    x, u, f = anchor[:, 0], -anchor[:, 1], -anchor[:, 2]

    front = _smoothstep(f / 40.0)  # features only on the front of the face
    disp = np.zeros_like(x)
    # Eyes: sockets, eyeballs and brow ridges.
    eye_x = 0.5 * p["eye_separation"]
    for side in (-1.0, 1.0):
        disp += -p["eye_depth"] * _gauss((x, side * eye_x, 15.0), (u, 0.0, 11.0))
        disp += 0.8 * p["eye_depth"] * _gauss((x, side * eye_x, 8.5), (u, 0.0, 5.5))
        disp += p["brow_ridge"] * _gauss((x, side * (eye_x - 2.0), 16.0), (u, 16.0, 5.0))
        cheekbone = 5.0 + 0.5 * (p["cheekbone_width"] - 132.0)
        disp += cheekbone * _gauss((x, side * 50.0, 11.0), (u, -23.0, 10.0))
        disp += p["cheek_fullness"] * _gauss((x, side * 40.0, 14.0), (u, -55.0, 14.0))
    # Nose: a ridge from the bridge to the tip, alae and the columella.
    tip_u = -p["nose_length"] + 8.0
    along = np.clip((8.0 - u) / (8.0 - tip_u), 0.0, 1.0)  # 0 at the bridge, 1 at the tip
    below_tip = np.exp(-np.clip(tip_u - u, 0.0, None) ** 2 / (2.0 * 6.0**2))
    ridge_height = (p["nasal_bridge"] + (p["nose_projection"] - p["nasal_bridge"]) * along**1.5) * below_tip
    ridge_width = 6.0 + 0.25 * p["nose_width"] * along
    disp += ridge_height * _gauss((x, 0.0, ridge_width)) * (u < 14.0) * _smoothstep((14.0 - u) / 6.0)
    for side in (-1.0, 1.0):
        disp += 7.0 * _gauss((x, side * 0.5 * p["nose_width"] * 0.75, 5.0), (u, tip_u + 3.0, 5.0))
    # Mouth: lips either side of the mouth line, narrowing towards the corners.
    mouth_u = -p["mouth_level"]
    width = _gauss((x, 0.0, 0.42 * p["mouth_width"]))
    disp += p["lip_thickness"] * width * _gauss((u, mouth_u + 5.0, 3.5))
    disp += p["lip_thickness"] * width * _gauss((u, mouth_u - 6.0, 4.0))
    disp += -3.0 * width * _gauss((u, mouth_u, 1.4))
    disp += -3.0 * _gauss((x, 0.0, 18.0), (u, mouth_u - 16.0, 4.0))  # labiomental fold
    # Chin.
    disp += p["chin_projection"] * _gauss((x, 0.0, 16.0), (u, -p["face_height"] + 18.0, 10.0))
    disp = disp * front

    # Ears: a cupped flap with a rim, standing out sideways behind the cheek.
    ear_u = -p["ear_level"]
    ear_f = -p["ear_position"]
    half_len = 0.5 * p["ear_length"]
    half_wid = 0.55 * half_len
    half_breadth = 0.5 * p["head_breadth"]
    lateral = _smoothstep((np.abs(x) - 0.6 * half_breadth) / (0.2 * half_breadth))
    rho = np.sqrt(((u - ear_u) / half_len) ** 2 + ((f - ear_f) / half_wid) ** 2)
    flap = 1.0 / (1.0 + np.exp((rho - 0.95) / 0.12))
    rim = _gauss((rho, 0.8, 0.12))
    bowl = _gauss((rho, 0.25, 0.3))
    tilt = 0.75 + 0.25 * np.clip(-(f - ear_f) / half_wid, -1.0, 1.0)  # the back edge stands out more
    ear = p["ear_protrusion"] * tilt * (flap + 0.25 * rim - 0.45 * bowl * flap)
    disp += ear * lateral
    return base + disp[:, None] * directions


@lru_cache(maxsize=1)
def _build() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    directions, faces = _icosphere()
    mean_params = np.array([spec.mean for spec in BUILTIN_PARAMETERS])
    std = np.array([spec.std for spec in BUILTIN_PARAMETERS])
    anchor = _base_surface(directions, {spec.name: spec.mean for spec in BUILTIN_PARAMETERS})
    mean = builtin_head_surface(directions, mean_params, anchor)
    basis = np.empty((len(BUILTIN_PARAMETERS), *mean.shape))
    for k in range(len(BUILTIN_PARAMETERS)):
        # Secant over ±1σ rather than the derivative at the mean: moving a sharp feature (an ear's
        # rim, the mouth line) then blends two bounded positions instead of producing spikes.
        step = np.zeros_like(mean_params)
        step[k] = std[k]
        plus = builtin_head_surface(directions, mean_params + step, anchor)
        minus = builtin_head_surface(directions, mean_params - step, anchor)
        basis[k] = (plus - minus) / (2.0 * step[k])
    return directions, faces, mean, basis, std


def _face_region(mean: np.ndarray) -> np.ndarray:
    """The evaluation face region: the front of the head within 95 mm of the nose tip (as for ICT)."""
    fwd = -mean[:, 2]
    nose = mean[np.argmax(np.where(np.abs(mean[:, 0]) < 0.5, fwd, -np.inf))]
    return (np.linalg.norm(mean - nose, axis=1) < FACE_CROP_RADIUS_MM) & (fwd > 0.0)


def builtin_head_model(dtype: torch.dtype = torch.float32) -> MorphableModel:
    """The built-in procedural head: 10,242 vertices, 24 shape components in mm, the 24 landmarks.

    Example:
        >>> model = builtin_head_model()
        >>> model.num_vertices, model.num_shape
        (10242, 24)
    """
    from facenormals.models.landmarks import builtin_landmark_indices

    check_model_dtype(dtype)
    directions, faces, mean, basis, std = _build()
    return MorphableModel(  # copies: the cached arrays must not become the buffers a caller may edit
        torch.tensor(mean, dtype=dtype),
        torch.tensor(basis, dtype=dtype),
        torch.tensor(faces),
        shape_std=torch.tensor(std, dtype=dtype),
        landmarks=builtin_landmark_indices(mean, BUILTIN_PARAMETERS),
        name="builtin",
        metadata={
            "source": "facenormals procedural head (facenormals.models.builtin)",
            "license": "MIT",
            "shape_components": [spec.name for spec in BUILTIN_PARAMETERS],
        },
        face_region=torch.from_numpy(_face_region(mean)),
    )
