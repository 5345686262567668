"""Input checks shared by every public op.

All checks raise :class:`ValueError` with a message that names the argument, the expected
shape and the received one, e.g.::

    points: expected shape (B, N, 3), got (2, 5, 4)
"""

from __future__ import annotations

import math
import operator
import os
from numbers import Real
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import Tensor
from torch._C._functorch import is_functorch_wrapped_tensor  # private; what torch.func itself asks

__all__ = [
    "check_all_finite",
    "check_device",
    "check_faces",
    "check_file_name",
    "check_finite",
    "check_flag",
    "check_floating",
    "check_folder_name",
    "check_image_size",
    "check_integer",
    "check_nonnegative",
    "check_real",
    "check_same_dims",
    "check_same_dtype_device",
    "check_shape",
    "check_tensor",
    "check_unit_range",
    "environment_integer",
    "outward_share",
    "outside_millimetre_span",
]

#: Bounding-box diagonal, in mm, of anything facenormals measures (a face crop spans about 200, a
#: head with neck about 400); outside it, lengths are almost surely in metres or centimetres.
MILLIMETRE_SPAN = (50.0, 5000.0)


def _format_shape(shape: Sequence[str | int]) -> str:
    items = [str(s) for s in shape]
    return "(" + ", ".join(items) + ("," if len(items) == 1 else "") + ")"


def check_file_name(value: object, name: str) -> Path:
    """``value`` as a ``Path`` to write a file to, or ``ValueError`` naming ``name`` unless it is a
    non-empty ``str`` / ``os.PathLike`` that is no folder and lies under no file (``""`` is the working
    folder: writing it failed with ``OSError: Device or resource busy``, a folder with
    ``IsADirectoryError``, deep in the writer).

    Example:
        >>> check_file_name("weights.pt", "out").name
        'weights.pt'
        >>> check_file_name("", "out")
        Traceback (most recent call last):
        ...
        ValueError: out: expected a file name (str or os.PathLike), got ''
    """
    if not (isinstance(value, (str, os.PathLike)) and str(value)):
        raise ValueError(f"{name}: expected a file name (str or os.PathLike), got {value!r}")
    path = Path(value)
    if path.is_dir():
        raise ValueError(f"{name}: {path} is a folder; give a file name")
    blocking = next((p for p in path.parents if p.exists() and not p.is_dir()), None)
    if blocking is not None:
        raise ValueError(f"{name}: {path} cannot be written: {blocking} is a file, not a folder")
    return path


def check_flag(value: object, name: str) -> bool:
    """``value`` as a ``bool``, or ``ValueError`` naming ``name`` unless it is ``True`` or ``False`` (a
    NumPy bool too): a string such as ``"no"`` is truthy and would switch the option on.

    Example:
        >>> check_flag(False, "verbose")
        False
        >>> check_flag("no", "verbose")
        Traceback (most recent call last):
        ...
        ValueError: verbose: expected True or False, got 'no'
    """
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name}: expected True or False, got {value!r}")
    return bool(value)


def check_folder_name(value: object, name: str) -> None:
    """Raise ``ValueError`` naming ``name`` unless ``value`` is ``None`` or a non-empty ``str`` /
    ``os.PathLike`` (``Path("")`` is the working folder: a mistaken empty name would write there).

    Example:
        >>> check_folder_name("out", "out_dir")
        >>> check_folder_name("", "out_dir")
        Traceback (most recent call last):
        ...
        ValueError: out_dir: expected a folder name or None, got ''
    """
    if value is not None and not (isinstance(value, (str, os.PathLike)) and str(value)):
        raise ValueError(f"{name}: expected a folder name or None, got {value!r}")


def check_device(device: object, name: str = "device", hint: str = "") -> torch.device:
    """The ``torch.device`` that ``device`` names, or ``ValueError`` naming ``name`` unless it is a CPU
    or CUDA device (a ``str`` such as ``"cpu"``, ``"cuda"``, ``"cuda:1"``, or a ``torch.device``) and,
    for CUDA, this torch build has one. ``hint`` ends the message about a missing CUDA device (e.g.
    which option to use instead). Checked before work starts: torch's own error comes from the first
    tensor moved, after the files are read.

    Example:
        >>> check_device("cpu")
        device(type='cpu')
        >>> check_device("mps")
        Traceback (most recent call last):
        ...
        ValueError: device: expected 'cpu', 'cuda' or 'cuda:N', got 'mps'
    """
    try:
        parsed = torch.device(device)  # type: ignore[arg-type]
    except (RuntimeError, TypeError):
        parsed = None
    if parsed is None or parsed.type not in ("cpu", "cuda"):
        raise ValueError(f"{name}: expected 'cpu', 'cuda' or 'cuda:N', got {device!r}")
    if parsed.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"{name}: {device!r} requested but this torch build ({torch.__version__}) has no CUDA "
                         f"device{hint}")
    return parsed


