import importlib.util
import re
import struct

import numpy as np
import pytest

from facenormals.data import backgrounds, random_background
from facenormals.data.backgrounds import SKIMAGE_IMAGES, PhotoLibrary


def test_backgrounds_are_deterministic_and_varied():
    images = [random_background(np.random.default_rng(i), (64, 48)) for i in range(12)]
    assert all(im.shape == (64, 48, 3) and im.dtype == np.uint8 for im in images)
    again = random_background(np.random.default_rng(3), (64, 48))
    assert np.array_equal(images[3], again)
    assert len({im.tobytes() for im in images}) == 12
    assert np.mean([im.std() for im in images]) > 5


def test_photo_folder(tmp_path):
    import cv2

    photo = np.zeros((100, 150, 3), np.uint8)
    photo[:, :75] = (0, 0, 255)  # BGR red on the left
    cv2.imwrite(str(tmp_path / "a.png"), photo)
    (tmp_path / "notes.txt").write_text("not an image")
    library = PhotoLibrary([tmp_path], use_skimage=False)
    assert len(library) == 1 and library.sources[0].endswith("a.png")
    crops = np.stack([random_background(np.random.default_rng(i), (32, 32), library, photo_probability=1.0)
                      for i in range(8)])
    assert crops.shape == (8, 32, 32, 3)
    pixels = crops.reshape(-1, 3).astype(int)  # RGB: the red half stays red, never blue
    assert (pixels == (255, 0, 0)).all(1).any() and not (pixels[:, 2] > 128).any()
    with pytest.raises(ValueError, match="does not exist"):
        PhotoLibrary([tmp_path / "missing"])


def test_skimage_is_optional():
    library = PhotoLibrary(use_skimage=True)  # scikit-image may be absent: then no photos, no error
    if importlib.util.find_spec("skimage") is None:
        assert len(library) == 0
    else:
        assert len(library) >= 10


def test_real_photo_crops_come_from_scikit_image():
    """The issue asks for crops of real photos from a package that ships images."""
    pytest.importorskip("skimage")
    from facenormals.data.backgrounds import PhotoLibrary

    library = PhotoLibrary()
    assert len(library) >= 10
    assert all(source.startswith("skimage.data.") for source in library.sources)
    faces = {"astronaut", "camera"}  # the astronaut and the cameraman: no faces in the backgrounds
    assert not {f"skimage.data.{name}" for name in faces} & set(library.sources)
    assert not faces & set(SKIMAGE_IMAGES)


def test_the_photo_library_is_the_same_every_time():
    """Every sample must follow from (seed, index) alone: a library image that changes between builds
    (skimage's binary_blobs draws new blobs on each call unless seeded) changes the samples that
    draw it from one process to the next."""
    pytest.importorskip("skimage")
    first, second = PhotoLibrary(), PhotoLibrary()
    assert first.sources == second.sources
    assert all(np.array_equal(a, b) for a, b in zip(first.images, second.images))


def test_undecodable_photos_and_empty_folders_are_named(tmp_path):
    import cv2

    good = tmp_path / "good"
    good.mkdir()
    cv2.imwrite(str(good / "a.png"), np.zeros((64, 64, 3), np.uint8))
    (good / "b.jpg").write_text("hello")
    with pytest.raises(ValueError, match=r"background photo .*b.jpg cannot be decoded"):
        PhotoLibrary([good], use_skimage=False)
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("no photos here")
    with pytest.raises(ValueError, match=r"background folder .*empty holds no usable"):
        PhotoLibrary([empty], use_skimage=False)


def test_hidden_files_and_macos_sidecars_are_not_photos(tmp_path):
    import cv2

    cv2.imwrite(str(tmp_path / "beach.jpg"), np.zeros((64, 64, 3), np.uint8))
    (tmp_path / "._beach.jpg").write_bytes(b"\x00\x05\x16\x07AppleDouble")
    (tmp_path / "__MACOSX").mkdir()
    (tmp_path / "__MACOSX" / "beach.jpg").write_bytes(b"resource fork")
    library = PhotoLibrary([tmp_path], use_skimage=False)
    assert library.sources == [str(tmp_path / "beach.jpg")]


def test_bright_clutter_saturates_instead_of_wrapping_around(monkeypatch):
    """Random colours reach 315; cast to uint8 unclipped, 300 became 44 (hard colour bands)."""
    monkeypatch.setattr(backgrounds, "_random_color", lambda rng: np.full(3, 300.0))
    for seed in range(4):
        image = backgrounds._clutter(np.random.default_rng(seed), 32, 32)
        assert (image == 255).all(), seed


def test_every_listed_skimage_image_exists():
    """A name that scikit-image lacks would be skipped: a dead entry (once `motorcycle_left`)."""
    skdata = pytest.importorskip("skimage.data")
    assert [name for name in SKIMAGE_IMAGES if not hasattr(skdata, name)] == []


def test_skimage_images_that_cannot_load_are_named(monkeypatch):
    """Skipping an image changes which photo every later sample crops: say so. Other errors are bugs."""
    skdata = pytest.importorskip("skimage.data")

    def needs_pooch():
        raise ModuleNotFoundError("requires the installation of an optional dependency, pooch")

    monkeypatch.setattr(skdata, "coins", needs_pooch)
    with pytest.warns(UserWarning, match=r"skimage.data.coins skipped \(ModuleNotFoundError: requires .*pooch"):
        library = PhotoLibrary()
    assert library.skipped == ["skimage.data.coins"] and "skimage.data.coins" not in library.sources

    def broken():
        raise RuntimeError("a bug, not a missing download")

    monkeypatch.undo()
    monkeypatch.setattr(skdata, "moon", broken)
    with pytest.raises(RuntimeError, match="a bug"):
        PhotoLibrary()


