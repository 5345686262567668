import numpy as np
import pytest
import torch

from facenormals.render import draw_alignment, normal_map_to_image


def test_overlay_draws_points_and_writes_png(tmp_path):
    image = np.zeros((16, 16, 3), np.uint8)
    out = draw_alignment(image, torch.tensor([[3.0, 4.0], [10.0, 12.0]]), torch.tensor([[8.0, 8.0], [float("nan"), 1.0]]),
                         path=tmp_path / "o.png", scale=4)
    assert out.shape == (64, 64, 3) and (tmp_path / "o.png").exists()
    assert out[4 * 4 + 1, 3 * 4 + 1].sum() > 0  # the vertex dot at pixel (3, 4)
    assert out[0, 0].sum() == 0


def test_overlay_bad_image():
    with pytest.raises(ValueError, match="image"):
        draw_alignment(np.zeros((4, 4, 3), np.float32), torch.zeros(1, 2))


@pytest.mark.parametrize("shape", [(0, 0, 3), (0, 5, 3), (5, 0), (0, 0)])
def test_overlay_refuses_an_empty_image(shape):
    """Regression: an empty image failed inside cv2.resize (cv2.error)."""
    with pytest.raises(ValueError, match=r"image: expected a non-empty image \(H, W >= 1\), got shape"):
        draw_alignment(np.zeros(shape, np.uint8), torch.rand(3, 2))


def test_normal_map_colours():
    nmap = torch.zeros(3, 1, 2)
    nmap[:, 0, 0] = torch.tensor([0.0, -1.0, 0.0])  # up (y is down)
    img = normal_map_to_image(nmap)
    assert img[0, 0].tolist() == [128, 255, 128] and img[0, 1].tolist() == [0, 0, 0]
    # oblique normals (x not 0, every component of another size): a flipped x or a wrong scale shows
    g = torch.Generator().manual_seed(2)
    n = torch.nn.functional.normalize(torch.randn(3, 4, 5, generator=g, dtype=torch.float64), dim=0)
    expected = np.round((n.numpy().transpose(1, 2, 0) * [1, -1, -1] + 1) / 2 * 255).astype(np.uint8)
    np.testing.assert_array_equal(normal_map_to_image(n), expected)


def test_dots_sit_on_the_pixel_centres():
    """Pixel (3, 4) of a 16² image upsampled 8× spans columns 24..31 and rows 32..39: its dot is
    centred at (27.5, 35.5), so a half-pixel convention error (4 upsampled pixels) is caught."""
    out = draw_alignment(np.zeros((16, 16, 3), np.uint8), torch.tensor([[3.0, 4.0]]), scale=8)
    brightest = out.sum(2) == out.sum(2).max()
    rows, cols = np.nonzero(brightest)
    assert abs(rows.mean() - 35.5) <= 0.5 and abs(cols.mean() - 27.5) <= 0.5
    # the intensity-weighted centre of a dot is the point's, to a tenth of a canvas pixel (integer
    # centres rounded half to even put it 1/(2 scale) px off, right and down at scale 4)
    for scale, point in ((4, (2.0, 3.0)), (4, (5.3, 2.6)), (8, (3.0, 4.0))):
        out = draw_alignment(np.zeros((16, 16, 3), np.uint8), torch.tensor([point]), scale=scale).sum(2).astype(float)
        rows, cols = np.mgrid[: out.shape[0], : out.shape[1]]
        centre = ((cols * out).sum() / out.sum(), (rows * out).sum() / out.sum())
        expected = [(c + 0.5) * scale - 0.5 for c in point]
        assert np.allclose(centre, expected, atol=0.1), (scale, point, centre, expected)


def test_points_off_the_image_or_not_finite_are_skipped(tmp_path):
    image = np.zeros((8, 8, 3), np.uint8)
    points = torch.tensor([[float("nan"), 1.0], [float("inf"), 2.0], [1e12, 3.0], [-5e11, 1e11], [2.0, 2.0]])
    out = draw_alignment(image, points, torch.tensor([[1e12, 1e12], [4.0, 4.0]]), scale=4)
    only_inside = draw_alignment(image, points[4:], torch.tensor([[4.0, 4.0]]), scale=4)
    assert np.array_equal(out, only_inside) and out.sum() > 0


def test_overlay_argument_checks(tmp_path):
    image = np.zeros((8, 8, 3), np.uint8)
    points = torch.tensor([[1.0, 1.0], [2.0, 2.0]])
    with pytest.raises(ValueError, match="visible: expected a bool mask, got dtype torch.int64"):
        draw_alignment(image, points, visible=torch.tensor([1, 0]))
    with pytest.raises(ValueError, match=r"visible: expected shape \(2,\), got \(3,\)"):
        draw_alignment(image, points, visible=torch.tensor([True, False, True]))
    with pytest.raises(ValueError, match=r"landmark_pixels: expected shape \(L, 2\) \(2 dimensions\), got \(3,\)"):
        draw_alignment(image, points, landmark_pixels=torch.zeros(3))
    with pytest.raises(ValueError, match="scale: expected an integer >= 1"):
        draw_alignment(image, points, scale=0)
    with pytest.raises(OSError, match="o.unknown: cannot write the overlay"):
        draw_alignment(image, points, path=tmp_path / "o.unknown")
    assert list(tmp_path.iterdir()) == []
    assert draw_alignment(image, points, visible=torch.tensor([True, False])).sum() > 0


def test_overlay_max_points_must_be_a_positive_integer():
    image = np.zeros((8, 8, 3), np.uint8)
    with pytest.raises(ValueError, match="max_points: expected an integer >= 1, got -1"):
        draw_alignment(image, torch.zeros(3, 2), max_points=-1)


def test_normal_map_to_image_refuses_nan_and_integer_maps():
    """NaN normals were drawn as black background, silently."""
    with pytest.raises(ValueError, match="normal_map: expected finite values"):
        normal_map_to_image(torch.full((3, 2, 2), float("nan")))
    with pytest.raises(ValueError, match="normal_map: expected a floating"):
        normal_map_to_image(torch.zeros(3, 2, 2, dtype=torch.long))
