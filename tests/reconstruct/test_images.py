from pathlib import Path

import numpy as np
import pytest

from facenormals.reconstruct import ImageReadError, read_image


def _banded(h=20, w=40):
    a = np.zeros((h, w, 3), np.uint8)
    a[:, :10] = (255, 0, 0)  # red band on the left
    return a


@pytest.mark.parametrize("orientation,where", [(1, "left"), (3, "right"), (6, "top"), (8, "bottom")])
def test_exif_orientation_is_applied(tmp_path, orientation, where):
    PIL = pytest.importorskip("PIL.Image")
    img = PIL.fromarray(_banded())
    exif = img.getexif()
    exif[0x0112] = orientation
    path = tmp_path / "photo.jpg"
    img.save(path, exif=exif.tobytes(), quality=95)
    out = read_image(path)
    assert out.shape == ((20, 40, 3) if orientation in (1, 3) else (40, 20, 3))
    red = out[..., 0].astype(float) - out[..., 1]
    band = {"left": red[:, :5], "right": red[:, -5:], "top": red[:5], "bottom": red[-5:]}[where]
    assert band.mean() > 200 and red.mean() < 100


def test_grey_rgba_and_16_bit_become_rgb_uint8(tmp_path):
    import cv2

    cv2.imwrite(str(tmp_path / "g.png"), np.full((5, 7), 90, np.uint8))
    cv2.imwrite(str(tmp_path / "a.png"), np.full((5, 7, 4), 90, np.uint8))
    cv2.imwrite(str(tmp_path / "d.png"), np.full((5, 7, 3), 65535, np.uint16))
    for name in ("g.png", "a.png"):
        out = read_image(tmp_path / name)
        assert out.shape == (5, 7, 3) and out.dtype == np.uint8 and (out == 90).all()
    assert (read_image(tmp_path / "d.png") == 255).all()


@pytest.mark.parametrize("bits", [10, 12, 14])
def test_16_bit_images_holding_fewer_bits_are_scaled_by_their_depth(tmp_path, bits):
    """Regression: 12-bit data in a 16-bit PNG was divided by 256 into a near-black image (at most
    15 of 255), which the network and the pictures then saw."""
    import cv2

    eight = np.linspace(0, 255, 5 * 7 * 3).reshape(5, 7, 3).round().astype(np.uint8)
    deep = np.round(eight.astype(np.float64) * ((1 << bits) - 1) / 255).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "deep.png"), deep)
    assert np.abs(read_image(tmp_path / "deep.png").astype(int) - eight[..., ::-1]).max() <= 1


def test_floating_point_tiffs_are_read_without_opencv_noise(tmp_path, capfd):
    """Regression: a float32 TIFF was refused as 'not an image' after OpenCV's 'TIFFRGBAImageOK:
    Sorry, can not handle images with 32-bit samples' on stderr."""
    import cv2

    eight = np.linspace(0, 255, 6 * 8 * 3).reshape(6, 8, 3).round().astype(np.uint8)
    for name, scale in (("unit.tif", 1 / 255), ("bytes.tif", 1.0)):
        assert cv2.imwrite(str(tmp_path / name), eight.astype(np.float32) * np.float32(scale))
        assert np.abs(read_image(tmp_path / name).astype(int) - eight[..., ::-1]).max() <= 1
    bad = eight.astype(np.float32)
    bad[0, 0, 0] = np.nan
    assert cv2.imwrite(str(tmp_path / "nan.tif"), bad)
    with pytest.raises(ImageReadError, match=r"nan.tif: a floating-point image with NaN or infinite pixels"):
        read_image(tmp_path / "nan.tif")
    assert "WARN" not in capfd.readouterr().err


