import pytest
import torch

from facenormals.data import landmark_maps, landmarks_from_maps


def test_gaussian_values_and_cut_off():
    points = torch.tensor([[[10.25, 7.5], [3.0, 3.0]]], dtype=torch.float64)
    maps = landmark_maps(points, torch.tensor([[True, False]]), (16, 20), sigma=1.5, radius=3.0)
    assert maps.shape == (1, 2, 16, 20) and maps.dtype == torch.float64
    v, u = torch.meshgrid(torch.arange(16.0), torch.arange(20.0), indexing="ij")
    d2 = (u - 10.25) ** 2 + (v - 7.5) ** 2
    expected = torch.where(d2 <= 4.5**2, torch.exp(-d2 / (2 * 1.5**2)), torch.zeros(()))
    torch.testing.assert_close(maps[0, 0], expected.double())
    assert (maps[0, 1] == 0).all(), "invisible landmarks leave their channel empty"


def test_peak_is_one_at_integer_positions_and_nan_is_never_drawn():
    maps = landmark_maps(torch.tensor([[[4.0, 5.0], [float("nan"), 1.0]]]), None, (8, 8))
    assert float(maps[0, 0, 5, 4]) == 1.0 and float(maps[0, 0].max()) == 1.0
    assert (maps[0, 1] == 0).all()


@pytest.mark.parametrize("sigma", [1.0, 1.5, 2.5])
def test_sub_pixel_peaks_round_trip(sigma):
    generator = torch.Generator().manual_seed(0)
    points = torch.rand(3, 24, 2, generator=generator) * 100 + 10
    visible = torch.rand(3, 24, generator=generator) > 0.3
    maps = landmark_maps(points, visible, (128, 128), sigma=sigma)
    peaks, found = landmarks_from_maps(maps)
    assert torch.equal(found, visible)
    assert torch.isnan(peaks[~visible]).all()
    assert float((peaks - points).norm(dim=-1)[visible].max()) < 1e-3


@pytest.mark.parametrize("u, v", [(0.2, 127.0), (0.3, 5.5), (0.49, 30.6), (-0.3, 31.4), (31.4, -0.2), (12.7, 31.45)])
def test_border_landmark_keeps_its_sub_pixel_position(u, v):
    # the refinement used to stop at the first and last row and column: up to 0.5 px of bias there
    size = 128 if v > 100 else 32
    maps = landmark_maps(torch.tensor([[[u, v]]], dtype=torch.float64), None, (size, size))
    peaks, found = landmarks_from_maps(maps)
    assert bool(found) and float((peaks[0, 0] - torch.tensor([u, v], dtype=torch.float64)).norm()) < 1e-6


def test_two_pixel_maps_keep_the_peak_pixel():
    peaks, found = landmarks_from_maps(torch.tensor([[[[0.2, 0.9], [0.1, 0.3]]]]))
    assert bool(found) and peaks[0, 0].tolist() == [1.0, 0.0]


def test_bad_inputs():
    with pytest.raises(ValueError, match="maps: expected finite values"):  # a NaN peak is not "not found"
        landmarks_from_maps(torch.full((1, 2, 4, 4), float("nan")))
    with pytest.raises(ValueError, match=r"points: expected shape \(B, L, 2\)"):
        landmark_maps(torch.zeros(2, 3), None, (8, 8))
    with pytest.raises(ValueError, match=r"visible: expected shape \(B, L\) with B=1"):
        landmark_maps(torch.zeros(1, 3, 2), torch.ones(2, 3, dtype=torch.bool), (8, 8))
    with pytest.raises(ValueError, match="visible: expected a bool tensor"):
        landmark_maps(torch.zeros(1, 3, 2), torch.ones(1, 3), (8, 8))
    with pytest.raises(ValueError, match="points: expected a floating-point tensor"):
        landmark_maps(torch.zeros(1, 3, 2, dtype=torch.long), None, (8, 8))
    with pytest.raises(ValueError, match="sigma"):
        landmark_maps(torch.zeros(1, 3, 2), None, (8, 8), sigma=0.0)
    with pytest.raises(ValueError, match=r"maps: expected shape \(B, L, H, W\)"):
        landmarks_from_maps(torch.zeros(3, 8, 8))
    for size in [(8,), 8, (8.0, 8), (0, 8)]:
        with pytest.raises(ValueError, match=r"image_size: expected \(H, W\), two integers >= 1"):
            landmark_maps(torch.zeros(1, 3, 2), None, size)