def check_unit_range(images: Tensor, name: str) -> None:
    """Raise ``ValueError`` naming ``name`` unless ``images`` are finite and in ``[0, 1]`` (up to 1e-3),
    e.g. RGB images scaled from 8 bits: 0-255 values or ``inf`` would otherwise be clamped to white, or
    find nothing, silently. One device synchronisation (``aminmax`` propagates NaN); skipped while
    ``torch.compile`` traces and under ``torch.func``.

    Example:
        >>> check_unit_range(torch.tensor([0.0, 0.5, 1.0]), "images")
        >>> check_unit_range(torch.tensor([0.0, 255.0]), "images")
        Traceback (most recent call last):
        ...
        ValueError: images: expected RGB values in [0, 1] (an 8-bit image / 255), got values in [0, 255]
    """
    if not images.numel() or not values_readable(images):
        return
    low, high = torch.aminmax(images.detach())
    low, high = torch.stack([low, high]).float().tolist()
    if low >= -1e-3 and high <= 1.0 + 1e-3:
        return
    check_finite(images, name)
    raise ValueError(f"{name}: expected RGB values in [0, 1] (an 8-bit image / 255), got values in [{low:g}, {high:g}]")


def check_tensor(x: object, name: str) -> None:
    """Raise ``ValueError`` unless ``x`` is a :class:`torch.Tensor`."""
    if not isinstance(x, Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")


def check_shape(
    x: object,
    shape: Sequence[str | int],
    name: str,
    dims: dict[str, int] | None = None,
) -> dict[str, int]:
    """Check the shape of ``x`` against a pattern of named and fixed dimensions.

    Args:
        x: the tensor to check.
        shape: the expected shape. Integers must match exactly, strings name a dimension
            (the same name must have the same size everywhere it appears) and a leading
            ``"*"`` matches any number of leading dimensions.
        name: the argument name used in error messages.
        dims: sizes bound by earlier checks (e.g. ``{"B": 4}``); new bindings are added to it
            in place, so that one dictionary checks consistency across several arguments.

    Returns:
        The dictionary of bound dimension sizes.

    Raises:
        ValueError: if ``x`` is not a tensor or its shape does not match.

    Example:
        >>> dims = check_shape(torch.zeros(2, 5, 3), ["B", "N", 3], "points")
        >>> dims
        {'B': 2, 'N': 5}
        >>> check_shape(torch.zeros(3, 4), ["B", 4], "other", dims)
        Traceback (most recent call last):
        ...
        ValueError: other: expected shape (B, 4) with B=2 (as bound by an earlier argument), got (3, 4)
    """
    check_tensor(x, name)
    bound = {} if dims is None else dims
    pattern = list(shape)
    got = tuple(x.shape)
    got_str = _format_shape(got)
    if pattern and pattern[0] == "*":
        tail = pattern[1:]
        if len(got) < len(tail):
            raise ValueError(f"{name}: expected shape {_format_shape(pattern)}, got {got_str}")
        got_tail = got[len(got) - len(tail):]
    else:
        tail = pattern
        if len(got) != len(tail):
            raise ValueError(
                f"{name}: expected shape {_format_shape(pattern)} ({len(tail)} dimensions), "
                f"got {got_str} ({len(got)} dimensions)"
            )
        got_tail = got
    new: dict[str, int] = {}
    for want, size in zip(tail, got_tail):
        if isinstance(want, int):
            if size != want:
                raise ValueError(f"{name}: expected shape {_format_shape(pattern)}, got {got_str}")
        elif want in bound:
            if size != bound[want]:
                raise ValueError(
                    f"{name}: expected shape {_format_shape(pattern)} with {want}={bound[want]} "
                    f"(as bound by an earlier argument), got {got_str}"
                )
        elif want in new:
            if size != new[want]:
                raise ValueError(
                    f"{name}: expected shape {_format_shape(pattern)} with equal {want} dimensions, "
                    f"got {got_str}"
                )
        else:
            new[want] = size
    bound.update(new)
    return bound


def check_same_dims(dims: dict[str, int], name: str, **expected: int) -> None:
    """Check that named dimensions bound by :func:`check_shape` have given sizes."""
    for key, value in expected.items():
        if dims.get(key) != value:
            raise ValueError(f"{name}: expected {key}={value}, got {key}={dims.get(key)}")


def check_same_dtype_device(reference: Tensor, reference_name: str, **tensors: Tensor) -> None:
    """Raise ``ValueError`` naming the first of ``tensors`` whose dtype or device differs from
    ``reference``'s (torch would raise a RuntimeError deep inside, or silently promote).

    Example:
        >>> check_same_dtype_device(torch.zeros(2), "points", rotation=torch.zeros(2, dtype=torch.float64))
        Traceback (most recent call last):
        ...
        ValueError: rotation: expected dtype torch.float32 (the dtype of points), got torch.float64
    """
    for name, x in tensors.items():
        if x.dtype != reference.dtype:
            raise ValueError(f"{name}: expected dtype {reference.dtype} (the dtype of {reference_name}), got {x.dtype}")
        if x.device != reference.device:
            raise ValueError(f"{name}: expected device {reference.device} (the device of {reference_name}), got {x.device}")


def check_floating(x: Tensor, name: str) -> None:
    """Raise ``ValueError`` unless ``x`` is a tensor with a floating-point dtype."""
    check_tensor(x, name)
    if not torch.is_floating_point(x):
        raise ValueError(f"{name}: expected a floating-point tensor, got dtype {x.dtype}")


def check_faces(faces: object, num_vertices: int, name: str = "faces") -> dict[str, int]:
    """Check ``(F, 3)`` integer triangles indexing ``num_vertices`` vertices; returns ``{"F": F}``.

    The range check reads tensor values, so it is skipped while ``torch.compile`` traces.

    Example:
        >>> check_faces(torch.tensor([[0, 1, 2]]), 3)
        {'F': 1}
        >>> check_faces(torch.tensor([[0, 1, 3]]), 3)
        Traceback (most recent call last):
        ...
        ValueError: faces: expected vertex indices in [0, 3), got values in [0, 3]
    """
    dims = check_shape(faces, ["F", 3], name)
    if faces.dtype.is_floating_point or faces.dtype.is_complex or faces.dtype == torch.bool:
        raise ValueError(f"{name}: expected an integer tensor, got dtype {faces.dtype}")
    if not torch.compiler.is_compiling() and faces.numel():
        lo, hi = int(faces.min()), int(faces.max())
        if lo < 0 or hi >= num_vertices:
            raise ValueError(f"{name}: expected vertex indices in [0, {num_vertices}), got values in [{lo}, {hi}]")
    return dims


def values_readable(x: Tensor) -> bool:
    """Whether a check may read ``x``'s values: not while ``torch.compile`` traces, nor for a tensor
    that a ``torch.func`` transform wraps (``vmap`` cannot branch on values)."""
    return not (torch.compiler.is_compiling() or is_functorch_wrapped_tensor(x))


def check_finite(x: Tensor, name: str, allow_inf: bool = False) -> None:
    """Raise ``ValueError`` if ``x`` holds NaN or infinite values (only NaN with ``allow_inf``, e.g. for
    a z-buffer that is ``inf`` on background).

    The check reads tensor values, so it is skipped while ``torch.compile`` traces and for a tensor
    that a ``torch.func`` transform wraps (``vmap`` cannot branch on values).

    Example:
        >>> check_finite(torch.tensor([1.0, float("inf")]), "zbuffer", allow_inf=True)
        >>> check_finite(torch.tensor([1.0, float("nan")]), "zbuffer", allow_inf=True)
        Traceback (most recent call last):
        ...
        ValueError: zbuffer: expected no NaN values, got 1 NaN entries
    """
    check_tensor(x, name)
    if not values_readable(x):
        return
    if not allow_inf and bool(torch.isfinite(x.sum())):  # fast path: a finite sum has no NaN or inf
        return
    if allow_inf:
        if bool(torch.isnan(x).any()):
            raise ValueError(f"{name}: expected no NaN values, got {int(torch.isnan(x).sum())} NaN entries")
        return
    if not bool(torch.isfinite(x).all()):
        bad = int((~torch.isfinite(x)).sum())
        raise ValueError(f"{name}: expected finite values, got {bad} NaN or infinite entries")


def check_all_finite(**tensors: Tensor) -> None:
    """:func:`check_finite` for several named tensors with one device synchronisation: the error
    names the first tensor, in argument order, that holds NaN or infinite values.

    Example:
        >>> check_all_finite(points=torch.zeros(1, 2, 3), angles=torch.tensor([[0.0, float("nan"), 0.0]]))
        Traceback (most recent call last):
        ...
        ValueError: angles: expected finite values, got 1 NaN or infinite entries
    """
    for name, x in tensors.items():
        check_tensor(x, name)
    if torch.compiler.is_compiling():
        return
    tensors = {name: x for name, x in tensors.items() if not is_functorch_wrapped_tensor(x)}
    if not tensors:
        return
    values = list(tensors.values())
    if len({x.device for x in values}) == 1:
        total = values[0].sum()
        for x in values[1:]:
            total = total + x.sum()
        if bool(torch.isfinite(total)):  # a finite sum has no NaN or inf (an overflow falls through)
            return
    for name, x in tensors.items():
        check_finite(x, name)


def check_nonnegative(value: object, name: str) -> float:
    """Return ``value`` as a float, raising ``ValueError`` unless it is a finite real number >= 0.

    Example:
        >>> check_nonnegative(0.5, "weight")
        0.5
    """
    number = check_real(value, name) if isinstance(value, Tensor) else value  # a 0-d tensor, as check_real takes
    if isinstance(number, bool) or not isinstance(number, Real):
        raise ValueError(f"{name}: expected a real number, got {type(value).__name__}")
    number = _as_float(number, name)
    if not math.isfinite(number) or number < 0:
        raise ValueError(f"{name}: expected a finite number >= 0, got {value!r}")
    return number


def _as_float(value: Real, name: str) -> float:
    """``float(value)``, an integer too large for a float named as ``name``'s error."""
    try:
        return float(value)
    except OverflowError:
        raise ValueError(f"{name}: expected a finite number, got an integer of {len(str(abs(int(value))))} "
                         "digits") from None


def check_real(value: object, name: str) -> float:
    """Return ``value`` as a float, raising ``ValueError`` unless it is a finite real number (a Python
    or numpy number; not a bool, a string or a tensor of several values).

    Example:
        >>> check_real(-0.25, "min_facing")
        -0.25
        >>> check_real("0.2", "min_facing")
        Traceback (most recent call last):
        ...
        ValueError: min_facing: expected a real number, got str '0.2'
    """
    if isinstance(value, Tensor) and value.numel() == 1 and value.dtype.is_floating_point:
        value = value.item()
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, Real):
        raise ValueError(f"{name}: expected a real number, got {type(value).__name__} {value!r}")
    number = _as_float(value, name)
    if not math.isfinite(number):
        raise ValueError(f"{name}: expected a finite number, got {value!r}")
    return number


