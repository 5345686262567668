import cv2
import numpy as np
import pytest

from facenormals.reconstruct import FaceBox, crop_square, detect_faces, head_crop_box


def test_finds_the_astronaut_face():
    skdata = pytest.importorskip("skimage.data")
    faces = detect_faces(skdata.astronaut())
    assert faces, "no face found"
    cx, cy = faces[0].center
    # Eileen Collins' face: between the eyes and the mouth, roughly x 180-270, y 70-165
    assert 205 < cx < 240 and 100 < cy < 135 and 70 < faces[0].width < 130


def test_a_small_face_in_a_large_photo_is_found_by_the_finer_searches():
    """Regression: the photo was searched at 480 px for faces of at least 0.08 of its shorter side,
    so a 105-px face in a 2400 x 1800 photo (a person a few metres away) was "no face found"."""
    skdata = pytest.importorskip("skimage.data")
    canvas = np.full((1800, 2400, 3), 128, np.uint8)
    canvas[1000:1512, 1500:2012] = skdata.astronaut()
    assert detect_faces(canvas, retry_sides=()) == []
    faces = detect_faces(canvas)
    assert faces, "no face found"
    cx, cy = faces[0].center
    assert 1705 < cx < 1740 and 1100 < cy < 1135 and 70 < faces[0].width < 130


def test_no_face_in_a_flat_image_or_a_gradient():
    assert detect_faces(np.full((200, 300, 3), 128, np.uint8)) == []
    ramp = np.tile(np.linspace(0, 255, 256).astype(np.uint8), (256, 1))
    assert detect_faces(ramp) == []


def test_bad_image_argument():
    with pytest.raises(ValueError, match="image"):
        detect_faces(np.zeros((10, 10, 3), np.float32))
    with pytest.raises(ValueError, match=r"image: expected a uint8 array \(H, W\[, 1\|3\|4\]\), got uint8 \(10, 10, 2\)"):
        detect_faces(np.zeros((10, 10, 2), np.uint8))
    assert detect_faces(np.full((40, 40, 1), 128, np.uint8)) == []  # one-channel grey is grey


@pytest.mark.parametrize("box,size,match", [
    ((0.0, 0.0, float("nan")), 8, "box: expected a crop box .* three finite numbers"),
    ((float("inf"), 0.0, 4.0), 8, "box: expected a crop box .* three finite numbers"),
    ((0.0, 0.0, 0.0), 8, "box: expected a crop box .* three finite numbers"),
    ((0.0, 0.0, 4.0), 0, r"size: expected an integer in \[1, 4096\], got 0"),
])
def test_crop_square_bad_box_or_size(box, size, match):
    with pytest.raises(ValueError, match=match):
        crop_square(np.zeros((10, 10, 3), np.uint8), box, size)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("side", [4.0, 32.0])  # sampled directly, and blurred first (downsampling)
def test_crop_square_refuses_a_float_image_that_is_not_finite(dtype, value, side):
    """Regression: a float image holding NaN gave a NaN crop, silently."""
    image = np.full((40, 40, 3), 0.5, dtype)
    image[2, 3, 1] = value
    with pytest.raises(ValueError, match="image: expected finite values, got 1 NaN or infinite entries"):
        crop_square(image, (0.0, 0.0, side), 8)
    image[2, 3, 1] = 0.5
    assert np.allclose(crop_square(image, (0.0, 0.0, side), 8), 0.5)


def test_grouping_prefers_many_overlapping_hits():
    from facenormals.reconstruct.detect import _group

    hits = [FaceBox(100, 100, 50, 50), FaceBox(104, 98, 52, 52), FaceBox(98, 103, 48, 48), FaceBox(10, 10, 80, 80)]
    groups = _group(hits, 0.3)
    assert groups[0].hits == 3 and abs(groups[0].center[0] - 125.3) < 1.0
    assert groups[1].hits == 1 and groups[1].width == 80


def test_head_crop_box_geometry():
    x0, y0, side = head_crop_box(FaceBox(100, 50, 40, 40), scale=2.0, shift=-0.25)
    assert side == 80 and x0 == 80 and y0 == 70 - 10 - 40


def test_crop_square_matches_a_naive_bilinear_loop():
    rng = np.random.default_rng(1)
    img = rng.integers(0, 255, (30, 40, 3)).astype(np.uint8)
    box, size = (5.3, 3.7, 12.0), 16  # upsampling: no pre-blur
    out = crop_square(img, box, size)
    s = box[2] / size
    for v in range(0, size, 5):
        for u in range(0, size, 5):
            x, y = box[0] + (u + 0.5) * s - 0.5, box[1] + (v + 0.5) * s - 0.5
            if int(cv2.__version__.split(".")[0]) < 5:  # OpenCV 4 warps uint8 at 1/32-pixel positions
                x, y = round(x * 32) / 32, round(y * 32) / 32
            x0, y0 = int(np.floor(x)), int(np.floor(y))
            ax, ay = x - x0, y - y0
            ref = ((1 - ax) * (1 - ay) * img[y0, x0] + ax * (1 - ay) * img[y0, x0 + 1]
                   + (1 - ax) * ay * img[y0 + 1, x0] + ax * ay * img[y0 + 1, x0 + 1])
            assert np.abs(out[v, u].astype(float) - ref).max() <= 1.0


