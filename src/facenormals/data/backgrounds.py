"""Random backgrounds: gradients, fractal noise, clutter, patterns and crops of real photos.

Photos come from ``skimage.data`` when scikit-image is installed (its bundled images, no download)
and from any folder of ``.jpg``/``.png`` files the user passes. Images of people are left out so
that no second face appears behind the rendered head.
"""

from __future__ import annotations

import hashlib
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np

from facenormals.core.check import check_image_size

__all__ = ["PhotoLibrary", "random_background"]

#: Bundled ``skimage.data`` images used as photo backgrounds (no faces; skipped, with a warning,
#: where this scikit-image lacks one or would have to download it).
SKIMAGE_IMAGES = (
    "chelsea", "coffee", "rocket", "horse", "coins", "moon", "text", "page", "brick", "grass",
    "gravel", "hubble_deep_field", "immunohistochemistry", "retina", "colorwheel", "logo", "clock", "cell",
    "binary_blobs",
)  # fmt: skip
#: Arguments that make a generated ``skimage.data`` image the same in every process (``binary_blobs``
#: draws new blobs on each call otherwise, so samples drawing it differed between runs).
_SKIMAGE_ARGUMENTS = {"binary_blobs": {"rng": 0}}

_MAX_SIDE = 512


def _to_rgb_uint8(image: np.ndarray) -> np.ndarray | None:
    image = np.asarray(image)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] < 3 or min(image.shape[:2]) < 32:
        return None
    image = image[..., :3]
    if image.dtype == bool:
        image = image.astype(np.uint8) * 255
    elif image.dtype != np.uint8:
        image = image.astype(np.float64)
        lo, hi = float(image.min()), float(image.max())
        image = ((image - lo) / max(hi - lo, 1e-12) * 255.0).astype(np.uint8)
    return _shrink(image)


