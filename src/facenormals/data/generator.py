r"""Synthetic training samples: rendered heads with exact normal maps, landmarks and ground truth.

A sample is a deterministic function of ``(seed, index)``: every random choice draws from
``numpy.random.SeedSequence(seed, spawn_key=(index,))`` (one child stream per aspect: shape, pose,
camera, skin, hair, lights, background, extras), and the sample is always drawn in the tile
``index mod grid²`` of the renderer, so its bytes do not depend on the batch it was generated
in, on the number of workers or on the machine's rank.

See ``docs/synthetic_data.md`` for the distributions and the design decisions.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from numbers import Real
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import torch

from facenormals.core.check import check_integer
from facenormals.data.appearance import (
    auto_exposure,
    sample_hair_color,
    sample_iris_color,
    sample_lighting,
    skin_albedo,
    srgb_to_linear,
)
from facenormals.data.backgrounds import PhotoLibrary, random_background
from facenormals.data.head import HeadAssets
from facenormals.data.raycast import blocked_rays
from facenormals.data.render import FAR_MM, NEAR_MM, MeshPart, RenderedTiles, TileRenderer, TileScene
from facenormals.data.scene import (
    HEAD_LABELS,
    clothing_part,
    eye_parts,
    hair_parts,
    mouth_part,
    occluder_parts,
)
from facenormals.geometry import euler_to_rotation_matrix, project_points
from facenormals.models.morphable import MorphableModel

__all__ = ["SynthBatch", "SynthConfig", "SyntheticHeadGenerator"]

_STREAMS = ("shape", "pose", "camera", "skin", "hair", "light", "background", "extras")
#: Version of what a (seed, index) draws: bumped whenever the same sample's bytes change (2: the
#: framing solved by Newton's method, clutter colours clipped; 3: landmark visibility by ray casting,
#: occluders aimed at visible landmarks, lights dimmed by auto-exposure), so that a dataset is never resumed
#: with samples of two generators (a manifest without it was written by version 1).
GENERATOR_VERSION = 3
#: Least depth slack in mm by which the head surface may lie in front of a landmark it does not hide.
LANDMARK_DEPTH_SLACK_MM = 3.0
#: Most iterations of the framing solve (it converges in 3 or 4), and the margin in pixels by which
#: the framed head stays inside the image edges (float32 rounding of the stored camera moves ~1e-5 px).
_FRAME_ITERATIONS = 50
_FRAME_MARGIN = 1e-3


@dataclass(frozen=True)
class SynthConfig:
    r"""The distributions of the synthetic data (defaults: the issue's ranges).

    Attributes:
        image_size: side of the square images in pixels, an integer >= 16.
        identity_scale: identity coefficients are :math:`y_k \sim \mathcal N(0, (s\,\sigma_k)^2)`;
            values above 1 give a wider range of faces.
        expression_probability: probability of a non-neutral expression: 1 to ``max_expressions``
            random blendshapes with weights ``uniform(0.15, 1) ** 0.8``, in ``[0.219, 1]``, often
            mirrored to their _L/_R partner (times 0.8–1.2), sometimes with ``jawOpen`` (0.1–0.8).
        max_expressions: at most this many blendshapes are active (before mirroring _L/_R pairs), an
            integer >= 0 (0: always neutral).
        yaw, pitch, roll: uniform ranges ``±`` these angles, degrees: yaw and roll at most 180, pitch
            below 90 (where :func:`~facenormals.geometry.rotation_matrix_to_euler` inverts it).
        fill: range of the head's size (larger side of the projected bounding box of the head
            without the neck) as a fraction of the image side. Up to 1 the head lies inside the
            image; above 1 (at most 1.5) it is cropped.
        focal: range of the focal length in pixels for a 128-pixel image (log-uniform; scaled
            with ``image_size``).
        principal_jitter: principal point offset from the image centre, uniform ``±`` pixels at 128
            (the principal point stays inside the image: below ``64 (S - 1) / S``).
        num_lights: range of the number of directional lights.
        temperature: range of the colour temperatures in kelvin.
        exposure: range of the auto-exposure target (linear, in ``(0, 1]``): lights that would make
            the 90th percentile of the camera-facing head's diffuse radiance brighter are dimmed to
            a target drawn from it (:func:`~facenormals.data.appearance.auto_exposure`).
        hair_probability: probability of procedural hair.
        cap_probability: probability of a cap (otherwise bald when no hair).
        occluder_probability: probability of 1–2 occluding solids in front of the face.
        eyes, mouth, clothing: draw eyeballs, a mouth interior, collar and shoulders.
        photo_probability: probability of a photo background when photos are available.
        background_folders: folders of background photos (``.jpg``/``.png``).
        use_skimage: also crop ``skimage.data`` images when scikit-image is installed.
        supersample: odd integer colour supersampling factor (anti-aliasing).
    """

    image_size: int = 128
    identity_scale: float = 1.0
    expression_probability: float = 0.8
    max_expressions: int = 4
    yaw: float = 90.0
    pitch: float = 35.0
    roll: float = 25.0
    fill: tuple[float, float] = (0.4, 0.9)
    focal: tuple[float, float] = (120.0, 800.0)
    principal_jitter: float = 6.0
    num_lights: tuple[int, int] = (1, 3)
    temperature: tuple[float, float] = (2500.0, 9000.0)
    exposure: tuple[float, float] = (0.8, 1.0)
    hair_probability: float = 0.65
    cap_probability: float = 0.15
    occluder_probability: float = 0.25
    eyes: bool = True
    mouth: bool = True
    clothing: bool = True
    photo_probability: float = 0.4
    background_folders: tuple[str, ...] = ()
    use_skimage: bool = True
    supersample: int = 3

    def __post_init__(self) -> None:
        def probability(name: str) -> None:
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name}: expected a probability in [0, 1], got {value}")

        for name, minimum in (("image_size", 16), ("supersample", 1), ("max_expressions", 0)):
            object.__setattr__(self, name, check_integer(getattr(self, name), name, minimum))  # numpy ints -> int
        for name in ("identity_scale", "expression_probability", "yaw", "pitch", "roll", "principal_jitter",
                     "hair_probability", "cap_probability", "occluder_probability", "photo_probability"):
            value = getattr(self, name)  # a type before the comparisons below: "90" or None raised TypeError
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, Real):
                raise ValueError(f"{name}: expected a real number, got {type(value).__name__} {value!r}")
            object.__setattr__(self, name, float(value))  # numpy floats -> float (JSON in the manifest)
        if self.supersample % 2 == 0:
            raise ValueError(f"supersample: expected an odd factor >= 1, got {self.supersample}")
        if not (math.isfinite(self.identity_scale) and self.identity_scale >= 0):
            raise ValueError(f"identity_scale: expected a finite number >= 0, got {self.identity_scale}")
        for name in ("expression_probability", "hair_probability", "cap_probability", "occluder_probability",
                     "photo_probability"):
            probability(name)
        if self.hair_probability + self.cap_probability > 1.0:
            raise ValueError("hair_probability + cap_probability: expected at most 1, got "
                             f"{self.hair_probability + self.cap_probability}")
        for name in ("fill", "focal", "temperature", "num_lights", "exposure"):
            pair = getattr(self, name)
            if (not isinstance(pair, (tuple, list)) or len(pair) != 2
                    or any(isinstance(v, (bool, np.bool_)) or not isinstance(v, Real) for v in pair)):
                raise ValueError(f"{name}: expected a (low, high) pair of numbers, got {pair!r}")
            object.__setattr__(self, name, tuple(pair))  # a list would leave the frozen config unhashable
        lo, hi = self.fill
        if not 0.0 < lo <= hi <= 1.5:
            raise ValueError(f"fill: expected 0 < low <= high <= 1.5, got {self.fill}")
        if not 0.0 < self.focal[0] <= self.focal[1] < math.inf:
            raise ValueError(f"focal: expected 0 < low <= high < inf, got {self.focal}")
        if not 1000.0 <= self.temperature[0] <= self.temperature[1] <= 40000.0:  # color_temperature's range
            raise ValueError(f"temperature: expected 1000 <= low <= high <= 40000 kelvin, got {self.temperature}")
        if not 0.0 < self.exposure[0] <= self.exposure[1] <= 1.0:
            raise ValueError(f"exposure: expected 0 < low <= high <= 1, got {self.exposure}")
        if any(not math.isfinite(v) or int(v) != v for v in self.num_lights):
            raise ValueError(f"num_lights: expected integers, got {self.num_lights}")
        if isinstance(self.background_folders, (str, Path)):
            raise ValueError(f"background_folders: expected a tuple of folders, got the single "
                             f"{type(self.background_folders).__name__} {str(self.background_folders)!r}")
        if (not isinstance(self.background_folders, (tuple, list))
                or not all(isinstance(f, (str, Path)) for f in self.background_folders)):
            raise ValueError(f"background_folders: expected a tuple of folders (str or Path), got "
                             f"{self.background_folders!r}")
        # a tuple of str: hashable, as the frozen config promises, and JSON for the manifest
        object.__setattr__(self, "background_folders", tuple(str(f) for f in self.background_folders))
        # the principal point stays inside the image: the framing relies on it
        limit = 64.0 * (self.image_size - 1) / self.image_size
        if not 0.0 <= self.principal_jitter < limit:
            raise ValueError(f"principal_jitter: expected pixels in [0, {limit:g}) (the principal point inside the "
                             f"image), got {self.principal_jitter}")
        if not 0 <= self.num_lights[0] <= self.num_lights[1] <= 3:
            raise ValueError(f"num_lights: expected 0 <= low <= high <= 3, got {self.num_lights}")
        for name in ("roll", "yaw"):
            if not 0.0 <= getattr(self, name) <= 180.0:
                raise ValueError(f"{name}: expected a range in [0, 180] degrees, got {getattr(self, name)}")
        if not 0.0 <= self.pitch < 90.0:  # rotation_matrix_to_euler recovers pitch only inside (-90, 90)
            raise ValueError(f"pitch: expected a range in [0, 90) degrees, got {self.pitch}")

    @classmethod
    def head_only(cls, **changes) -> "SynthConfig":
        """A configuration that renders the bare head mesh: no hair, caps, occluders, eyes, mouth or clothing."""
        base = dict(hair_probability=0.0, cap_probability=0.0, occluder_probability=0.0, eyes=False, mouth=False,
                    clothing=False)
        base.update(changes)
        return cls(**base)

    def to_dict(self) -> dict:
        """JSON-serialisable form (tuples become lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict) -> "SynthConfig":
        names = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - set(names))
        if unknown:
            raise ValueError(f"config: unknown fields {unknown}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})


@dataclass
class SynthBatch:
    """A batch of samples as NumPy arrays (``B`` samples, ``L = 24`` landmarks, ``S = H = W``).

    Attributes:
        index: ``(B,)`` int64 sample indices.
        image: ``(B, S, S, 3)`` uint8 RGB images.
        normals: ``(B, 3, S, S)`` float32 camera-frame unit normals of the head surface, 0 elsewhere.
        segmentation: ``(B, S, S)`` uint8 labels (see :data:`~facenormals.data.scene.LABELS`).
        depth: ``(B, S, S)`` float32 camera-frame depth of the nearest surface (any label), ``inf``
            on background. Not stored in shards.
        landmarks: ``(B, L, 2)`` float32 landmark pixels ``(u, v)``, :func:`~facenormals.geometry.project_points`
            of the ground truth.
        landmark_visible: ``(B, L)`` bool: inside the image, not hidden by the head (z-buffer) nor
            by hair, headwear, clothing or occluders (a landmark on the outline is visible).
        shape_coeffs: ``(B, K)`` float32 identity coefficients.
        expression_coeffs: ``(B, E)`` float32 expression weights (``E = 0`` without blendshapes).
        angles: ``(B, 3)`` float32 ``(roll, pitch, yaw)`` in radians.
        rotation: ``(B, 3, 3)`` float32, ``euler_to_rotation_matrix(angles)``.
        translation: ``(B, 3)`` float32 model-frame translation ``t`` in mm.
        intrinsics: ``(B, 3)`` float32 ``(f, u0, v0)`` in pixels.
    """

    index: np.ndarray
    image: np.ndarray
    normals: np.ndarray
    segmentation: np.ndarray
    depth: np.ndarray
    landmarks: np.ndarray
    landmark_visible: np.ndarray
    shape_coeffs: np.ndarray
    expression_coeffs: np.ndarray
    angles: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    intrinsics: np.ndarray

    def __len__(self) -> int:
        return len(self.index)

    @property
    def mask(self) -> np.ndarray:
        """``(B, S, S)`` bool foreground: the head surface (where N is non-zero)."""
        return np.isin(self.segmentation, HEAD_LABELS)

    @staticmethod
    def concatenate(batches: Sequence["SynthBatch"]) -> "SynthBatch":
        fields_ = [f.name for f in dataclasses.fields(SynthBatch)]
        return SynthBatch(**{name: np.concatenate([getattr(b, name) for b in batches]) for name in fields_})


@dataclass
class _Plan:
    """Everything sampled for one sample before rendering."""

    index: int
    scene: TileScene
    background: np.ndarray
    record: dict[str, np.ndarray] = field(default_factory=dict)


class SyntheticHeadGenerator:
    """Render synthetic training samples of a morphable model.

    Args:
        model: a :class:`~facenormals.models.MorphableModel` or a spec for
            :func:`~facenormals.models.load_model` (``"auto"``, ``"ict"``, ``"builtin"``, a path). The
            generator works in float32 on the CPU: another model is copied and converted, the
            caller's stays as it is.
        config: the :class:`SynthConfig`.
        grid: renderer tiles per side (``grid²`` samples per render call). A sample is always drawn
            in tile ``index mod grid²``; its bytes are reproducible for the same ``grid`` (the
            default 8 is what :func:`~facenormals.data.write_dataset` uses).

    The OpenGL context is created on first use, so constructing a generator is cheap and the
    object can be built before a process forks; each process must use its own generator.

    Example:
        >>> gen = SyntheticHeadGenerator("builtin")  # doctest: +SKIP
        >>> batch = gen.generate(seed=0, indices=range(4))  # doctest: +SKIP
        >>> batch.image.shape, batch.normals.shape  # doctest: +SKIP
        ((4, 128, 128, 3), (4, 3, 128, 128))
    """

    def __init__(self, model: MorphableModel | str = "auto", config: SynthConfig | None = None, grid: int = 8) -> None:
        from facenormals.models import load_model

        if isinstance(model, MorphableModel):
            tensors = [*model.parameters(), *model.buffers()]
            if any(t.device.type != "cpu" or (t.is_floating_point() and t.dtype != torch.float32) for t in tensors):
                model = copy.deepcopy(model).float().cpu()  # the caller's model stays as it is
            self.model = model
        elif isinstance(model, (str, Path)):
            self.model = load_model(model)
        else:  # load_model's error would name its own argument, `spec`
            raise ValueError(f"model: expected a MorphableModel or a spec for load_model ('auto', 'ict', 'builtin' "
                             f"or a path), got {type(model).__name__} {model!r}")
        self.model.check_millimetres()  # the scene (camera distance, hair, eyeballs) is built in mm
        self.config = config if config is not None else SynthConfig()
        if not isinstance(self.config, SynthConfig):
            raise ValueError(f"config: expected a SynthConfig, got {type(self.config).__name__}")
        if int(grid) < 1:
            raise ValueError(f"grid: expected >= 1, got {grid}")
        self.grid = int(grid)
        self.assets = HeadAssets.from_model(self.model)
        self._faces = np.ascontiguousarray(self.assets.faces, dtype=np.uint32)
        self.photos = PhotoLibrary(self.config.background_folders, self.config.use_skimage)
        self._renderer: TileRenderer | None = None
        names = self.model.expression_names
        mirror = {n: n[:-2] + {"_L": "_R", "_R": "_L"}[n[-2:]] for n in names if n[-2:] in ("_L", "_R")}
        self._pairs = {i: names.index(mirror[n]) for i, n in enumerate(names) if mirror.get(n) in names}
        self._jaw = names.index("jawOpen") if "jawOpen" in names else None
        self._mouth_close = names.index("mouthClose") if "mouthClose" in names else None

    def __repr__(self) -> str:
        return f"SyntheticHeadGenerator(model={self.model.name!r}, image_size={self.config.image_size}, grid={self.grid})"

    @property
    def renderer(self) -> TileRenderer:
        """The tiled renderer (created on first use)."""
        if self._renderer is None:
            size = self.config.image_size
            self._renderer = TileRenderer((size, size), grid=self.grid, supersample=self.config.supersample)
            self.grid = self._renderer.grid
        return self._renderer

    def close(self) -> None:
        """Release the OpenGL context."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self) -> "SyntheticHeadGenerator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ public

    def generate(self, seed: int, indices: Iterable[int], angles: Sequence[Sequence[float]] | None = None) -> SynthBatch:
        """Generate the samples ``indices`` of the dataset ``seed``.

        Args:
            seed: dataset seed, an integer ``>= 0``.
            indices: sample indices, integers ``>= 0`` (any order, repeats allowed).
            angles: optional ``(roll, pitch, yaw)`` in radians per entry of ``indices``, replacing
                the sampled head pose and keeping everything else of the sample (identity,
                expression, appearance, hair, lights, camera): repeating an index with several
                poses gives a multi-view set of one person, e.g.
                ``generate(0, [7, 7, 7], angles=[(0, 0, -0.8), (0, 0, 0), (0, 0, 0.8)])``.

        Returns:
            The :class:`SynthBatch`, in the order of ``indices``.

        Raises:
            ValueError: on a negative or non-integer seed or index.
        """
        seed = _check_int(seed, "seed")
        indices = [_check_int(i, "indices") for i in indices]
        if angles is not None:
            angles = [np.asarray(a, dtype=np.float32) for a in angles]
            if len(angles) != len(indices) or any(a.shape != (3,) or not np.isfinite(a).all() for a in angles):
                raise ValueError(f"angles: expected {len(indices)} finite (roll, pitch, yaw) triples, one per index, "
                                 f"got {len(angles)} of shapes {sorted({a.shape for a in angles})}")
        capacity = self.renderer.capacity
        groups: list[list[int]] = []
        used: set[int] = set()
        for position, index in enumerate(indices):
            tile = index % capacity
            if not groups or tile in used or len(groups[-1]) == capacity:
                groups.append([])
                used = set()
            groups[-1].append(position)
            used.add(tile)
        results: list[SynthBatch] = []
        for group in groups:
            plans = [self._plan(seed, indices[p], None if angles is None else angles[p]) for p in group]
            rendered = self.renderer.render([p.scene for p in plans], [p.index % capacity for p in plans])
            results.append(self._finish(plans, rendered))
        if not results:
            return self._empty()
        return SynthBatch.concatenate(results)

    def sample(self, seed: int, index: int) -> SynthBatch:
        """One sample, as a batch of one."""
        return self.generate(seed, [index])

    # ------------------------------------------------------------------ sampling

    def _streams(self, seed: int, index: int) -> dict[str, np.random.Generator]:
        root = np.random.SeedSequence(entropy=seed, spawn_key=(index,))
        return {name: np.random.Generator(np.random.PCG64(child)) for name, child in zip(_STREAMS, root.spawn(len(_STREAMS)))}

    def _expressions(self, rng: np.random.Generator) -> np.ndarray:
        """Expression weights ``(E,)`` float32 in ``[0, 1]``: with ``expression_probability``, 1 to
        ``max_expressions`` blendshapes with weights ``uniform(0.15, 1) ** 0.8`` (in ``[0.219, 1]``), each
        copied to its _L/_R partner with probability 0.6 (times 0.8–1.2), then ``jawOpen`` at least
        ``uniform(0.1, 0.8)`` with probability 0.25; ``mouthClose <= jawOpen``."""
        count = self.model.num_expressions
        weights = np.zeros(count, dtype=np.float64)
        if count == 0 or self.config.max_expressions == 0 or rng.random() >= self.config.expression_probability:
            return weights.astype(np.float32)
        k = int(rng.integers(1, self.config.max_expressions + 1))
        chosen = rng.choice(count, size=min(k, count), replace=False)
        weights[chosen] = rng.uniform(0.15, 1.0, size=len(chosen)) ** 0.8
        for i in chosen:
            if i in self._pairs and rng.random() < 0.6:
                weights[self._pairs[i]] = np.clip(weights[i] * rng.uniform(0.8, 1.2), 0.0, 1.0)
        if self._jaw is not None and rng.random() < 0.25:
            weights[self._jaw] = max(weights[self._jaw], rng.uniform(0.1, 0.8))
        if self._mouth_close is not None and self._jaw is not None:
            weights[self._mouth_close] = min(weights[self._mouth_close], weights[self._jaw])
        return np.clip(weights, 0.0, 1.0).astype(np.float32)

    def _frame(self, rng: np.random.Generator, vertices: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Intrinsics ``(f, u0, v0)`` ``(3,)`` and translation ``(3,)`` float32 for the head ``vertices``
        ``(N, 3)`` posed by ``rotation`` ``(3, 3)``: the larger side of the projected bounding box of the
        framing vertices is the sampled fraction ``fill`` of the image side, its centre a random pixel
        that keeps it inside the image, and for ``fill <= 1`` the box lies inside the image
        ``[-0.5, size - 0.5]`` (pixel edges) whatever the solve left."""
        cfg = self.config
        size = cfg.image_size
        scale = size / 128.0
        f = math.exp(rng.uniform(math.log(cfg.focal[0]), math.log(cfg.focal[1]))) * scale
        center_px = (size - 1) / 2.0
        u0 = center_px + rng.uniform(-1.0, 1.0) * cfg.principal_jitter * scale
        v0 = center_px + rng.uniform(-1.0, 1.0) * cfg.principal_jitter * scale
        fill = rng.uniform(*cfg.fill)
        target = fill * size
        head = vertices[self.assets.framing].astype(np.float64)  # every vertex: a subset let heads leave the frame
        middle = 0.5 * (head.min(0) + head.max(0))
        posed = (head - middle) @ rotation.T  # camera-frame offsets from the head's middle
        principal = np.array([u0, v0])
        half = min(target / 2.0, size / 2.0)
        want = np.array([rng.uniform(half - 0.5, size - 0.5 - half), rng.uniform(half - 0.5, size - 0.5 - half)])
        # Newton's method on (box centre - want, larger side - target) over the camera-frame position of
        # the head's middle; the derivatives are those of the box's extreme points. (A fixed-point update
        # z *= side / target oscillates up close, where the side shrinks faster than 1 / z.)
        z = f * float(np.max(posed[:, :2].max(0) - posed[:, :2].min(0))) / target
        position = np.append((want - principal) * z / f, z)
        for _ in range(_FRAME_ITERATIONS):
            points = posed + position
            depth = np.maximum(points[:, 2], 1.0)
            uv = f * points[:, :2] / depth[:, None] + principal
            ends = np.stack([uv.argmin(0), uv.argmax(0)])  # (2, 2): the lowest and highest point along u and v
            u, end_depth = uv[ends, [0, 1]], depth[ends]
            side = u[1] - u[0]
            a = int(np.argmax(side))
            residual = np.append(0.5 * (u[0] + u[1]) - want, side[a] - target)
            if np.abs(residual).max() < 1e-9:
                break
            du_dxy, du_dz = f / end_depth, (principal - u) / end_depth  # derivatives of each end along its axis
            jacobian = np.zeros((3, 3))
            jacobian[[0, 1], [0, 1]] = du_dxy.mean(0)
            jacobian[:2, 2] = du_dz.mean(0)
            jacobian[2, [a, 2]] = du_dxy[1, a] - du_dxy[0, a], du_dz[1, a] - du_dz[0, a]
            position = position - np.linalg.solve(jacobian, residual)
        if target <= size:  # moving the head away draws every point towards the principal point, inside the image
            lateral = posed[:, :2] + position[:2]
            edge = np.where(lateral > 0, size - 0.5 - _FRAME_MARGIN, -0.5 + _FRAME_MARGIN) - principal
            position[2] = max(position[2], float(np.max(f * lateral / edge - posed[:, 2:3])))
        depth = posed[:, 2] + position[2]
        if depth.min() < NEAR_MM or depth.max() > FAR_MM:  # clipped: an empty image with every landmark "visible"
            raise ValueError(f"focal: {f / scale:.0f} px (at 128 px) with fill {fill:.2f} puts the head "
                             f"{depth.min():.0f}-{depth.max():.0f} mm from the camera, outside the renderer's clipping "
                             f"range [{NEAR_MM:g}, {FAR_MM:g}] mm; narrow the config's focal or fill range")
        translation = rotation.T @ position - middle
        return np.array([f, u0, v0], dtype=np.float32), translation.astype(np.float32)

    def _plan(self, seed: int, index: int, pose: np.ndarray | None = None) -> _Plan:
        cfg = self.config
        rng = self._streams(seed, index)
        model = self.model
        shape = (rng["shape"].normal(size=model.num_shape) * cfg.identity_scale
                 * model.shape_std.numpy().astype(np.float64)).astype(np.float32)
        expression = self._expressions(rng["shape"])
        identity, vertices = self.assets.vertices(shape, expression if model.num_expressions else None)
        angles = np.radians(np.array([
            rng["pose"].uniform(-cfg.roll, cfg.roll), rng["pose"].uniform(-cfg.pitch, cfg.pitch),
            rng["pose"].uniform(-cfg.yaw, cfg.yaw),
        ])).astype(np.float32) if pose is None else pose  # fmt: skip
        rotation = euler_to_rotation_matrix(torch.from_numpy(angles)[None])[0].numpy()
        intrinsics, translation = self._frame(rng["camera"], vertices, rotation.astype(np.float64))
        R, t = rotation.astype(np.float64), translation.astype(np.float64)

        # appearance
        hair_rng = rng["hair"]
        hair_color, brow_color = sample_hair_color(hair_rng)
        albedo = skin_albedo(self.assets.noise, self.assets.regions, rng["skin"], brow_color)
        normals = self.assets.vertex_normals(vertices)
        skin = rng["skin"]
        head = MeshPart(
            vertices=vertices, normals=normals, colors=albedo, faces=self._faces, label=1,
            rotation=R, translation=t, occlusion=self.assets.occlusion,
            specular=skin.uniform(0.05, 0.35), shininess=skin.uniform(8.0, 35.0), wrap=skin.uniform(0.1, 0.4),
            noise=(skin.uniform(0.02, 0.08), skin.uniform(0.3, 0.8), 1.0, skin.uniform(0, 100)),
        )  # fmt: skip
        parts = [head]
        extras = rng["extras"]
        if cfg.eyes:
            parts += eye_parts(self.assets, identity, vertices, extras, sample_iris_color(extras), R, t)
        if cfg.mouth:
            lip = albedo[self.assets.mouth_loop].mean(0) if self.assets.mouth_loop is not None else albedo.mean(0)
            parts += mouth_part(self.assets, vertices, extras, lip, R, t)
        if cfg.clothing:
            parts += clothing_part(self.assets, vertices, extras, R, t)
        style = hair_rng.random()
        if style < cfg.hair_probability:
            parts += hair_parts(self.assets, vertices, normals, hair_rng, hair_color, "hair", R, t)
        elif style < cfg.hair_probability + cfg.cap_probability:
            cap = srgb_to_linear(hair_rng.uniform(0.05, 0.9, size=3))
            parts += hair_parts(self.assets, vertices, normals, hair_rng, cap, "cap", R, t)
        with torch.no_grad():  # one sample at a time: the values never depend on the batch
            pixels = project_points(
                torch.from_numpy(vertices[model.landmark_indices.numpy()])[None], torch.from_numpy(rotation)[None],
                torch.from_numpy(translation)[None], torch.from_numpy(intrinsics)[None])[0][0].numpy()
        landmarks = (vertices[model.landmark_indices.numpy()].astype(np.float64) + t) @ R.T  # camera frame
        visible = self._visible(pixels, landmarks, float(intrinsics[0]), parts)
        if extras.random() < cfg.occluder_probability:
            head_size = float(np.ptp(vertices[self.assets.framing], axis=0).max())
            targets = landmarks[visible] if visible.any() else landmarks  # cover what the image shows
            occluders = occluder_parts(extras, targets, head_size, albedo.mean(0), int(extras.integers(1, 3)))
            parts += occluders
            visible &= ~_blocked(landmarks, occluders, 0.0)
        lighting = sample_lighting(rng["light"], cfg.num_lights, cfg.temperature)
        lighting = auto_exposure(lighting, head, rng["light"].uniform(*cfg.exposure))
        background = random_background(rng["background"], (cfg.image_size, cfg.image_size), self.photos,
                                       cfg.photo_probability)
        record = {"shape_coeffs": shape, "expression_coeffs": expression, "angles": angles, "rotation": rotation,
                  "translation": translation, "intrinsics": intrinsics, "landmarks": pixels,
                  "landmark_visible": visible}
        return _Plan(index=index, scene=TileScene(parts, intrinsics, lighting), background=background, record=record)

    # ------------------------------------------------------------------ after rendering

    def _finish(self, plans: list[_Plan], rendered: RenderedTiles) -> SynthBatch:
        model = self.model
        coverage = rendered.coverage.astype(np.float32)[..., None] / 255.0
        backgrounds = np.stack([p.background for p in plans]).astype(np.float32)
        images = np.clip(np.rint(rendered.color.astype(np.float32) + backgrounds * (1.0 - coverage)), 0, 255).astype(np.uint8)
        head = np.isin(rendered.labels, HEAD_LABELS)
        normals = np.where(head[..., None], rendered.normals, np.float32(0.0)).transpose(0, 3, 1, 2)
        record = {k: np.stack([p.record[k] for p in plans]) for k in plans[0].record}
        pixels, visible = record.pop("landmarks"), record.pop("landmark_visible")
        return SynthBatch(
            index=np.array([p.index for p in plans], dtype=np.int64),
            image=images,
            normals=np.ascontiguousarray(normals, dtype=np.float32),
            segmentation=rendered.labels,
            depth=rendered.depth,
            landmarks=pixels,
            landmark_visible=visible,
            shape_coeffs=record["shape_coeffs"],
            expression_coeffs=record["expression_coeffs"].reshape(len(plans), model.num_expressions),
            angles=record["angles"],
            rotation=record["rotation"],
            translation=record["translation"],
            intrinsics=record["intrinsics"],
        )

    def _visible(self, pixels: np.ndarray, landmarks: np.ndarray, focal: float, parts: list[MeshPart]) -> np.ndarray:
        """Landmarks ``(L,)`` whose nearest pixel lies in the image and that nothing in ``parts`` hides.

        A ray cast from the camera centre to each camera-frame landmark ``(L, 3)``
        (:func:`~facenormals.data.raycast.blocked_rays`): hair, headwear, clothing and occluders hide
        it wherever they cross the ray in front of it; the head surface (skin, eyes, mouth) only more
        than the slack in front of it, the larger of 3 mm and the lateral size of two pixels at its
        depth. The slack keeps landmarks in creases visible (an eye corner tucked a few mm behind
        its lids): a fold that shallow does not move where the image shows the landmark.
        """
        size = self.config.image_size
        u, v = np.rint(pixels[:, 0]), np.rint(pixels[:, 1])
        inside = np.isfinite(pixels).all(-1) & (u >= 0) & (u <= size - 1) & (v >= 0) & (v <= size - 1)
        slack = np.maximum(LANDMARK_DEPTH_SLACK_MM, 2.0 * landmarks[:, 2] / focal)
        head = [p for p in parts if p.label in HEAD_LABELS]
        others = [p for p in parts if p.label not in HEAD_LABELS]
        return inside & ~_blocked(landmarks, head, slack) & ~_blocked(landmarks, others, 0.0)

    def _empty(self) -> SynthBatch:
        s, k, e = self.config.image_size, self.model.num_shape, self.model.num_expressions
        n = len(self.model.landmark_indices)
        return SynthBatch(
            index=np.zeros(0, np.int64), image=np.zeros((0, s, s, 3), np.uint8), normals=np.zeros((0, 3, s, s), np.float32),
            segmentation=np.zeros((0, s, s), np.uint8), depth=np.zeros((0, s, s), np.float32),
            landmarks=np.zeros((0, n, 2), np.float32), landmark_visible=np.zeros((0, n), bool),
            shape_coeffs=np.zeros((0, k), np.float32), expression_coeffs=np.zeros((0, e), np.float32),
            angles=np.zeros((0, 3), np.float32), rotation=np.zeros((0, 3, 3), np.float32),
            translation=np.zeros((0, 3), np.float32), intrinsics=np.zeros((0, 3), np.float32),
        )  # fmt: skip


def _blocked(points: np.ndarray, parts: list[MeshPart], tolerance: float | np.ndarray) -> np.ndarray:
    """:func:`~facenormals.data.raycast.blocked_rays` of camera-frame ``points`` ``(P, 3)`` by the
    triangles of ``parts``, posed into the camera frame."""
    if not parts:
        return np.zeros(len(points), dtype=bool)
    vertices, faces, offset = [], [], 0
    for part in parts:
        rotation, translation = np.asarray(part.rotation, np.float64), np.asarray(part.translation, np.float64)
        vertices.append((part.vertices.astype(np.float64) + translation) @ rotation.T)
        faces.append(part.faces.astype(np.int64) + offset)
        offset += len(part.vertices)
    return blocked_rays(points, np.concatenate(vertices), np.concatenate(faces), tolerance)


def _check_int(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name}: expected a non-negative integer, got {value!r}")
    if int(value) < 0:
        raise ValueError(f"{name}: expected a non-negative integer, got {value}")
    return int(value)
