r"""Linear morphable models, :math:`X = X_0 + W y (+ E e)`."""

from __future__ import annotations

import json
import math
import warnings
import zipfile
import zlib
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from facenormals.core.check import (INWARD_SHARE, MILLIMETRE_SPAN, check_all_finite, check_faces, check_finite,
                                    check_floating, check_integer, check_positive, check_shape, check_tensor,
                                    outside_millimetre_span, outward_share)
from facenormals.core.files import atomic_write

__all__ = ["MorphableModel", "ModelFileError"]

# What reading a damaged .npz can raise: a bad zip directory or a member failing its CRC-32 check
# (BadZipFile), a truncated member or a damaged deflate stream (EOFError, zlib.error), a bad .npy header
# (ValueError), an unknown compression method (NotImplementedError).
NPZ_READ_ERRORS: tuple[type[BaseException], ...] = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error,
                                                    NotImplementedError)

_NPY_HEADERS = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}


def read_npz(path: str | Path, names: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` archive (all, or those of ``names`` it holds), each member checked whole.

    ``np.load`` reads the bytes a member's ``.npy`` header declares and stops there: a damaged header
    (a shape digit changed) loaded part of an array silently, and zip's CRC-32, checked only at a
    member's end, was never reached. Here each member's size must be its header's plus the declared
    data, and it is read to its end, so that a damaged byte anywhere in it fails the CRC-32 check.
    Arrays of Python objects are refused (nothing is unpickled). Reads each member once, in chunks.

    Raises:
        One of ``NPZ_READ_ERRORS`` for a damaged archive (the message names the member), e.g.
        ``zipfile.BadZipFile`` for a CRC mismatch, ``ValueError`` for a size that does not match the header.

    Example:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "a.npz"
        >>> np.savez(path, x=np.arange(6).reshape(2, 3), y=np.array("mm"))
        >>> {k: v.shape for k, v in read_npz(path).items()}
        {'x': (2, 3), 'y': ()}
    """
    arrays: dict[str, np.ndarray] = {}
    with zipfile.ZipFile(path) as archive:
        members = {info.filename.removesuffix(".npy"): info for info in archive.infolist()}
        for key in members if names is None else [n for n in names if n in members]:
            arrays[key] = _read_npy_member(archive, members[key])
    return arrays


def _read_npy_member(archive: zipfile.ZipFile, info: zipfile.ZipInfo) -> np.ndarray:
    with archive.open(info) as member:
        version = np.lib.format.read_magic(member)
        if version not in _NPY_HEADERS:
            raise ValueError(f"member {info.filename!r}: unsupported .npy format version {version}")
        shape, fortran_order, dtype = _NPY_HEADERS[version](member)
        if dtype.hasobject:
            raise ValueError(f"member {info.filename!r}: holds Python objects, which are not loaded")
        count = math.prod(shape)
        size = count * dtype.itemsize
        if info.file_size != member.tell() + size:
            raise ValueError(f"member {info.filename!r}: its .npy header declares {shape} {dtype} ({size} bytes of "
                             f"data), but the member holds {info.file_size - member.tell()} (a damaged header)")
        array = np.empty(count, dtype=dtype)
        view, done = memoryview(array.view(np.uint8)), 0
        while done < size:
            chunk = member.read(min(1 << 20, size - done))
            if not chunk:
                raise EOFError(f"member {info.filename!r}: ends after {done} of {size} bytes of data")
            view[done:done + len(chunk)] = chunk
            done += len(chunk)
        if member.read(1):  # also what makes zipfile check the CRC-32 of a member read exactly to its end
            raise ValueError(f"member {info.filename!r}: holds more data than its .npy header declares")
    if fortran_order:
        return array.reshape(shape[::-1]).transpose()
    return array.reshape(shape)

#: Radius in mm around the nose tip of the evaluation face region (the crop of common face-reconstruction
#: benchmarks): the built-in head's, ICT-FaceKit's and :meth:`MorphableModel.with_annotations`'s default.
FACE_CROP_RADIUS_MM = 95.0
FORMAT_NAME = "facenormals-morphable-model"
FORMAT_VERSION = 1
#: The arrays :meth:`MorphableModel.save` writes (and :meth:`MorphableModel.load` reads; others are ignored).
_MODEL_KEYS = ("format", "version", "name", "units", "mean", "shape_basis", "shape_std", "faces", "expression_basis",
               "expression_names", "landmark_names", "landmark_indices", "metadata", "face_region")


class ModelFileError(ValueError):
    """A model file is missing, corrupt, truncated or of the wrong layout. The message names the file."""


def check_model_dtype(dtype: object) -> None:
    """Raise ``ValueError`` unless ``dtype`` is a floating torch dtype (before a file is blamed for it)."""
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise ValueError(f"dtype: expected a floating-point torch dtype, got {dtype!r}")


def _version(tensor: Tensor) -> int | None:
    """``tensor._version``, the count of its in-place edits; ``None`` for an inference tensor (made
    under ``torch.inference_mode``), which keeps no count."""
    return None if tensor.is_inference() else tensor._version


class MorphableModel(nn.Module):
    r"""A linear shape model with optional expression blendshapes and named landmarks.

    Vertices are :math:`X = X_0 + \sum_k y_k W_k + \sum_j e_j E_j`. Lengths are in mm and the model
    frame is the one of ``docs/conventions.md`` (face along −z, y down). All arrays are registered as
    buffers, so ``.to(device, dtype)`` moves them.

    Every buffer is built on ``mean``'s device and the floating ones in its dtype: arguments on another
    device (e.g. ``faces`` or ``shape_std`` on the CPU with a CUDA ``mean``) are moved there after
    their checks, and the defaults are created there.

    Args:
        mean: the mean shape :math:`X_0`.
        shape_basis: the shape components :math:`W_k`, one per coefficient.
        faces: triangles, counter-clockwise seen from outside.
        shape_std: the standard deviation :math:`\sigma_k` of each shape coefficient (default 1). The
            shape prior is :math:`\tfrac12 \sum_k (y_k / \sigma_k)^2`.
        expression_basis: optional expression blendshapes :math:`E_j`.
        landmarks: optional mapping from landmark name to vertex index.
        expression_names: optional names of the expression blendshapes.
        name: a short name shown in ``repr`` and saved with the model.
        metadata: JSON-serialisable extra information (source, licence, ...).
        face_region: optional ``(N,)`` bool mask of the face area used by evaluation (default: all
            vertices).

    Raises:
        ValueError: if the arrays have inconsistent shapes, hold NaN or infinite values, indices are out
            of range, the mean's triangles face inward (wound clockwise seen from outside), or
            ``metadata`` holds values JSON cannot store.

    Shape:
        - mean: :math:`(N, 3)`; shape_basis: :math:`(K, N, 3)`; faces: :math:`(F, 3)`
        - shape_std: :math:`(K,)`; expression_basis: :math:`(E, N, 3)`
        - forward: shape_coeffs :math:`(B, K)`, expression_coeffs :math:`(B, E)` → :math:`(B, N, 3)`

    Example:
        >>> mean = torch.zeros(4, 3); basis = torch.randn(2, 4, 3)
        >>> model = MorphableModel(mean, basis, torch.tensor([[0, 1, 2], [0, 2, 3]]))
        >>> model(torch.zeros(5, 2)).shape
        torch.Size([5, 4, 3])
    """

    mean: Tensor
    shape_basis: Tensor
    shape_std: Tensor
    faces: Tensor
    expression_basis: Tensor
    landmark_indices: Tensor
    face_region: Tensor

    def __init__(
        self,
        mean: Tensor,
        shape_basis: Tensor,
        faces: Tensor,
        shape_std: Tensor | None = None,
        expression_basis: Tensor | None = None,
        landmarks: Mapping[str, int] | None = None,
        expression_names: Sequence[str] | None = None,
        name: str = "model",
        metadata: Mapping[str, object] | None = None,
        face_region: Tensor | None = None,
    ) -> None:
        super().__init__()
        mean, shape_basis, faces = (torch.as_tensor(x) for x in (mean, shape_basis, faces))
        dims = check_shape(mean, ["N", 3], "mean")
        check_floating(mean, "mean")
        check_shape(shape_basis, ["K", "N", 3], "shape_basis", dims)
        check_floating(shape_basis, "shape_basis")
        num_vertices = dims["N"]
        if check_faces(faces, num_vertices)["F"] == 0:  # no surface: empty normal maps, a landmarks-only fit
            raise ValueError(f"faces: expected at least one triangle, got shape {tuple(faces.shape)}")
        dtype, device = mean.dtype, mean.device
        faces = faces.to(device=device, dtype=torch.long)  # checked: every buffer lives on mean's device
        check_finite(mean, "mean")
        check_finite(shape_basis, "shape_basis")
        outward = outward_share(mean, faces)
        if outward < INWARD_SHARE:  # inward normals: the fit would match them to no normal map, silently
            raise ValueError(
                f"faces: the mean's triangles face inward (their normals point towards its centre over "
                f"{50 * (1 - outward):.0f} % of its area): they are wound clockwise seen from outside, facenormals "
                "expects counter-clockwise (docs/conventions.md); reverse them (faces[:, [0, 2, 1]])"
            )
        if shape_std is None:
            shape_std = torch.ones(dims["K"], dtype=dtype, device=device)
        shape_std = torch.as_tensor(shape_std, dtype=dtype)
        check_shape(shape_std, ["K"], "shape_std", dims)
        if shape_std.numel() and not bool((shape_std > 0).all() & torch.isfinite(shape_std).all()):
            raise ValueError("shape_std: expected positive finite standard deviations")
        if expression_basis is None:
            expression_basis = torch.zeros(0, num_vertices, 3, dtype=dtype, device=device)
        expression_basis = torch.as_tensor(expression_basis)
        check_shape(expression_basis, ["E", "N", 3], "expression_basis", dims)
        check_floating(expression_basis, "expression_basis")
        check_finite(expression_basis, "expression_basis")
        landmarks = dict(landmarks or {})
        for key, index in landmarks.items():
            index = landmarks[key] = check_integer(index, f"landmarks[{key!r}]")  # int() would truncate 2.7
            if not 0 <= index < num_vertices:
                raise ValueError(f"landmarks: index {index} of {key!r} is outside [0, {num_vertices})")
        names = list(expression_names) if expression_names is not None else []
        if names and len(names) != expression_basis.shape[0]:
            raise ValueError(
                f"expression_names: expected {expression_basis.shape[0]} names, got {len(names)}"
            )
        if face_region is None:
            face_region = torch.ones(num_vertices, dtype=torch.bool, device=device)
        face_region = torch.as_tensor(face_region)
        check_shape(face_region, ["N"], "face_region", dims)
        if face_region.dtype != torch.bool:
            raise ValueError(f"face_region: expected a bool tensor, got dtype {face_region.dtype}")
        metadata = dict(metadata or {})
        try:
            json.dumps(metadata)  # saved as JSON
        except (TypeError, ValueError) as error:
            raise ValueError(f"metadata: expected JSON values (str, int, float, bool, None, lists, dicts), "
                             f"got {error}") from None
        self.name = name
        self.metadata = metadata
        self.landmark_names = list(landmarks)
        self.expression_names = names
        self.register_buffer("mean", mean.contiguous())
        self.register_buffer("shape_basis", shape_basis.to(device=device, dtype=dtype).contiguous())
        self.register_buffer("shape_std", shape_std.to(device).contiguous())
        self.register_buffer("expression_basis", expression_basis.to(device=device, dtype=dtype).contiguous())
        self.register_buffer("faces", faces.contiguous())
        self.register_buffer(
            "landmark_indices", torch.tensor([int(i) for i in landmarks.values()], dtype=torch.long, device=device)
        )
        self.register_buffer("face_region", face_region.to(device).contiguous())

    @property
    def num_vertices(self) -> int:
        return self.mean.shape[0]

    @property
    def num_shape(self) -> int:
        return self.shape_basis.shape[0]

    @property
    def num_expressions(self) -> int:
        return self.expression_basis.shape[0]

    @property
    def landmarks(self) -> dict[str, int]:
        """Landmark name → vertex index."""
        return dict(zip(self.landmark_names, self.landmark_indices.tolist()))

    def forward(self, shape_coeffs: Tensor, expression_coeffs: Tensor | None = None) -> Tensor:
        """Vertices of the heads with the given coefficients; see the class docstring for shapes.

        Raises:
            ValueError: if a coefficient tensor has the wrong shape, dtype or device, or holds NaN or
                infinite values.
        """
        dims = check_shape(shape_coeffs, ["B", self.num_shape], "shape_coeffs")
        self._check_coeffs(shape_coeffs, "shape_coeffs")
        batch = dims["B"]
        if expression_coeffs is not None:
            check_shape(expression_coeffs, ["B", self.num_expressions], "expression_coeffs", dims)
            self._check_coeffs(expression_coeffs, "expression_coeffs")
            check_all_finite(shape_coeffs=shape_coeffs, expression_coeffs=expression_coeffs)  # one sync
        else:
            check_finite(shape_coeffs, "shape_coeffs")
        flat = self.mean.reshape(1, -1).expand(batch, -1)
        # explicit sizes: a model without shape components (K = 0) has nothing to infer -1 from
        vertices = torch.addmm(flat, shape_coeffs, self.shape_basis.reshape(self.num_shape, 3 * self.num_vertices))
        if expression_coeffs is not None and self.num_expressions:
            vertices = torch.addmm(
                vertices, expression_coeffs, self.expression_basis.reshape(self.num_expressions, -1)
            )
        return vertices.reshape(batch, self.num_vertices, 3)

    def _check_coeffs(self, coeffs: Tensor, name: str) -> None:
        check_floating(coeffs, name)
        if coeffs.dtype != self.mean.dtype or coeffs.device != self.mean.device:
            raise ValueError(f"{name}: expected dtype {self.mean.dtype} on {self.mean.device} as the model "
                             f"(convert the model with .to()), got {coeffs.dtype} on {coeffs.device}")

    def basis_matrix(self, with_expression: bool = False, dtype: torch.dtype | None = None) -> Tensor:
        r"""The basis as a Jacobian: row ``3 i + j`` holds :math:`\partial X_{ij} / \partial (y, e)`.

        Fitting code multiplies per-vertex derivative blocks with these rows, which needs them
        contiguous per vertex; the transposed copy (13 MB for ICT in float32) is made once per
        ``dtype`` (default: the model's, e.g. float32 for float32 normal equations of a float64
        model) and reused until a buffer changes (``.to()``, in-place edits).

        The result is that cached tensor, shared by every call (no copy on this hot path): treat it as
        read-only. An in-place edit of it (``J.zero_()``) is detected and the next call rebuilds it,
        but other holders of the tensor see the edit; ``.clone()`` it to modify it.

        Shape:
            - output: :math:`(3N, K)`, or :math:`(3N, K + E)` with ``with_expression``

        Example:
            >>> model = MorphableModel(torch.zeros(4, 3), torch.randn(2, 4, 3), torch.tensor([[0, 1, 2]]))
            >>> J = model.basis_matrix()
            >>> J.shape, bool((J[3 * 1 + 2] == model.shape_basis[:, 1, 2]).all())
            (torch.Size([12, 2]), True)
        """
        parts = [self.shape_basis] + ([self.expression_basis] if with_expression else [])
        if dtype is not None:
            check_model_dtype(dtype)
        dtype = dtype or self.shape_basis.dtype
        columns = sum(p.shape[0] for p in parts)  # explicit: (3N, -1) is ambiguous with no component at all
        return self._derived(("basis_matrix", with_expression, dtype), parts, lambda: torch.cat(
            [p.permute(1, 2, 0) for p in parts], dim=-1).reshape(3 * self.num_vertices, columns).to(dtype).contiguous())

    def mean_normals(self) -> Tensor:
        """``(N, 3)`` outward unit vertex normals of the mean shape (model frame); computed once and
        reused until a buffer changes.

        The result is that cached tensor, shared by every call: treat it as read-only (an in-place
        edit is detected and the next call rebuilds it, but other holders see the edit).

        Example:
            >>> from facenormals.models import builtin_head_model
            >>> builtin_head_model().mean_normals().shape
            torch.Size([10242, 3])
        """
        from facenormals.mesh.normals import vertex_normals

        return self._derived("mean_normals", (self.mean, self.faces),
                             lambda: vertex_normals(self.mean[None], self.faces)[0])

    def landmark_normals(self) -> Tensor:
        """``(L, 3)`` outward unit vertex normals of the mean shape at the landmarks (model frame), e.g.
        for :func:`~facenormals.fitting.prealign_pose`'s ``model_normals``; computed once and reused
        until a buffer changes; like :meth:`mean_normals`, a shared cached tensor to treat as read-only.

        Example:
            >>> from facenormals.models import builtin_head_model
            >>> model = builtin_head_model()
            >>> float(model.landmark_normals()[model.landmark_names.index("nose_tip"), 2]) < -0.9  # -z: forward
            True
        """
        return self._derived("landmark_normals", (self.mean, self.faces, self.landmark_indices),
                             lambda: self.mean_normals()[self.landmark_indices])

    def landmark_faces(self) -> Tensor:
        """``(F_L, 3)`` the triangles around the landmark vertices: ``vertex_normals(vertices,
        model.landmark_faces())`` is exact at the landmarks of any shape (and 0 where no such triangle
        reaches) at a fraction of the whole mesh's cost; computed once and reused until a buffer
        changes, a shared cached tensor to treat as read-only.

        Example:
            >>> from facenormals.mesh import vertex_normals
            >>> from facenormals.models import builtin_head_model
            >>> model = builtin_head_model()
            >>> index = model.landmark_indices
            >>> exact = vertex_normals(model.mean[None], model.faces)[0, index]
            >>> bool(torch.allclose(vertex_normals(model.mean[None], model.landmark_faces())[0, index], exact))
            True
        """
        return self._derived("landmark_faces", (self.faces, self.landmark_indices),
                             lambda: self.faces[torch.isin(self.faces, self.landmark_indices).any(1)])

    def _derived(self, slot: object, sources: Sequence[Tensor], build: Callable[[], Tensor]) -> Tensor:
        """``build()``, kept under ``slot`` until one of its ``sources`` changes: is replaced (``.to()``,
        assignment) or edited in place (its ``_version``), or the result itself is edited in place by a
        caller (``J.zero_()``; its ``_version`` too). The entry holds the sources themselves, so that a
        new tensor can never pass for a freed one that had its ``id``."""
        cache = self.__dict__.setdefault("_derived_cache", {})
        entry = cache.get(slot)
        if entry is None or entry[2] != _version(entry[1]) or len(entry[0]) != len(sources) or any(
                old is not p or version != _version(p) for (old, version), p in zip(entry[0], sources)):
            result = build()
            entry = cache[slot] = (tuple((p, _version(p)) for p in sources), result, _version(result))
        return entry[1]

    def _apply(self, fn, *args, **kwargs):
        self.__dict__.pop("_derived_cache", None)  # .to() / .double(): the cache would keep the old buffers alive
        return super()._apply(fn, *args, **kwargs)

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state.pop("_derived_cache", None)  # derived data, rebuilt on demand; not worth pickling
        return state

    def landmark_vertices(self, vertices: Tensor, names: Sequence[str] | None = None) -> Tensor:
        """Pick the landmark vertices ``(B, L, 3)`` out of ``vertices`` ``(B, N, 3)`` (all, or ``names``)."""
        check_shape(vertices, ["B", self.num_vertices, 3], "vertices")
        if names is None:
            index = self.landmark_indices
        else:
            lookup = self.landmarks
            missing = [n for n in names if n not in lookup]
            if missing:
                raise ValueError(f"names: unknown landmarks {missing}; the model has {self.landmark_names}")
            index = torch.tensor([lookup[n] for n in names], dtype=torch.long, device=vertices.device)
        return vertices[:, index]

    def sample_shape_coeffs(self, batch: int, scale: float = 1.0, generator: torch.Generator | None = None) -> Tensor:
        """Random coefficients :math:`y_k \\sim \\mathcal{N}(0, (\\text{scale}\\,\\sigma_k)^2)` of shape ``(B, K)``."""
        if isinstance(batch, bool) or not isinstance(batch, int) or batch < 0:
            raise ValueError(f"batch: expected a non-negative integer, got {batch!r}")
        if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale >= 0):
            raise ValueError(f"scale: expected a finite number >= 0, got {scale!r}")
        if generator is not None and not isinstance(generator, torch.Generator):
            raise ValueError(f"generator: expected a torch.Generator or None, got {type(generator).__name__}")
        noise = torch.randn(batch, self.num_shape, generator=generator, dtype=self.shape_std.dtype)
        return noise.to(self.shape_std.device) * (scale * self.shape_std)

    def export_mesh(self, path: str | Path, shape_coeffs: Tensor | None = None) -> None:
        """Write the mean head, or the head with ``shape_coeffs`` ``(K,)``/``(1, K)``, as ``.ply`` or ``.obj``."""
        from facenormals.mesh.io import save_mesh

        if Path(path).suffix.lower() not in (".ply", ".obj"):
            raise ValueError(f"path: expected a .ply or .obj file, got {str(path)!r}")
        if shape_coeffs is None:
            vertices = self.mean
        else:
            check_tensor(shape_coeffs, "shape_coeffs")
            if tuple(shape_coeffs.shape) not in ((self.num_shape,), (1, self.num_shape)):
                raise ValueError(f"shape_coeffs: expected shape ({self.num_shape},) or (1, {self.num_shape}), "
                                 f"got {tuple(shape_coeffs.shape)}")
            vertices = self(shape_coeffs.reshape(1, -1).to(self.mean))[0]
        save_mesh(path, vertices, self.faces)

    def check_millimetres(self) -> None:
        """Raise ``ValueError`` unless the mean head has the size of a face or head in millimetres.

        Every length in facenormals is in mm (docs/conventions.md): depth slacks, the 95 mm face
        region, ICP cut-offs, reported errors. A model in metres (or centimetres) would be accepted
        by the maths and give wrong results labelled mm, so the fit, the landmark z-buffer and the
        synthetic-data generator call this first. The test is the diagonal of the mean's bounding
        box: 50 to 5,000 units passes (a face crop spans about 200 mm, a head with neck about 400).

        Example:
            >>> from facenormals.models import builtin_head_model
            >>> head = builtin_head_model()
            >>> head.check_millimetres()
            >>> MorphableModel(head.mean / 1000, head.shape_basis / 1000, head.faces, name="m").check_millimetres()
            Traceback (most recent call last):
            ...
            ValueError: model 'm': its mean spans 0.367 units across, not the 50-5000 of a face or head in millimetres; facenormals works in mm (a model in metres needs its mean and bases times 1000, docs/models.md)
        """
        span = outside_millimetre_span(self.mean)  # never empty: a model has at least one triangle
        if span is not None:
            low, high = MILLIMETRE_SPAN
            raise ValueError(
                f"model {self.name!r}: its mean spans {span:.3g} units across, not the {low:g}-{high:g} of a face or "
                "head in millimetres; facenormals works in mm (a model in metres needs its mean and bases times 1000, "
                "docs/models.md)"
            )

    def with_annotations(self, landmarks: Mapping[str, int], face_region: Tensor | None = None,
                         radius: float = FACE_CROP_RADIUS_MM) -> "MorphableModel":
        """A copy with named landmarks (and a face region) attached: what a model brought from LYHM,
        BFM or FLAME files needs before the pipeline can use it.

        Args:
            landmarks: landmark name → vertex index; the network's are
                :data:`~facenormals.models.LANDMARK_NAMES` (at least 4 of them to pre-align, all 24
                to use every detection).
            face_region: ``(N,)`` bool mask scored by evaluation; default: the vertices within
                ``radius`` mm of the ``nose_tip`` landmark (the crop of common benchmarks) whose
                normals face forward (−z), or this model's region without a ``nose_tip``.
            radius: the default region's radius in mm.

        Raises:
            ValueError: on an index outside the mesh, or on mirrored pairs: a ``right_*`` landmark
                that does not lie at −x of its ``left_*`` twin (the subject's right; image-sense
                names would fit a head turned away from the camera).

        Example:
            >>> from facenormals.models import builtin_head_model
            >>> head = builtin_head_model()
            >>> bare = MorphableModel(head.mean, head.shape_basis, head.faces, shape_std=head.shape_std)
            >>> model = bare.with_annotations(head.landmarks)
            >>> len(model.landmark_names), int((model.face_region != head.face_region).sum()) < 200
            (24, True)
        """
        from facenormals.mesh import vertex_normals
        from facenormals.models.landmarks import LANDMARK_NAMES, LANDMARK_PAIRS

        landmarks = dict(landmarks)
        unknown = [name for name in landmarks if name not in LANDMARK_NAMES]
        if unknown:  # a typo would silently never be detected, or change the face region
            warnings.warn(f"landmarks: {unknown} are not among the network's LANDMARK_NAMES: the network never "
                          "detects them (they still work with landmarks you pass to fit_head yourself)", stacklevel=2)
        if face_region is None and "nose_tip" not in landmarks:
            warnings.warn("landmarks: no 'nose_tip', so the face region scored by evaluation stays the model's own "
                          f"({int(self.face_region.sum())} of {self.num_vertices} vertices); pass face_region or "
                          "name the nose tip", stacklevel=2)
        elif face_region is None:
            radius = check_positive(radius, "radius")
            nose = check_integer(landmarks["nose_tip"], "landmarks['nose_tip']")
            if not 0 <= nose < self.num_vertices:
                raise ValueError(f"landmarks: index {nose} of 'nose_tip' is outside [0, {self.num_vertices})")
            self.check_millimetres()  # the radius is in mm
            mean = self.mean.double()
            near = (mean - mean[nose]).norm(dim=-1) < radius
            facing = vertex_normals(mean[None], self.faces)[0, :, 2] < 0
            face_region = near & facing
        model = MorphableModel(self.mean, self.shape_basis, self.faces, shape_std=self.shape_std,
                               expression_basis=self.expression_basis, landmarks=landmarks,
                               expression_names=self.expression_names or None, name=self.name,
                               metadata=self.metadata,
                               face_region=self.face_region if face_region is None else face_region)
        # The subject's right is at -x (docs/conventions.md): mirrored names fit a head turned away
        # from the camera, "converged" with sub-pixel landmark errors.
        x, index = model.mean[:, 0], model.landmarks
        mirrored = [f"{right}/{left}" for right, left in LANDMARK_PAIRS
                    if right in index and left in index and not float(x[index[right]]) < float(x[index[left]])]
        if mirrored:
            raise ValueError(f"landmarks: {', '.join(mirrored)} are mirrored: the subject's right lies at -x of the "
                             "left in the model frame (x towards the subject's left, docs/conventions.md), and "
                             "these 'right' vertices are not; right and left are the subject's, not the image's "
                             "(swap the names), or the model's geometry is mirrored")
        return model

    def extra_repr(self) -> str:
        return (
            f"name={self.name!r}, vertices={self.num_vertices}, faces={self.faces.shape[0]}, "
            f"shape={self.num_shape}, expressions={self.num_expressions}, landmarks={len(self.landmark_names)}"
        )

    def save(self, path: str | Path) -> None:
        """Write the model to ``path`` in the facenormals ``.npz`` format (see docs/models.md)."""
        arrays: dict[str, np.ndarray] = {
            "format": np.array(FORMAT_NAME),
            "version": np.array(FORMAT_VERSION),
            "name": np.array(self.name),
            "units": np.array("mm"),
            "mean": self.mean.detach().cpu().numpy(),
            "shape_basis": self.shape_basis.detach().cpu().numpy(),
            "shape_std": self.shape_std.detach().cpu().numpy(),
            "faces": self.faces.detach().cpu().numpy().astype(np.int64),
            "expression_basis": self.expression_basis.detach().cpu().numpy(),
            "expression_names": np.array(self.expression_names, dtype=str),
            "landmark_names": np.array(self.landmark_names, dtype=str),
            "landmark_indices": self.landmark_indices.cpu().numpy(),
            "metadata": np.array(json.dumps(self.metadata)),
            "face_region": self.face_region.cpu().numpy(),
        }
        with atomic_write(path) as part, open(part, "wb") as handle:
            np.savez(handle, **arrays)

    @classmethod
    def load(cls, path: str | Path, dtype: torch.dtype = torch.float32) -> "MorphableModel":
        """Read a model written by :meth:`save`.

        Raises:
            ModelFileError: if the file is missing, not an ``.npz`` archive, truncated, or lacks keys.
        """
        check_model_dtype(dtype)
        path = Path(path)
        if not path.exists():
            raise ModelFileError(f"{path}: model file not found")
        required = ["format", "version", "mean", "shape_basis", "shape_std", "faces"]
        try:  # every member read whole, CRC-checked (np.load stopped where a damaged header said)
            arrays = read_npz(path, _MODEL_KEYS)
        except NPZ_READ_ERRORS as error:
            raise ModelFileError(f"{path}: cannot read model file ({type(error).__name__}: {error})") from error
        missing = [k for k in required if k not in arrays]
        if missing:
            raise ModelFileError(f"{path}: not a facenormals model file, missing keys {missing}")
        if str(arrays["format"]) != FORMAT_NAME:
            raise ModelFileError(f"{path}: format is {str(arrays['format'])!r}, expected {FORMAT_NAME!r}")
        version = arrays["version"]
        if version.ndim != 0 or version.dtype.kind not in "iu":
            raise ModelFileError(f"{path}: format version {version.tolist()!r}, expected an integer")
        if int(version) > FORMAT_VERSION:
            raise ModelFileError(f"{path}: format version {int(version)} is newer than supported")
        if int(version) < 1:
            raise ModelFileError(f"{path}: format version {int(version)}, expected 1 to {FORMAT_VERSION}")
        for key in ("landmark_names", "landmark_indices", "expression_names"):  # a 0-d array is no list
            if key in arrays and arrays[key].ndim != 1:
                raise ModelFileError(f"{path}: array {key!r} has shape {arrays[key].shape}, expected a 1-D list")
        names = [str(n) for n in arrays.get("landmark_names", np.array([], dtype=str))]
        indices = arrays.get("landmark_indices", np.zeros(0, dtype=np.int64)).tolist()
        if len(names) != len(indices) or len(set(names)) != len(names):
            raise ModelFileError(f"{path}: {len(names)} landmark names (distinct: {len(set(names))}) for "
                                 f"{len(indices)} landmark indices")
        if "units" in arrays and str(arrays["units"]) != "mm":
            raise ModelFileError(f"{path}: units {str(arrays['units'])!r}, expected 'mm'")
        for key, kind in (("mean", "f"), ("shape_basis", "f"), ("shape_std", "f"), ("expression_basis", "f"),
                          ("faces", "iu"), ("face_region", "b")):
            if key in arrays and arrays[key].dtype.kind not in kind:
                expected = {"f": "floating-point", "iu": "integer", "b": "bool"}[kind]
                raise ModelFileError(f"{path}: array {key!r} has dtype {arrays[key].dtype}, expected {expected}")
        try:
            return cls(
                torch.from_numpy(arrays["mean"]).to(dtype),
                torch.from_numpy(arrays["shape_basis"]).to(dtype),
                torch.from_numpy(arrays["faces"].astype(np.int64)),
                shape_std=torch.from_numpy(arrays["shape_std"]).to(dtype),
                expression_basis=torch.from_numpy(arrays["expression_basis"]).to(dtype)
                if "expression_basis" in arrays
                else None,
                landmarks=dict(zip(names, indices)),
                expression_names=[str(n) for n in arrays.get("expression_names", [])] or None,
                name=str(arrays.get("name", path.stem)),
                metadata=json.loads(str(arrays.get("metadata", "{}"))),
                face_region=torch.from_numpy(arrays["face_region"]) if "face_region" in arrays else None,
            )
        except (ValueError, TypeError) as error:
            raise ModelFileError(f"{path}: inconsistent model arrays: {error}") from error
