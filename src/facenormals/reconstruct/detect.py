r"""Offline face detection and the square head crop the network expects.

The detector is scikit-image's LBP frontal-face cascade (``skimage.data`` ships the trained
OpenCV cascade file). Why this one: scikit-image is already a dependency, the cascade is in its
wheel (OpenCV 5 wheels dropped their cascade files), it needs no network access, no model download
and no extra package (mediapipe pins its own NumPy and protobuf and has no wheels for every
platform we support). Its limit: it finds roughly frontal faces (up to ~30-40° of yaw). For
profile photos pass the face box yourself (``--box`` on the command line).

Raw cascade hits are grouped: hits whose boxes overlap (IoU ≥ 0.3) form one candidate, scored by
its number of hits, and the candidate with the most hits (then the largest) wins; single stray
hits are false positives far more often than faces.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from facenormals.core.check import check_integer, check_positive

__all__ = ["FaceBox", "NoFaceError", "crop_square", "detect_faces", "head_crop_box"]


class NoFaceError(ValueError):
    """No face was found in an image."""


@dataclass(frozen=True)
class FaceBox:
    """An axis-aligned box in image pixels: corner ``(x, y)``, ``width``, ``height``; ``hits`` cascade hits."""

    x: float
    y: float
    width: float
    height: float
    hits: int = 1

    def __post_init__(self) -> None:
        for name in ("x", "y", "width", "height"):
            _check_finite_number(getattr(self, name), f"FaceBox {name}")
        if not (self.width > 0 and self.height > 0):
            raise ValueError(f"FaceBox: expected width and height > 0, got {self.width!r} x {self.height!r}")

    @property
    def center(self) -> tuple[float, float]:
        return self.x + self.width / 2, self.y + self.height / 2

    def iou(self, other: "FaceBox") -> float:
        ix = max(0.0, min(self.x + self.width, other.x + other.width) - max(self.x, other.x))
        iy = max(0.0, min(self.y + self.height, other.y + other.height) - max(self.y, other.y))
        inter = ix * iy
        return inter / (self.width * self.height + other.width * other.height - inter)


def _check_finite_number(value: object, name: str) -> None:
    """A plain finite real number (Python or NumPy; not a bool, a string or a tensor)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise ValueError(f"{name}: expected a finite number, got {value!r}")


@lru_cache(maxsize=1)
def _cascade():
    import skimage.data
    import skimage.feature

    return skimage.feature.Cascade(skimage.data.lbp_frontal_face_cascade_filename())


def _group(hits: list[FaceBox], min_iou: float) -> list[FaceBox]:
    groups: list[list[FaceBox]] = []
    for box in sorted(hits, key=lambda b: -b.width):
        for group in groups:
            if box.iou(group[0]) >= min_iou:
                group.append(box)
                break
        else:
            groups.append([box])
    merged = []
    for group in groups:
        arr = np.array([[b.x, b.y, b.width, b.height] for b in group])
        x, y, w, h = arr.mean(0)
        merged.append(FaceBox(float(x), float(y), float(w), float(h), hits=len(group)))
    return sorted(merged, key=lambda b: (-b.hits, -b.width))