def check_positive(value: object, name: str) -> float:
    """Return ``value`` as a float, raising ``ValueError`` unless it is a finite real number > 0
    (as :func:`check_real`).

    Example:
        >>> check_positive(1e-9, "eps")
        1e-09
        >>> check_positive(0.0, "eps")
        Traceback (most recent call last):
        ...
        ValueError: eps: expected a finite number > 0, got 0.0
    """
    number = check_real(value, name)
    if number <= 0:
        raise ValueError(f"{name}: expected a finite number > 0, got {value!r}")
    return number


def check_integer(value: object, name: str, minimum: int | None = None) -> int:
    """Return ``value`` as an ``int``, raising ``ValueError`` unless it is an integer (a Python or
    numpy integer or an integer 0-d tensor; not a bool, not a float) of at least ``minimum``.

    Example:
        >>> check_integer(3, "radius", minimum=0)
        3
        >>> check_integer(1.5, "radius")
        Traceback (most recent call last):
        ...
        ValueError: radius: expected an integer, got float 1.5
    """
    if isinstance(value, (bool, np.bool_)) or (isinstance(value, Tensor) and (value.dtype == torch.bool or value.dim())):
        raise ValueError(f"{name}: expected an integer, got {type(value).__name__} {value!r}")
    try:
        number = operator.index(value)
    except TypeError:
        raise ValueError(f"{name}: expected an integer, got {type(value).__name__} {value!r}") from None
    if minimum is not None and number < minimum:
        raise ValueError(f"{name}: expected an integer >= {minimum}, got {number}")
    return number