def test_signed_and_extreme_samples_still_read(tmp_path):
    """Reading every depth as it is refused signed TIFFs, which OpenCV's 8-bit decode had read;
    a float64 image beyond ~1e46 came back black (its scale underflowed in float32), and all
    pixels at 1e307 read as 'NaN or infinite' (their float64 sum overflowed)."""
    import cv2

    signed = np.linspace(-3000, 3000, 6 * 8 * 3).reshape(6, 8, 3).astype(np.int16)
    assert cv2.imwrite(str(tmp_path / "signed.tif"), signed)
    expected = cv2.cvtColor(cv2.imread(str(tmp_path / "signed.tif"), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert np.array_equal(read_image(tmp_path / "signed.tif"), expected)
    from facenormals.reconstruct.images import _eight_bits

    for value in (1e60, 1e307):
        assert (_eight_bits(np.full((2, 2, 3), value), Path("x.tif")) == 255).all()


def test_exif_orientation_is_applied_to_16_bit_images(tmp_path):
    PIL = pytest.importorskip("PIL.Image")
    grey = np.zeros((20, 40), np.uint16)
    grey[:, :10] = 4095  # a bright band on the left, 12-bit data
    img = PIL.fromarray(grey)
    exif = img.getexif()
    exif[0x0112] = 6
    img.save(tmp_path / "deep.png", exif=exif.tobytes())
    out = read_image(tmp_path / "deep.png")
    assert out.shape == (40, 20, 3) and out[:5].mean() > 200 and out.mean() < 100


def test_colour_order_is_rgb(tmp_path):
    import cv2

    bgr = np.zeros((3, 3, 3), np.uint8)
    bgr[..., 2] = 255  # red in OpenCV's BGR
    cv2.imwrite(str(tmp_path / "r.png"), bgr)
    assert read_image(tmp_path / "r.png")[0, 0].tolist() == [255, 0, 0]


def test_errors_name_the_file(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    (tmp_path / "empty.jpg").write_bytes(b"")
    for name, message in (("notes.txt", "not an image"), ("empty.jpg", "not an image"), ("missing.jpg", "no such file")):
        with pytest.raises(ImageReadError, match=f"{name}: {message}"):
            read_image(tmp_path / name)
    with pytest.raises(ImageReadError, match="not a file"):
        read_image(tmp_path)


def test_a_header_claiming_too_many_pixels_names_the_file(tmp_path):
    import struct
    import zlib

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", 100_000, 100_000, 8, 2, 0, 0, 0)  # 10^10 RGB pixels
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\x00")) + chunk(b"IEND", b"")
    path = tmp_path / "huge.png"
    path.write_bytes(png)
    with pytest.raises(ImageReadError, match=r"huge.png: (cannot be decoded|not an image)"):
        read_image(path)


@pytest.mark.parametrize("mode", ["L", "RGB", "CMYK"])
@pytest.mark.parametrize("size", [(3, 2), (70, 50)])
def test_intact_jpegs_of_every_colour_mode_and_tiny_ones_pass_the_integrity_check(tmp_path, mode, size):
    PIL = pytest.importorskip("PIL.Image")
    rgb = np.random.default_rng(0).integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)
    path = tmp_path / f"{mode}.jpg"
    PIL.fromarray(rgb).convert(mode).save(path, quality=95)
    out = read_image(path)
    assert out.shape == (size[1], size[0], 3) and out.dtype == np.uint8
    if mode == "L":
        assert (out[..., 0] == out[..., 2]).all()


def test_corrupt_jpeg_data_is_an_error_not_garbage_pixels(tmp_path):
    """OpenCV decodes corrupt entropy-coded JPEG data without an error (libjpeg only prints a warning)."""
    import cv2

    image = np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8)
    ok, encoded = cv2.imencode(".jpg", image)
    data = bytearray(encoded.tobytes())
    good = tmp_path / "good.jpg"
    good.write_bytes(bytes(data))
    assert read_image(good).shape == (64, 64, 3)
    start = int(len(data) * 0.85)
    data[start:-2] = bytes(255 - b for b in data[start:-2])  # damage the scan, keep the end marker
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(bytes(data))
    assert cv2.imdecode(np.frombuffer(bytes(data), np.uint8), cv2.IMREAD_COLOR) is not None  # OpenCV accepts it
    with pytest.raises(ImageReadError, match="bad.jpg: corrupt JPEG data"):
        read_image(bad)


def test_damaged_scan_data_that_still_decodes_is_refused(tmp_path, capfd):
    """29 zeroed bytes in the example photo's scan: OpenCV returned 45 % garbage pixels and exit 0
    (libjpeg only printed "Corrupt JPEG data: ... extraneous bytes" to stderr), and Pillow's decoder,
    the earlier check, accepted the stream too."""
    import io

    import cv2
    from PIL import Image

    photo = Path(__file__).resolve().parents[2] / "examples" / "data" / "astronaut.jpg"
    data = bytearray(photo.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 29] = bytes(29)
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(bytes(data))
    assert cv2.imdecode(np.frombuffer(bytes(data), np.uint8), cv2.IMREAD_COLOR) is not None  # OpenCV accepts it
    with Image.open(io.BytesIO(bytes(data))) as image:
        image.load()  # and so does Pillow
    capfd.readouterr()
    with pytest.raises(ImageReadError, match=r"bad.jpg: corrupt JPEG data \(Corrupt JPEG data: \d+ extraneous bytes"):
        read_image(bad)
    assert "Corrupt JPEG" not in capfd.readouterr().err  # the warning became the error, not stderr noise
    assert read_image(photo).shape == (512, 512, 3)


def test_other_stderr_output_during_the_decode_is_passed_on(capfd, monkeypatch):
    """fd 2 is captured only to find libjpeg's damage warnings; anything else reaches stderr."""
    import os

    import cv2

    real = cv2.imdecode

    def noisy(data, flags):
        os.write(2, b"something else\n")
        return real(data, flags)

    monkeypatch.setattr(cv2, "imdecode", noisy)
    photo = Path(__file__).resolve().parents[2] / "examples" / "data" / "astronaut.jpg"
    capfd.readouterr()
    assert read_image(photo).shape == (512, 512, 3)
    assert capfd.readouterr().err == "something else\n"



def test_padding_between_header_segments_is_not_damage(tmp_path):
    """A stray byte before the SOS marker (header padding some writers leave) decodes to the same
    pixels, but libjpeg's "extraneous bytes before marker 0xda" warning made it a corrupt JPEG."""
    photo = Path(__file__).resolve().parents[2] / "examples" / "data" / "astronaut.jpg"
    data = photo.read_bytes()
    sos = data.index(b"\xff\xda")
    second = 4 + int.from_bytes(data[4:6], "big")  # the end of the first segment after SOI
    padded = tmp_path / "padded.jpg"
    padded.write_bytes(data[:second] + b"\x00\x17" + data[second:sos] + b"\x00" + data[sos:])
    np.testing.assert_array_equal(read_image(padded), read_image(photo))


def test_truncated_jpeg_and_png_are_named_damaged_not_foreign(tmp_path):
    """OpenCV 5 returns no image for a cut-off JPEG or PNG, without libjpeg's warning: the message
    said "not an image", sending the user looking for a format problem."""
    import cv2

    for suffix in (".jpg", ".png"):
        ok, encoded = cv2.imencode(suffix, _banded(64, 64))
        cut = tmp_path / f"cut{suffix}"
        cut.write_bytes(encoded.tobytes()[: len(encoded) // 2])
        kind = "JPEG" if suffix == ".jpg" else "PNG"
        with pytest.raises(ImageReadError, match=rf"cut\{suffix}: a damaged or truncated {kind} file"):
            read_image(cut)


def test_reading_without_stderr(tmp_path):
    """With file descriptor 2 closed Python sets ``sys.stderr = None``; the decode's warning capture
    called ``sys.stderr.flush()`` and every JPEG failed with an AttributeError nobody could see."""
    import subprocess
    import sys

    photo = Path(__file__).resolve().parents[2] / "examples" / "data" / "astronaut.jpg"
    code = ("import sys; assert sys.stderr is None; from facenormals.reconstruct import read_image; "
            f"print(read_image({str(photo)!r}).shape)")
    out = subprocess.run([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                         close_fds=True, pass_fds=(), text=True, preexec_fn=lambda: __import__("os").close(2))
    assert out.stdout.strip() == "(512, 512, 3)", out


def test_a_path_of_the_wrong_type_is_named():
    with pytest.raises(ImageReadError, match="path: expected a file name .*got NoneType"):
        read_image(None)