def detect_faces(image: np.ndarray, max_side: int = 480, min_face: float = 0.08, min_hits: int = 1,
                 retry_sides: tuple[int, ...] = (960, 1920)) -> list[FaceBox]:
    """Find faces with the LBP cascade; the best candidate comes first.

    The image is searched at most ``max_side`` pixels on its longer side (boxes are returned in the
    original pixels), for faces from ``min_face`` of its shorter side up. If that finds nothing in
    a larger image, it is searched again at each of ``retry_sides`` (capped at its own size), for
    the faces smaller than the search before could see, down to the cascade's 24-pixel window, in
    steps of 1.5 instead of 1 pixel: a face 100 pixels wide in a 2400 x 1800 photo is below the
    first search's 0.08 x 1800 = 144. A large photo without a face takes longer to refuse (a
    12-MP one ~2.5 s instead of 0.4 s).

    Args:
        image: RGB or grey ``uint8`` image ``(H, W, 3)`` / ``(H, W)``.
        max_side: longer side of the searched copy.
        min_face: smallest face side of the first search, as a fraction of the shorter image side;
            the retries search smaller faces (``retry_sides=()`` makes it a strict bound).
        min_hits: drop candidates with fewer overlapping cascade hits.
        retry_sides: longer sides of the copies searched for smaller faces when nothing is found,
            increasing; ``()`` searches once.

    Returns:
        Grouped detections, most hits (then largest) first; empty if none.
    """
    import cv2

    if (not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim not in (2, 3)
            or (image.ndim == 3 and image.shape[2] not in (1, 3, 4))):
        raise ValueError(f"image: expected a uint8 array (H, W[, 1|3|4]), got "
                         f"{getattr(image, 'dtype', type(image).__name__)} {getattr(image, 'shape', '')}")
    max_side = check_integer(max_side, "max_side", minimum=24)  # the cascade's window is 24 px
    min_face = check_positive(min_face, "min_face")
    if min_face > 1:
        raise ValueError(f"min_face: expected a fraction of the shorter image side in (0, 1], got {min_face!r}")
    min_hits = check_integer(min_hits, "min_hits", minimum=1)
    if not isinstance(retry_sides, (tuple, list)):
        raise ValueError(f"retry_sides: expected a tuple of image sides, got {retry_sides!r}")
    sides = [max_side] + [check_integer(s, "retry_sides", minimum=24) for s in retry_sides]
    if image.size == 0:
        return []  # no pixels, no face (as for a sliver below)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    grey = image if image.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(image[:, :, :3]), cv2.COLOR_RGB2GRAY)
    height, width = grey.shape
    seen_down_to = math.inf  # the smallest face side searched so far, original pixels
    for long_side in sides:
        long_side = min(long_side, max(height, width))
        copy = grey
        if long_side < max(height, width):
            size = (max(1, round(width * long_side / max(height, width))),
                    max(1, round(height * long_side / max(height, width))))
            copy = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
        scale_x, scale_y = copy.shape[1] / width, copy.shape[0] / height  # the real ratios after rounding
        side = min(copy.shape)
        first = math.isinf(seen_down_to)
        if first:
            smallest, largest = max(24, int(min_face * side)), side
        else:
            smallest, largest = 24, min(side, math.ceil(seen_down_to * max(scale_x, scale_y)))
        if smallest > largest:  # a sliver, or nothing smaller than before at this size
            continue
        # the retries step the window 1.5 px at the smallest scale instead of 1: 3x faster (a 12-MP photo
        # without a face took 6.6 s to refuse, now ~2.5 s), and the small faces of the tests are still found
        raw = _cascade().detect_multi_scale(img=copy, scale_factor=1.15, step_ratio=1 if first else 1.5,
                                            min_size=(smallest, smallest), max_size=(largest, largest))
        hits = [FaceBox(d["c"] / scale_x, d["r"] / scale_y, d["width"] / scale_x, d["height"] / scale_y) for d in raw]
        faces = [b for b in _group(hits, 0.3) if b.hits >= min_hits]
        if faces or long_side >= max(height, width):
            return faces
        seen_down_to = smallest / max(scale_x, scale_y)
    return []


def head_crop_box(face: FaceBox, scale: float = 1.9, shift: float = -0.12) -> tuple[float, float, float]:
    """The square crop around a detected face that frames the head as in the training data.

    The cascade's box spans roughly brows to mouth; the crop is ``scale`` times its size, centred
    ``shift`` box heights below its centre (negative: up, towards the cranium).

    Returns:
        ``(x0, y0, side)``: the crop's top-left corner and side, image pixels (may leave the image).
    """
    if not isinstance(face, FaceBox):
        raise ValueError(f"face: expected a FaceBox, got {type(face).__name__}")
    _check_finite_number(scale, "scale")
    _check_finite_number(shift, "shift")
    if scale <= 0:
        raise ValueError(f"scale: expected a number > 0, got {scale!r}")
    cx, cy = face.center
    side = scale * max(face.width, face.height)
    cy += shift * face.height
    return cx - side / 2, cy - side / 2, side