def check_image_size(image_size: object, name: str = "image_size") -> tuple[int, int]:
    """Return ``(H, W)``, raising ``ValueError`` unless ``image_size`` is a pair of positive integers.

    Example:
        >>> check_image_size((128, 96))
        (128, 96)
        >>> check_image_size((128.7, 96))
        Traceback (most recent call last):
        ...
        ValueError: image_size: expected (H, W), two integers >= 1, got (128.7, 96)
    """
    try:
        height, width = image_size  # type: ignore[misc]
        return check_integer(height, name, 1), check_integer(width, name, 1)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected (H, W), two integers >= 1, got {image_size!r}") from None


def outside_millimetre_span(points: Tensor) -> float | None:
    """The bounding-box diagonal of ``points`` ``(..., 3)`` when it lies outside
    :data:`MILLIMETRE_SPAN` (a model or mesh not in mm), else ``None``.

    Example:
        >>> outside_millimetre_span(torch.tensor([[0.0, 0, 0], [0.2, 0.1, 0.1]])) is not None
        True
        >>> outside_millimetre_span(torch.tensor([[0.0, 0, 0], [200.0, 100, 100]])) is None
        True
    """
    flat = points.detach().reshape(-1, 3)
    span = float((flat.amax(0) - flat.amin(0)).norm())
    low, high = MILLIMETRE_SPAN
    return None if low <= span <= high else span