def _shrink(image: np.ndarray) -> np.ndarray:
    import cv2

    side = max(image.shape[:2])
    if side > _MAX_SIDE:
        scale = _MAX_SIDE / side
        image = cv2.resize(image, (round(image.shape[1] * scale), round(image.shape[0] * scale)), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(image)


class PhotoLibrary:
    """Photos to crop backgrounds from, loaded once (at most 512 px per side).

    Args:
        folders: folders searched (recursively) for ``.jpg``, ``.jpeg`` and ``.png`` files.
        use_skimage: add the bundled ``skimage.data`` images when scikit-image is installed.

    Attributes:
        images: the ``(H, W, 3)`` uint8 RGB photos.
        sources: where each photo comes from (``skimage.data.<name>`` or its path).
        skipped: the ``skimage.data`` images this installation cannot load (each also warned about).

    Raises:
        ValueError: on a missing folder, a folder without photos, or a photo that cannot be decoded
            or is damaged (:func:`facenormals.reconstruct.read_image`'s checks, e.g. libjpeg's warnings
            about corrupt or truncated JPEG data, which OpenCV decodes to garbage pixels).
    """

    def __init__(self, folders: Sequence[str | Path] = (), use_skimage: bool = True) -> None:
        # imported here: facenormals.reconstruct imports facenormals.data, which imports this module
        from facenormals.reconstruct.images import ImageReadError, read_image

        self.images: list[np.ndarray] = []
        self.sources: list[str] = []
        self.skipped: list[str] = []
        if use_skimage:
            try:
                import skimage.data as skdata
            except ImportError:
                skdata = None
            if skdata is not None:
                for name in SKIMAGE_IMAGES:
                    try:
                        image = _to_rgb_uint8(getattr(skdata, name)(**_SKIMAGE_ARGUMENTS.get(name, {})))
                    # not in this scikit-image version, or it needs pooch or a download; other errors are bugs
                    except (AttributeError, ImportError, OSError) as error:
                        self.skipped.append(f"skimage.data.{name}")
                        warnings.warn(f"background photos: skimage.data.{name} skipped ({type(error).__name__}: "
                                      f"{error})", stacklevel=2)
                        continue
                    if image is not None:
                        self.images.append(image)
                        self.sources.append(f"skimage.data.{name}")
        for folder in folders:
            folder = Path(folder)
            if not folder.is_dir():
                raise ValueError(f"background folder {folder} does not exist")
            found = 0
            photos = (p for p in folder.rglob("*") if p.suffix.lower() in (".jpg", ".jpeg", ".png")
                      and not any(part.startswith(".") or part == "__MACOSX"  # hidden files, macOS sidecars
                                  for part in p.relative_to(folder).parts))
            for path in sorted(photos):
                try:  # read_image, not cv2.imread: that decodes a damaged JPEG to garbage pixels, no error
                    rgb = read_image(path)
                except ImageReadError as error:  # a user's photo silently missing would change the data unnoticed
                    reason = str(error).removeprefix(f"{path}: ")
                    raise ValueError(f"background photo {path} cannot be decoded as an image ({reason}); remove or "
                                     "replace it") from None
                image = _to_rgb_uint8(rgb)
                if image is not None:
                    self.images.append(image)
                    self.sources.append(str(path))
                    found += 1
            if not found:
                raise ValueError(f"background folder {folder} holds no usable .jpg/.jpeg/.png photo")

    def __len__(self) -> int:
        return len(self.images)

    def __repr__(self) -> str:
        return f"PhotoLibrary(images={len(self)})"

    def fingerprint(self) -> dict:
        """``{"count", "sha256"}`` of the photos in order (their shapes and pixels): which photo a
        sample crops depends on both, so a dataset resumed with other photos would mix two sets."""
        digest = hashlib.sha256()
        for image in self.images:
            digest.update(repr(image.shape).encode())
            digest.update(image.tobytes())
        return {"count": len(self.images), "sha256": digest.hexdigest()}

    def crop(self, rng: np.random.Generator, size: tuple[int, int]) -> np.ndarray:
        """A random crop (20–100% of the shorter side), flipped at random, resized to ``size``."""
        import cv2

        image = self.images[int(rng.integers(len(self.images)))]
        h, w = image.shape[:2]
        side = int(rng.uniform(0.2, 1.0) * min(h, w))
        side = max(side, 16)
        y, x = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
        crop = image[y:y + side, x:x + side]
        if rng.random() < 0.5:
            crop = crop[:, ::-1]
        interpolation = cv2.INTER_AREA if side > max(size) else cv2.INTER_LINEAR
        return cv2.resize(np.ascontiguousarray(crop), (size[1], size[0]), interpolation=interpolation)


def _random_color(rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(0, 255, size=3) * rng.uniform(0.3, 1.0) + rng.uniform(0, 60)


def _gradient(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    if rng.random() < 0.6:
        angle = rng.uniform(0, 2 * np.pi)
        t = (np.cos(angle) * xx + np.sin(angle) * yy) / max(h, w)
    else:
        cx, cy = rng.uniform(-0.2, 1.2) * w, rng.uniform(-0.2, 1.2) * h
        t = np.hypot(xx - cx, yy - cy) / max(h, w)
    t = (t - t.min()) / max(t.max() - t.min(), 1e-9)
    a, b = _random_color(rng), _random_color(rng)
    return a[None, None] * (1 - t[..., None]) + b[None, None] * t[..., None]


def _fractal_noise(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    import cv2

    out = np.zeros((h, w, 3))
    amplitude, total = 1.0, 0.0
    persistence = rng.uniform(0.35, 0.7)
    for cells in (2, 4, 8, 16, 32, 64):
        grid = rng.normal(size=(cells + 1, cells + 1, 3 if rng.random() < 0.5 else 1))
        layer = cv2.resize(grid.astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
        if layer.ndim == 2:
            layer = layer[..., None]
        out += amplitude * layer
        total += amplitude
        amplitude *= persistence
    out /= total
    base, spread = _random_color(rng), rng.uniform(20, 90)
    return base[None, None] + spread * out


def _clutter(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    import cv2

    image = np.ascontiguousarray(np.clip(_gradient(rng, h, w), 0, 255).astype(np.uint8))  # colours reach 315
    for _ in range(int(rng.integers(3, 25))):
        color = tuple(int(c) for c in np.clip(_random_color(rng), 0, 255))
        kind = rng.integers(4)
        p1 = (int(rng.integers(-w // 4, w + w // 4)), int(rng.integers(-h // 4, h + h // 4)))
        if kind == 0:
            p2 = (int(rng.integers(-w // 4, w + w // 4)), int(rng.integers(-h // 4, h + h // 4)))
            cv2.rectangle(image, p1, p2, color, -1 if rng.random() < 0.7 else int(rng.integers(1, 4)))
        elif kind == 1:
            cv2.circle(image, p1, int(rng.integers(3, max(h, w) // 2)), color, -1 if rng.random() < 0.7 else 2,
                       lineType=cv2.LINE_AA)
        elif kind == 2:
            p2 = (int(rng.integers(0, w)), int(rng.integers(0, h)))
            cv2.line(image, p1, p2, color, int(rng.integers(1, 8)), lineType=cv2.LINE_AA)
        else:
            points = rng.integers(-w // 4, w + w // 4, size=(int(rng.integers(3, 7)), 2)).astype(np.int32)
            cv2.fillPoly(image, [points], color, lineType=cv2.LINE_AA)
    if rng.random() < 0.5:
        image = cv2.GaussianBlur(image, (0, 0), rng.uniform(0.5, 4.0))
    return image.astype(np.float64)


def _pattern(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    angle = rng.uniform(0, np.pi)
    u = np.cos(angle) * xx + np.sin(angle) * yy
    v = -np.sin(angle) * xx + np.cos(angle) * yy
    period = rng.uniform(3, 40)
    warp = rng.uniform(0, 6) * np.sin(v / rng.uniform(8, 60) + rng.uniform(0, 6.3))
    if rng.random() < 0.5:
        t = 0.5 + 0.5 * np.sin(2 * np.pi * (u + warp) / period)
    else:
        t = ((np.floor((u + warp) / period) + np.floor(v / period)) % 2).astype(np.float64)
    a, b = _random_color(rng), _random_color(rng)
    return a[None, None] * (1 - t[..., None]) + b[None, None] * t[..., None]


def random_background(rng: np.random.Generator, size: tuple[int, int] = (128, 128),
                      photos: PhotoLibrary | None = None, photo_probability: float = 0.4) -> np.ndarray:
    """A random ``(H, W, 3)`` uint8 RGB background of ``size`` ``(H, W)``.

    One of: linear or radial colour gradient, fractal (multi-octave) noise, clutter of random
    shapes, warped stripes/checkers, or a photo crop (with probability ``photo_probability`` when
    ``photos`` holds images). Half of them get a random brightness/contrast change and some sensor
    noise.

    Raises:
        ValueError: unless ``rng`` is a :class:`numpy.random.Generator`, ``size`` is two integers >= 1
            and ``photo_probability`` lies in ``[0, 1]``.

    Example:
        >>> random_background(np.random.default_rng(0)).shape
        (128, 128, 3)
    """
    if not isinstance(rng, np.random.Generator):  # a seed or None failed deep inside with an AttributeError
        raise ValueError(f"rng: expected a numpy.random.Generator (e.g. numpy.random.default_rng(seed)), got "
                         f"{type(rng).__name__} {rng!r}")
    h, w = check_image_size(size, "size")
    if not 0.0 <= photo_probability <= 1.0:
        raise ValueError(f"photo_probability: expected a probability in [0, 1], got {photo_probability}")
    if photos is not None and len(photos) and rng.random() < photo_probability:
        image = photos.crop(rng, (h, w)).astype(np.float64)
    else:
        kind = rng.choice(4, p=[0.25, 0.3, 0.3, 0.15])
        image = (_gradient, _fractal_noise, _clutter, _pattern)[kind](rng, h, w)
    if rng.random() < 0.5:
        image = (image - 128.0) * rng.uniform(0.6, 1.3) + 128.0 + rng.uniform(-40, 40)
        image = image * rng.uniform(0.85, 1.15, size=3)[None, None]
    if rng.random() < 0.3:
        image = image + rng.normal(0.0, rng.uniform(1.0, 6.0), size=image.shape)
    return np.clip(image, 0, 255).astype(np.uint8)