@pytest.mark.parametrize("box", [(40.0, 30.0, 64.0), (-20.5, -13.2, 90.0), (70.3, 55.8, 80.0),
                                 (-200.0, 10.0, 100.0), (-50.0, -40.0, 300.0), (130.0, 90.0, 40.0)])
def test_crop_square_downsampling_equals_blurring_the_whole_photo(box):
    # crop_square blurs only the region it samples; the pixels must be those of blurring everything
    rng = np.random.default_rng(2)
    img = rng.integers(0, 255, (120, 150, 3)).astype(np.uint8)
    size = 16
    s = box[2] / size
    blurred = cv2.GaussianBlur(img, (0, 0), 0.5 * np.sqrt(s * s - 1.0))
    matrix = np.array([[s, 0.0, box[0] + 0.5 * s - 0.5], [0.0, s, box[1] + 0.5 * s - 0.5]])
    ref = cv2.warpAffine(blurred, matrix, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_REPLICATE)
    # equal up to one grey level: warpAffine rounds source positions to 1/32 px, and the region's
    # integer offset can tip a rounding of the fractional position
    diff = np.abs(crop_square(img, box, size).astype(int) - ref.astype(int))
    assert diff.max() <= 1 and (diff > 0).mean() < 0.02


def test_crop_square_maps_a_dot_to_the_documented_pixel():
    img = np.zeros((400, 400, 3), np.uint8)
    img[200:204, 120:124] = 255  # a 4x4 block centred on (121.5, 201.5)
    view_box = (100.0, 180.0, 64.0)  # 4 image px per crop px when cropping to 16
    out = crop_square(img, view_box, size=16).astype(float)[..., 0]
    v, u = np.unravel_index(out.argmax(), out.shape)
    s = 4.0
    assert (u + 0.5) * s - 0.5 + view_box[0] == pytest.approx(121.5, abs=s / 2 + 1e-9)
    assert (v + 0.5) * s - 0.5 + view_box[1] == pytest.approx(201.5, abs=s / 2 + 1e-9)


def test_slivers_have_no_face_and_do_not_crash():
    for shape in ((3, 5000), (5000, 3), (1, 2000), (30, 4000)):  # the downscale used to round a side to 0
        assert detect_faces(np.full(shape, 128, np.uint8)) == []


@pytest.mark.parametrize("name,value", [("max_side", 0), ("max_side", -5), ("max_side", 23.5), ("min_face", 2.0),
                                        ("min_face", float("nan")), ("min_face", 0.0), ("min_hits", 0),
                                        ("min_hits", True), ("retry_sides", 960), ("retry_sides", (960, 10))])
def test_detector_options_are_checked(name, value):
    """A bad option used to return "no face" (max_side=0, min_face=2) or a message not naming it."""
    with pytest.raises(ValueError, match=name):
        detect_faces(np.full((64, 64, 3), 128, np.uint8), **{name: value})


def test_an_empty_image_has_no_face_in_colour_as_in_grey():
    assert detect_faces(np.zeros((0, 0, 3), np.uint8)) == []
    assert detect_faces(np.zeros((0, 0), np.uint8)) == []


@pytest.mark.parametrize("image,box,size,name", [
    (np.zeros((0, 0, 3), np.uint8), (0.0, 0.0, 4.0), 8, "image"),
    (np.zeros((8, 8, 3), np.int64), (0.0, 0.0, 4.0), 8, "image"),
    (np.zeros((8, 8, 3), bool), (0.0, 0.0, 4.0), 8, "image"),
    (np.zeros((8, 8, 3), np.uint8), (0.0, 0.0, 4.0, 4.0), 8, "box"),  # a face box (x, y, w, h) by mistake
    (np.zeros((8, 8, 3), np.uint8), (0.0, 0.0), 8, "box"),
    (np.zeros((8, 8, 3), np.uint8), "abc", 8, "box"),
    (np.zeros((8, 8, 3), np.uint8), (0.0, 0.0, 4.0), 100_000, "size"),
])
def test_crop_square_names_what_is_wrong(image, box, size, name):
    """These reached OpenCV (cv2.error) or a bare unpacking error."""
    with pytest.raises(ValueError, match=name):
        crop_square(image, box, size)


def test_face_boxes_and_crop_options_are_checked():
    """``scale=-1`` gave a negative side, NaN boxes NaN crops, a zero box a ZeroDivisionError in iou
    and an (x, y, w, h) tuple an AttributeError."""
    for args, match in (((0, 0, float("nan"), 10), "FaceBox width: expected a finite number, got nan"),
                        ((0, 0, 0, 0), r"FaceBox: expected width and height > 0, got 0 x 0"),
                        (("1", 0, 5, 5), "FaceBox x: expected a finite number, got '1'")):
        with pytest.raises(ValueError, match=match):
            FaceBox(*args)
    face = FaceBox(100, 100, 50, 50)
    for kwargs, match in (({"scale": -1}, "scale: expected a number > 0, got -1"),
                          ({"scale": float("nan")}, "scale: expected a finite number, got nan"),
                          ({"shift": float("inf")}, "shift: expected a finite number, got inf")):
        with pytest.raises(ValueError, match=match):
            head_crop_box(face, **kwargs)
    with pytest.raises(ValueError, match="face: expected a FaceBox, got tuple"):
        head_crop_box((100, 100, 50, 50))
    assert FaceBox(np.float64(1.5), np.int64(2), 3, 4).center == (3.0, 4.0)