#: Below this :func:`outward_share` the triangles are taken as wound clockwise seen from outside.
INWARD_SHARE = -0.25


def outward_share(vertices: Tensor, faces: Tensor) -> float:
    """How consistently the triangles of a mesh face outward, in ``[-1, 1]``: the area-weighted mean
    sign of ``n_f · (c_f − c)``, face normal against the direction from the mesh's area-weighted
    centre ``c`` to the face's centroid ``c_f``.

    A closed head is near 1 and a face mask (a cap bulging away from its centre) clearly positive
    when wound counter-clockwise seen from outside (docs/conventions.md), and as negative when wound
    the other way; a flat mesh gives about 0. Below :data:`INWARD_SHARE` the winding is reversed.

    Example:
        >>> vertices = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        >>> faces = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])  # a tetrahedron
        >>> outward_share(vertices, faces), outward_share(vertices, faces[:, [0, 2, 1]])
        (1.0, -1.0)
    """
    corners = vertices.detach().double()[faces.detach().long().to(vertices.device)]  # (F, 3, 3)
    cross = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], dim=1)
    area, centroids = cross.norm(dim=1), corners.mean(1)
    total = area.sum().clamp_min(1e-300)
    centre = (area[:, None] * centroids).sum(0) / total
    away = centroids - centre
    facing = (cross * away).sum(1)
    # a face seen edge-on from the centre (within 1e-4 of 90 degrees, e.g. every face of a flat mesh) or
    # at the centre (one triangle) has no side: its sign would be rounding noise, a full vote either way
    size = float((corners.amax((0, 1)) - corners.amin((0, 1))).norm()) if len(corners) else 0.0
    sure = facing.abs() > 1e-4 * area * away.norm(dim=1).clamp_min(1e-6 * size)
    return float((area * torch.sign(facing) * sure).sum() / total)


def environment_integer(name: str, default: int) -> int:
    """The integer in environment variable ``name`` (e.g. ``torchrun``'s ``RANK``), ``default`` when it
    is unset or empty; ``ValueError`` naming ``$name`` otherwise.

    Example:
        >>> environment_integer("FACENORMALS_UNSET_EXAMPLE", 1)
        1
    """
    value = os.environ.get(name)
    if value is None or value == "":
        return default
    try:
        return int(value)
    except ValueError:
        raise ValueError(f"${name}: expected an integer, got {value!r}") from None
