"""Reading photos for reconstruction: any size, colour or grey, EXIF orientation applied."""

from __future__ import annotations

import os
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np

__all__ = ["ImageReadError", "read_image"]


class ImageReadError(ValueError):
    """A file that is missing, unreadable or not an image; the message names the file."""


def read_image(path: str | Path) -> np.ndarray:
    """Read a photo as RGB ``uint8`` ``(H, W, 3)``, rotated as its EXIF orientation says.

    Grey images are replicated to three channels and an alpha channel is dropped (OpenCV's
    ``IMREAD_COLOR``, which also applies the EXIF orientation tag). Deeper samples are scaled to 8
    bits: 16-bit ones as holding 8-, 10-, 12-, 14- or 16-bit data, the least that holds the image's
    largest value (scanners and cameras often store 10 or 12 bits in 16, which divided by 256 would
    leave a black image); floating-point ones (e.g. a float TIFF) from ``[0, 1]``, or from
    ``[0, 255]`` or their largest value where they exceed 1, and clipped below at 0.

    Raises:
        ImageReadError: naming ``path`` if it does not exist, is a folder or is not a decodable
            image, or if libjpeg reports damaged JPEG data (which OpenCV would decode to garbage
            pixels without an error; damage that still decodes cleanly cannot be seen, as JPEG has
            no checksum).

    Example:
        >>> import cv2, tempfile, os
        >>> path = os.path.join(tempfile.mkdtemp(), "grey.png")
        >>> _ = cv2.imwrite(path, np.full((4, 6), 200, np.uint8))
        >>> read_image(path).shape
        (4, 6, 3)
    """
    import cv2

    if not isinstance(path, (str, os.PathLike)):
        raise ImageReadError(f"path: expected a file name (str or os.PathLike), got {type(path).__name__}")
    path = Path(path)
    if not path.exists():
        raise ImageReadError(f"{path}: no such file")
    if not path.is_file():
        raise ImageReadError(f"{path}: not a file")
    try:
        data = np.fromfile(path, dtype=np.uint8)  # also works for non-ASCII paths, unlike cv2.imread
    except OSError as error:
        raise ImageReadError(f"{path}: cannot be read ({error.strerror or error})") from None
    try:
        image, damage = _decode(data)
    except cv2.error as error:  # e.g. a header claiming more pixels than OpenCV accepts
        raise ImageReadError(f"{path}: cannot be decoded ({str(error).strip().splitlines()[-1]})") from None
    if image is None:
        kind = next((name for signature, name in _SIGNATURES if data[: len(signature)].tobytes() == signature), None)
        if kind is not None:  # OpenCV 5 returns None for a cut-off JPEG or PNG, without libjpeg's warning
            raise ImageReadError(f"{path}: a damaged or truncated {kind} file")
        raise ImageReadError(f"{path}: not an image, or one in a format OpenCV cannot decode")
    if damage:
        raise ImageReadError(f"{path}: corrupt JPEG data ({damage[0]})")
    if image.dtype not in (np.uint8, np.uint16) and image.dtype.kind != "f":  # e.g. a signed TIFF
        image = cv2.imdecode(data, cv2.IMREAD_COLOR)  # OpenCV's own conversion to 8 bits, as before
        if image is None:
            raise ImageReadError(f"{path}: not an image, or one in a format OpenCV cannot decode")
    return cv2.cvtColor(_eight_bits(image, path), cv2.COLOR_BGR2RGB)  # a third of the time of a reversed copy


def _eight_bits(image: np.ndarray, path: Path) -> np.ndarray:
    """A decoded image of any sample type as ``uint8``, scaled as :func:`read_image` says."""
    if image.dtype == np.uint8:
        return image
    if image.dtype == np.uint16:
        bits = next(b for b in (8, 10, 12, 14, 16) if int(image.max()) < 1 << b)
        return np.round(image.astype(np.float32) * (255.0 / ((1 << bits) - 1))).astype(np.uint8)
    if image.dtype.kind == "f":
        if not np.isfinite(image).all():
            raise ImageReadError(f"{path}: a floating-point image with NaN or infinite pixels")
        top = float(image.max())
        scale = 255.0 if top <= 1.0 else 1.0 if top <= 255.0 else 255.0 / top  # in the image's dtype: no underflow
        return np.round(np.clip(image * scale, 0.0, 255.0)).astype(np.uint8)
    raise ImageReadError(f"{path}: {image.dtype} samples are not supported (8- or 16-bit integers or floating point)")