def test_decoding_with_one_threshold_per_channel():
    z = landmark_maps(torch.tensor([[[3.0, 2.0], [5.0, 4.0]]]), None, (8, 8)) * torch.tensor([0.5, 0.9]).view(1, 2, 1, 1)
    _, found = landmarks_from_maps(z, threshold=torch.tensor([0.6, 0.6]))
    assert found.tolist() == [[False, True]]
    _, found = landmarks_from_maps(z, threshold=torch.tensor([0.4, 0.95]))
    assert found.tolist() == [[True, False]]
    with pytest.raises(ValueError, match="threshold"):
        landmarks_from_maps(z, threshold=torch.tensor([0.1, 0.2, 0.3]))


def test_bfloat16_peaks_lie_on_the_right_pixel():
    """bfloat16 holds whole numbers exactly only up to 256: the pixel grid is built in float32."""
    points = torch.tensor([[[300.0, 10.0]]])
    maps = landmark_maps(points.bfloat16(), None, (20, 400))
    assert maps.dtype == torch.bfloat16
    assert int(maps[0, 0].float().argmax()) == 10 * 400 + 300


def test_scalar_options_and_empty_maps_are_checked():
    with pytest.raises(ValueError, match="sigma: expected a real number, got str"):
        landmark_maps(torch.zeros(1, 1, 2), None, (8, 8), sigma="x")
    with pytest.raises(ValueError, match="sigma: expected a real number, got Tensor"):
        landmark_maps(torch.zeros(1, 1, 2), None, (8, 8), sigma=torch.tensor([1.0, 2.0]))
    with pytest.raises(ValueError, match=r"maps: expected H, W >= 1, got shape \(1, 2, 0, 5\)"):
        landmarks_from_maps(torch.zeros(1, 2, 0, 5))


def test_eps_and_a_nan_threshold_are_checked():
    """eps = 0 took log(0) beside a sharp peak: a NaN position for a landmark counted as found; a NaN
    threshold found nothing, silently."""
    z = landmark_maps(torch.tensor([[[3.2, 4.0]]]), None, (8, 8), sigma=0.3)
    for eps in (0.0, -1.0):
        with pytest.raises(ValueError, match=f"eps: expected a finite number > 0, got {eps}"):
            landmarks_from_maps(z, eps=eps)
    with pytest.raises(ValueError, match="threshold: expected numbers .*got NaN"):
        landmarks_from_maps(z, threshold=float("nan"))
    points, found = landmarks_from_maps(z, threshold=float("-inf"))  # -inf keeps every peak
    assert bool(found.all()) and bool(torch.isfinite(points).all())


@pytest.mark.parametrize("dtype,tolerance", [(torch.float16, 0.003), (torch.bfloat16, 0.02)])
def test_half_precision_maps_decode_to_float32_sub_pixel_points(dtype, tolerance):
    """Regression: points came back in the maps' dtype, whose pixel grid is too coarse (bfloat16
    spaces whole numbers 0.5 apart above 64): a half-precision network's landmarks lost up to 0.25 px."""
    g = torch.Generator().manual_seed(0)
    points = torch.rand(4, 24, 2, generator=g, dtype=torch.float64) * 120 + 4
    maps = landmark_maps(points, None, (128, 128), sigma=1.5).to(dtype)
    decoded, found = landmarks_from_maps(maps, threshold=torch.full((24,), 0.5, dtype=dtype))
    assert decoded.dtype == torch.float32 and bool(found.all())
    assert float((decoded.double() - points).abs().max()) < tolerance


def test_a_float_threshold_is_not_rounded_to_the_maps_half_precision():
    """A bfloat16 peak of 0.77734375 exceeds the threshold 0.776, which bfloat16 rounds up to the
    peak itself: compared in bfloat16, the landmark was not found."""
    maps = torch.zeros(1, 1, 5, 5, dtype=torch.bfloat16)
    maps[0, 0, 2, 2] = 0.77734375
    assert bool(landmarks_from_maps(maps, threshold=0.776)[1].all())
