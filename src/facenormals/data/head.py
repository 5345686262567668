"""Per-model data the scenes need, computed once from the mean head: holes, regions, occlusion.

Everything here is topology-level: boundary loops of the eye, mouth and neck openings, per-vertex
weights of facial regions (lips, brows, beard, cheeks, ...) placed from the 24 landmarks, a cavity
term used as ambient occlusion, and angular coordinates around the skull for hair lines. It works
for any :class:`~facenormals.models.MorphableModel` with the 24 landmarks; a closed mesh (the
built-in head) simply has no openings.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse
import torch

from facenormals.data.meshes import boundary_loops, neighbour_average
from facenormals.mesh import VertexNormals, vertex_normals
from facenormals.models.morphable import MorphableModel

__all__ = ["HeadAssets"]


def _smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _polyline_distance(points: np.ndarray, polyline: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """2-D distance of ``points`` ``(N, 2)`` to a polyline ``(M, 2)`` and the arc-length fraction of the foot."""
    best = np.full(len(points), np.inf)
    where = np.zeros(len(points))
    lengths = np.linalg.norm(np.diff(polyline, axis=0), axis=1)
    start = np.concatenate([[0.0], np.cumsum(lengths)]) / max(lengths.sum(), 1e-9)
    for k in range(len(polyline) - 1):
        a, b = polyline[k], polyline[k + 1]
        ab = b - a
        t = np.clip(((points - a) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
        d = np.linalg.norm(points - (a + t[:, None] * ab), axis=1)
        closer = d < best
        best[closer] = d[closer]
        where[closer] = start[k] + t[closer] * (start[k + 1] - start[k])
    return best, where


@dataclass
class HeadAssets:
    """Topology-level data of one morphable model, computed from its mean head.

    Attributes:
        model: the model.
        faces: ``(F, 3)`` int64 triangles.
        eye_loops: ordered boundary loops of the (subject's) right and left eye openings, or ``[]``.
        mouth_loop: ordered boundary loop of the mouth opening, or ``None``.
        neck_loop: ordered boundary loop of the neck cut, or ``None``.
        regions: per-vertex weights in ``[0, 1]``: ``lips``, ``brows``, ``beard``, ``cheeks``,
            ``nose``, ``under_eyes``, ``ears``, ``face`` (front-facing face area).
        occlusion: ``(N,)`` ambient occlusion from the mean head's concavity, in ``[0.35, 1]``.
        azimuth: ``(N,)`` angle around the vertical axis through the skull centre, 0 at the face,
            ±π at the back (radians).
        height: ``(N,)`` height above eye level in mm (up is positive).
        framing: ``(N,)`` bool, the vertices that count as the head when framing the camera (not the neck).
        smoothing: the one-ring averaging operator ``(N, N)``.
        skull_center: ``(3,)`` centre of the skull in the mean head's model frame.
        skull_radius: ``(N,)`` distance of each mean vertex from the skull centre, smoothed over
            the mesh (20 one-ring averages), the base of hair shells.
    """

    model: MorphableModel
    faces: np.ndarray
    eye_loops: list[np.ndarray]
    mouth_loop: np.ndarray | None
    neck_loop: np.ndarray | None
    regions: dict[str, np.ndarray]
    occlusion: np.ndarray
    azimuth: np.ndarray
    height: np.ndarray
    framing: np.ndarray
    smoothing: scipy.sparse.csr_matrix
    skull_center: np.ndarray
    skull_radius: np.ndarray
    _noise: dict = field(default_factory=dict, repr=False)
    _normals: VertexNormals | None = field(default=None, repr=False)

    @classmethod
    def from_model(cls, model: MorphableModel) -> "HeadAssets":
        """Compute the assets of ``model`` (about 0.2 s for the ICT head).

        Raises:
            ValueError: if the model lacks any of the 24 landmarks.
        """
        from facenormals.models.landmarks import LANDMARK_NAMES

        missing = [n for n in LANDMARK_NAMES if n not in model.landmarks]
        if missing:
            raise ValueError(f"model: the generator needs the 24 landmarks of models/landmarks.py, missing {missing}")
        mean = model.mean.detach().cpu().double()
        faces_t = model.faces.detach().cpu()
        normals = vertex_normals(mean[None], faces_t)[0].numpy()
        v = mean.numpy()
        faces = faces_t.numpy().astype(np.int64)
        lm = {name: v[model.landmarks[name]] for name in LANDMARK_NAMES}
        smoothing = neighbour_average(faces, len(v))

        # openings
        eye_centers = [(lm["right_eye_outer"] + lm["right_eye_inner"]) / 2, (lm["left_eye_outer"] + lm["left_eye_inner"]) / 2]
        mouth_center = (lm["right_mouth_corner"] + lm["left_mouth_corner"]) / 2
        eye_loops: list[np.ndarray | None] = [None, None]
        mouth_loop = neck_loop = None
        for loop in boundary_loops(faces):
            centroid = v[loop].mean(0)
            distances = [np.linalg.norm(centroid - c) for c in eye_centers]
            side = int(np.argmin(distances))
            if distances[side] < 15.0 and len(loop) >= 6:
                eye_loops[side] = loop
            elif np.linalg.norm(centroid - mouth_center) < 20.0 and len(loop) >= 6:
                mouth_loop = loop
            elif centroid[1] > lm["chin"][1] and (neck_loop is None or len(loop) > len(neck_loop)):
                neck_loop = loop
        eyes = [loop for loop in eye_loops if loop is not None] if all(l is not None for l in eye_loops) else []

        # angular coordinates around the skull
        eye_level = float(np.mean([lm[n][1] for n in ("right_eye_outer", "right_eye_inner", "left_eye_inner", "left_eye_outer")]))
        cranium = v[:, 1] < eye_level
        skull_center = np.array([0.0, eye_level, 0.5 * (v[cranium, 2].min() + v[cranium, 2].max())])
        rel = v - skull_center
        azimuth = np.arctan2(rel[:, 0], -rel[:, 2])
        height = eye_level - v[:, 1]
        framing = v[:, 1] <= lm["chin"][1] + 5.0

        # regions
        front = _smoothstep(-0.1, -0.45, normals[:, 2])
        xy = v[:, :2]
        regions: dict[str, np.ndarray] = {}
        lip_center = np.array([0.0, 0.5 * (lm["upper_lip"][1] + lm["lower_lip"][1])])
        half = np.array([abs(lm["left_mouth_corner"][0] - lm["right_mouth_corner"][0]) / 2 + 2.0,
                         (lm["lower_lip"][1] - lm["upper_lip"][1]) / 2 + 1.0])
        d = np.sum(((xy - lip_center) / half) ** 2, axis=1)
        regions["lips"] = _smoothstep(1.05, 0.6, d) * front
        brows = np.zeros(len(v))
        for side, sign in (("right", -1.0), ("left", 1.0)):
            inner, outer, center = lm[f"{side}_eye_inner"], lm[f"{side}_eye_outer"], lm[f"{side}_brow_center"]
            line = np.array([[inner[0] - sign * 3.0, center[1] + 4.0], center[:2],
                             [outer[0] + sign * 7.0, center[1] + 7.0]])
            dist, along = _polyline_distance(xy, line)
            width = 5.0 - 2.5 * along
            brows = np.maximum(brows, np.exp(-((dist / width) ** 2)) * front)
        regions["brows"] = brows
        nose, sub, chin = lm["nose_tip"], lm["subnasale"], lm["chin"]
        jaw = 0.5 * (abs(lm["left_jaw_angle"][0]) + abs(lm["right_jaw_angle"][0]))
        ear_z = 0.5 * (lm["left_ear_tragus"][2] + lm["right_ear_tragus"][2])
        beard = _smoothstep(sub[1] - 2.0, sub[1] + 6.0, v[:, 1]) * _smoothstep(chin[1] + 35.0, chin[1] + 15.0, v[:, 1])
        beard *= _smoothstep(jaw + 10.0, jaw - 5.0, np.abs(v[:, 0])) * _smoothstep(ear_z - 5.0, ear_z - 25.0, v[:, 2])
        regions["beard"] = beard * (1.0 - regions["lips"])
        cheek = np.zeros(len(v))
        for side in ("right", "left"):
            c = np.array([0.8 * lm[f"{side}_eye_outer"][0], nose[1]])
            cheek = np.maximum(cheek, np.exp(-np.sum((xy - c) ** 2, axis=1) / (2 * 16.0**2)))
        regions["cheeks"] = cheek * front
        regions["nose"] = np.exp(-np.sum((v - nose) ** 2, axis=1) / (2 * 12.0**2))
        under = np.zeros(len(v))
        for c in eye_centers:
            under = np.maximum(under, np.exp(-np.sum((xy - (c[:2] + [0.0, 9.0])) ** 2 / np.array([14.0, 5.0]) ** 2, axis=1)))
        regions["under_eyes"] = under * front
        ears = np.zeros(len(v))
        for side in ("right", "left"):
            c = (lm[f"{side}_ear_top"] + lm[f"{side}_ear_lobe"] + lm[f"{side}_ear_tragus"]) / 3
            ears = np.maximum(ears, np.exp(-np.sum((v - c) ** 2, axis=1) / (2 * 18.0**2)))
        regions["ears"] = ears
        regions["face"] = front * _smoothstep(lm["right_brow_center"][1] - 25.0, lm["right_brow_center"][1] - 10.0, v[:, 1])

        # cavity-based ambient occlusion: how far the smoothed surface lies in front of the vertex
        smooth = v.copy()
        for _ in range(12):
            smooth = smoothing @ smooth
        concavity = np.sum((smooth - v) * normals, axis=1)
        occlusion = np.clip(np.exp(-np.maximum(concavity, 0.0) / 3.0), 0.35, 1.0)
        for loop in [*eyes, *(l for l in (mouth_loop,) if l is not None)]:
            occlusion[loop] = np.minimum(occlusion[loop], 0.6)

        radius = np.linalg.norm(v - skull_center, axis=1)
        for _ in range(20):
            radius = smoothing @ radius

        return cls(
            model=model,
            faces=faces,
            eye_loops=eyes,
            mouth_loop=mouth_loop,
            neck_loop=neck_loop,
            regions={k: w.astype(np.float32) for k, w in regions.items()},
            occlusion=occlusion.astype(np.float32),
            azimuth=azimuth.astype(np.float32),
            height=height.astype(np.float32),
            framing=framing,
            smoothing=smoothing,
            skull_center=skull_center,
            skull_radius=radius,
        )

    def vertices(self, shape_coeffs: np.ndarray, expression_coeffs: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Identity-only and full vertices ``(N, 3)`` float32 of one head, from float32 coefficients.

        The full vertices are computed with the same two ``addmm`` as ``model(y, e)``, so they are
        bit-identical to rebuilding the head from the stored coefficients.
        """
        model = self.model
        with torch.no_grad():
            y = torch.from_numpy(np.asarray(shape_coeffs, np.float32))[None]
            identity = model(y)
            full = identity
            if expression_coeffs is not None and model.num_expressions:
                e = torch.from_numpy(np.asarray(expression_coeffs, np.float32))[None]
                basis = model.expression_basis.reshape(model.num_expressions, -1)
                full = torch.addmm(identity.reshape(1, -1), e, basis).reshape(identity.shape)
        return identity[0].numpy(), full[0].numpy()

    def vertex_normals(self, vertices: np.ndarray) -> np.ndarray:
        """Ring vertex normals ``(N, 3)`` float32 (:func:`~facenormals.mesh.vertex_normals`) of one head."""
        if self._normals is None:
            self._normals = VertexNormals(self.model.faces, self.model.num_vertices)
        with torch.no_grad():
            return self._normals(torch.from_numpy(np.ascontiguousarray(vertices, np.float32))[None])[0].numpy()

    def noise(self, rng: np.random.Generator, name: str) -> np.ndarray:
        """A smooth random per-vertex field ``(N,)`` of unit variance, attached to the surface.

        It is a random combination of 24 fixed fields (sums of plane waves over the mean head,
        built once per process with a fixed seed), so sampling costs one small matrix product.
        ``name`` picks the scale: ``"blotches"`` (60 mm), ``"mottle"`` (15 mm), ``"grain"`` (4 mm),
        ``"freckles"`` (3 mm), ``"hairs"`` (2 mm), ``"stubble"`` (1.5 mm), ``"hair_volume"`` (40 mm),
        ``"strands"`` (stripes across the azimuth).
        """
        from facenormals.data.appearance import fourier_noise

        if name not in self._noise:
            scales = {"blotches": 60.0, "mottle": 15.0, "grain": 4.0, "freckles": 3.0, "hairs": 2.0, "stubble": 1.5,
                      "hair_volume": 40.0, "strands": 2.5}
            if name not in scales:
                raise ValueError(f"name: expected one of {sorted(scales)}, got {name!r}")
            points = self.model.mean.detach().cpu().double().numpy()
            if name == "strands":
                points = np.stack([self.azimuth * 90.0, self.height * 0.15, np.zeros_like(self.height)], axis=1)
            bank_rng = np.random.default_rng(sorted(scales).index(name))
            terms = 24 if scales[name] < 5 else 12
            self._noise[name] = np.stack([fourier_noise(points, bank_rng, scales[name], terms) for _ in range(24)]).astype(np.float32)
        bank = self._noise[name]
        weights = rng.normal(size=len(bank)).astype(np.float32) / np.sqrt(len(bank))
        return weights @ bank