_JPEG_DAMAGE = ("Corrupt JPEG data", "Premature end of JPEG file", "Inconsistent progression sequence")
"""libjpeg's warnings about damaged data (``JWRN_*``: bad Huffman codes, extraneous bytes, missing
restart markers, a truncated file); its other warnings (an unknown JFIF revision...) are harmless."""

_JPEG_SIGNATURE = b"\xff\xd8\xff"
_SIGNATURES = ((_JPEG_SIGNATURE, "JPEG"), (b"\x89PNG\r\n\x1a\n", "PNG"))
"""File signatures of the formats whose damage :func:`read_image` names as such."""

_STDERR_LOCK = threading.Lock()

#: JPEG markers without a length field (TEM and RSTn); every other header marker is followed by one.
_STANDALONE = frozenset([0x01, *range(0xD0, 0xD8)])


def _without_header_padding(data: np.ndarray) -> np.ndarray:
    """``data`` without stray bytes between the header segments of a JPEG (before its first scan).

    Some writers pad the header; libjpeg skips the bytes but warns "Corrupt JPEG data: N extraneous
    bytes before marker 0x..", which cannot be told apart from damaged scan data by its text. Stray
    bytes before the first SOS cannot come from scan data, so they are dropped here and any warning
    left is real damage. A header that does not parse is returned unchanged for the decoder to judge.
    """
    raw = data.tobytes()
    keep, pos, start = [], 2, 2  # after SOI
    while pos < len(raw):
        if raw[pos] != 0xFF:  # a stray byte between segments
            keep.append(raw[start:pos])
            while pos < len(raw) and raw[pos] != 0xFF:
                pos += 1
            start = pos
            continue
        while pos < len(raw) and raw[pos] == 0xFF:  # fill bytes are allowed before a marker
            pos += 1
        if pos >= len(raw):
            return data
        marker = raw[pos]
        pos += 1
        if marker == 0xDA:  # start of scan: the rest is scan data and later segments
            if not keep:
                return data
            keep.append(raw[start:])
            return np.frombuffer(raw[:2] + b"".join(keep), dtype=np.uint8)
        if marker in _STANDALONE:
            continue
        if marker == 0x00 or pos + 2 > len(raw):
            return data
        pos += (raw[pos] << 8) | raw[pos + 1]
    return data


def _decode(data: np.ndarray) -> tuple[np.ndarray | None, list[str]]:
    """``cv2.imdecode`` (``None`` for no data) and, for a JPEG, libjpeg's warnings about damage.

    libjpeg decodes damaged scan data as best it can and only *prints* "Corrupt JPEG data: ..." to
    the C ``stderr``; OpenCV returns the garbage pixels without an error. For a JPEG, file
    descriptor 2 is redirected to a temporary file for the call (under a lock), and anything else
    written there meanwhile (e.g. by another thread) is passed on to the real ``stderr``. Damage
    that leaves valid Huffman codes is invisible to any decoder: JPEG has no checksum.
    """
    import cv2

    flags = cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH  # 16-bit and float samples kept, for _eight_bits
    if not data.size:
        return None, []
    if data[: len(_JPEG_SIGNATURE)].tobytes() != _JPEG_SIGNATURE:
        return cv2.imdecode(data, flags), []
    data = _without_header_padding(data)
    if sys.stderr is None:  # Python started with file descriptor 2 closed: no warnings to read
        return cv2.imdecode(data, flags), []
    with _STDERR_LOCK, tempfile.TemporaryFile() as capture:
        sys.stderr.flush()
        try:
            saved = os.dup(2)
        except OSError:  # no stderr to redirect (a daemon): decode without the check
            return cv2.imdecode(data, flags), []
        try:
            os.dup2(capture.fileno(), 2)
            image = cv2.imdecode(data, flags)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        capture.seek(0)
        lines = capture.read().decode("utf-8", errors="replace").splitlines(keepends=True)
    damage = [line.strip() for line in lines if line.startswith(_JPEG_DAMAGE)]
    others = "".join(line for line in lines if not line.startswith(_JPEG_DAMAGE))
    if others and sys.stderr is not None:
        sys.stderr.write(others)
    return image, damage
