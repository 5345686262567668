"""Reading photos for reconstruction: any size, colour or grey, EXIF orientation applied."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["ImageReadError", "read_image"]


class ImageReadError(ValueError):
    """A file that is missing, unreadable or not an image; the message names the file."""


def read_image(path: str | Path) -> np.ndarray:
    """Read a photo as RGB ``uint8`` ``(H, W, 3)``, rotated as its EXIF orientation says.

    Grey images are replicated to three channels, an alpha channel is dropped and 16-bit images
    are scaled to 8 bits (OpenCV's ``IMREAD_COLOR``, which also applies the EXIF orientation tag).

    Raises:
        ImageReadError: naming ``path`` if it does not exist, is a folder or is not a decodable image.

    Example:
        >>> import cv2, tempfile, os
        >>> path = os.path.join(tempfile.mkdtemp(), "grey.png")
        >>> _ = cv2.imwrite(path, np.full((4, 6), 200, np.uint8))
        >>> read_image(path).shape
        (4, 6, 3)
    """
    import cv2

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
        image = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    except cv2.error as error:  # e.g. a header claiming more pixels than OpenCV accepts
        raise ImageReadError(f"{path}: cannot be decoded ({str(error).strip().splitlines()[-1]})") from None
    if image is None:
        raise ImageReadError(f"{path}: not an image, or one in a format OpenCV cannot decode")
    if data[:3].tobytes() == b"\xff\xd8\xff":
        _check_jpeg_stream(path, data)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)  # a third of the time of a reversed copy


def _check_jpeg_stream(path: Path, data: np.ndarray) -> None:
    """OpenCV decodes a JPEG with corrupt entropy-coded data as best it can (libjpeg only prints
    "Corrupt JPEG data" to stderr) and returns garbage pixels without an error; Pillow's decoder
    refuses the same stream, so it checks the file once more. It decodes at an eighth of the size
    (libjpeg's DCT scaling: every coefficient is still entropy-decoded, so the same streams are
    refused, in a quarter of the time). Pillow's decompression-bomb limit (89 M pixels warns, 179 M
    fails) is lifted for the check: OpenCV has already decoded the whole image."""
    import io
    import warnings

    from PIL import Image

    limit = Image.MAX_IMAGE_PIXELS
    try:
        Image.MAX_IMAGE_PIXELS = None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(data.tobytes())) as image:
                image.draft(image.mode, (max(1, image.width // 8), max(1, image.height // 8)))
                image.load()
    except (OSError, SyntaxError, ValueError) as error:
        raise ImageReadError(f"{path}: corrupt JPEG data ({error})") from None
    finally:
        Image.MAX_IMAGE_PIXELS = limit