#: The largest crop :func:`crop_square` makes (the network takes 128 px): a bigger one is a mistake,
#: not a request for gigabytes.
MAX_CROP_SIZE = 4096


def check_crop_box(box: object, name: str = "box") -> tuple[float, float, float]:
    """``box`` as ``(x0, y0, side)`` floats: three finite numbers with ``side > 0``, else a
    ``ValueError`` naming ``name`` (e.g. for an ``(x, y, w, h)`` face box passed by mistake)."""
    try:
        values = tuple(float(v) for v in box)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values) or not values[2] > 0:
        raise ValueError(f"{name}: expected a crop box (x0, y0, side) of three finite numbers with side > 0, "
                         f"got {box!r}")
    return values  # type: ignore[return-value]


def crop_square(image: np.ndarray, box: tuple[float, float, float], size: int = 128) -> np.ndarray:
    """Resample the square ``box = (x0, y0, side)`` of ``image`` to ``size × size`` (edges replicated).

    Crop pixel ``(u, v)`` (centre convention of ``docs/conventions.md``) shows image point
    ``(x0 + (u + 0.5)·s − 0.5, y0 + (v + 0.5)·s − 0.5)`` with ``s = side / size``.

    Raises:
        ValueError: naming ``image`` unless it is a non-empty ``(H, W, 3)`` uint8, uint16, float32 or
            float64 array (a float one finite), or naming ``box`` or ``size`` when they are invalid.

    Example:
        >>> img = np.arange(16, dtype=np.uint8).reshape(4, 4)[..., None].repeat(3, -1)
        >>> crop_square(img, (0.0, 0.0, 4.0), size=4)[..., 0].tolist() == img[..., 0].tolist()
        True
    """
    import cv2

    if (not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3 or image.size == 0
            or image.dtype not in (np.uint8, np.uint16, np.float32, np.float64)):
        raise ValueError(f"image: expected a non-empty uint8, uint16, float32 or float64 array (H, W, 3), got "
                         f"{getattr(image, 'dtype', type(image).__name__)} {getattr(image, 'shape', '')}")
    # a NaN pixel would spread through the blur and the interpolation into a NaN crop, silently; a finite
    # sum (float64: no overflow from float32 values) has no NaN or inf
    if image.dtype.kind == "f" and not np.isfinite(image.sum(dtype=np.float64)):
        bad = int(np.count_nonzero(~np.isfinite(image)))
        if bad:
            raise ValueError(f"image: expected finite values, got {bad} NaN or infinite entries")
    x0, y0, side = check_crop_box(box)
    if isinstance(size, bool) or not isinstance(size, int) or not 1 <= size <= MAX_CROP_SIZE:
        raise ValueError(f"size: expected an integer in [1, {MAX_CROP_SIZE}], got {size!r}")
    s = side / size
    # crop pixel u -> image x = s*u + (x0 + 0.5*s - 0.5); warpAffine maps destination to source.
    matrix = np.array([[s, 0.0, x0 + 0.5 * s - 0.5], [0.0, s, y0 + 0.5 * s - 0.5]])
    if s > 1.5:  # downsampling: pre-blur against aliasing (INTER_AREA cannot do sub-pixel offsets)
        sigma = 0.5 * np.sqrt(s * s - 1.0)
        # Blur only the part of the photo the crop samples, plus the kernel's reach (OpenCV's radius
        # is 3σ for uint8, 4σ otherwise) and the bilinear neighbour: the same pixels as blurring all
        # of it, as the cut edges lie beyond what any sample reads, and the photo's own edges are kept.
        reach = math.ceil(4.0 * sigma) + 2
        height, width = image.shape[:2]

        def span(start: float, count: int) -> tuple[int, int]:  # the rows or columns read, clamped, + reach
            first = min(max(math.floor(start), 0), count - 1)
            last = min(max(math.ceil(start + side), 0), count - 1)
            return max(first - reach, 0), min(last + reach + 1, count)

        (left, right), (top, bottom) = span(x0, width), span(y0, height)
        image = cv2.GaussianBlur(image[top:bottom, left:right], (0, 0), sigma)
        matrix[:, 2] -= (left, top)
    return cv2.warpAffine(image, matrix, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)