def test_the_fingerprint_follows_the_photos(tmp_path):
    import cv2

    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((64, 64, 3), np.uint8))
    cv2.imwrite(str(tmp_path / "b.png"), np.full((64, 80, 3), 200, np.uint8))
    first = PhotoLibrary([tmp_path], use_skimage=False).fingerprint()
    assert first == PhotoLibrary([tmp_path], use_skimage=False).fingerprint() and first["count"] == 2
    cv2.imwrite(str(tmp_path / "b.png"), np.full((64, 80, 3), 201, np.uint8))
    assert PhotoLibrary([tmp_path], use_skimage=False).fingerprint() != first


def test_bad_background_arguments():
    rng = np.random.default_rng(0)
    for size in [(8,), 8, (8.5, 8), (0, 8), (True, 8)]:
        with pytest.raises(ValueError, match=r"size: expected \(H, W\), two integers >= 1"):
            random_background(rng, size)
    with pytest.raises(ValueError, match=r"photo_probability: expected a probability in \[0, 1\], got 1.5"):
        random_background(rng, (8, 8), photo_probability=1.5)


@pytest.mark.parametrize("rng", [0, None, np.random.RandomState(0)])
def test_an_rng_that_is_no_generator_is_named(rng):
    """Regression: random_background(0) and random_background(None) failed with an AttributeError."""
    with pytest.raises(ValueError, match=f"rng: expected a numpy.random.Generator .*, got {type(rng).__name__} "):
        random_background(rng)


def _jpeg(seed=0):
    """A small photo-like JPEG (smooth noise), as bytes."""
    import cv2

    image = (np.random.default_rng(seed).random((96, 128, 3)) * 255).astype(np.uint8)
    ok, data = cv2.imencode(".jpg", cv2.GaussianBlur(image, (0, 0), 2), [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    return data.tobytes()


def _flip(data, offset):
    damaged = bytearray(data)
    damaged[offset] ^= 0xFF
    return bytes(damaged)


@pytest.mark.parametrize("damage, match", [
    (lambda data: data[: len(data) * 2 // 3], "a damaged or truncated JPEG file"),
    (lambda data: _flip(data, len(data) // 2), "corrupt JPEG data"),
], ids=["cut short", "a flipped byte"])
def test_damaged_photos_are_named_instead_of_cropped(tmp_path, damage, match):
    """Regression: the photos were read with cv2.imread, which decodes a truncated or damaged JPEG to
    grey or garbage pixels without an error (libjpeg only prints a warning): they went into the
    synthetic dataset's backgrounds. read_image (as for reconstruction) refuses them."""
    import cv2

    (tmp_path / "a.jpg").write_bytes(_jpeg())
    path = tmp_path / "b.jpg"
    path.write_bytes(damage(_jpeg()))
    assert cv2.imread(str(path), cv2.IMREAD_COLOR) is not None  # OpenCV alone accepts it
    with pytest.raises(ValueError, match=rf"background photo {re.escape(str(path))} cannot be decoded as an image "
                                         rf"\({match}.*\); remove or replace it"):
        PhotoLibrary([tmp_path], use_skimage=False)


def _with_exif_orientation(jpeg, orientation):
    """``jpeg`` with an EXIF segment whose orientation tag is ``orientation`` (6: rotate 90° clockwise)."""
    tiff = b"II*\x00" + struct.pack("<IH", 8, 1) + struct.pack("<HHII", 0x0112, 3, 1, orientation) + bytes(4)
    exif = b"Exif\x00\x00" + tiff
    return jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(exif) + 2) + exif + jpeg[2:]


def test_intact_photos_give_the_same_pixels_as_with_cv2_imread(tmp_path):
    """read_image replaced cv2.imread (BGR) + cvtColor: the RGB pixels of intact photos are unchanged."""
    import cv2

    rng = np.random.default_rng(1)
    colour = (rng.random((70, 90, 3)) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "colour.png"), colour)
    cv2.imwrite(str(tmp_path / "grey.png"), colour[..., 0])
    cv2.imwrite(str(tmp_path / "alpha.png"), np.dstack([colour, colour[..., :1]]))
    deep = (rng.random((40, 50, 3)) * 65535).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "deep.png"), deep)
    cv2.imwrite(str(tmp_path / "large.jpeg"), cv2.resize(colour, (900, 700)))
    (tmp_path / "photo.jpg").write_bytes(_jpeg(2))
    (tmp_path / "rotated.JPG").write_bytes(_with_exif_orientation(_jpeg(3), 6))
    library = PhotoLibrary([tmp_path], use_skimage=False)
    paths = sorted(p for p in tmp_path.iterdir())
    assert library.sources == [str(p) for p in paths]
    for path, image in zip(paths, library.images):
        before = backgrounds._to_rgb_uint8(cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB))
        if path.name == "deep.png":  # 16 bits are scaled by 255 / 65535 and rounded, not shifted by 8 as by cv2
            before = np.round(deep[..., ::-1] * (255 / 65535)).astype(np.uint8)
        assert image.dtype == np.uint8 and np.array_equal(image, before), path.name
    assert library.images[paths.index(tmp_path / "rotated.JPG")].shape == (128, 96, 3)  # turned upright
    rgb = library.images[paths.index(tmp_path / "colour.png")]
    assert np.array_equal(rgb, colour[..., ::-1])  # RGB, not OpenCV's BGR
