import pytest
import torch

from facenormals.data import PhotoAugmentation


def test_shapes_range_and_randomness():
    torch.manual_seed(0)
    images = torch.rand(8, 3, 32, 32)
    out = PhotoAugmentation(blur_probability=1.0, noise_probability=1.0)(images)
    assert out.shape == images.shape and out.min() >= 0 and out.max() <= 1
    assert not torch.allclose(out, images)
    single = PhotoAugmentation()(images[0])
    assert single.shape == (3, 32, 32)


def test_blur_alone_smooths_and_keeps_the_mean():
    torch.manual_seed(0)
    images = torch.rand(4, 3, 32, 32)
    out = PhotoAugmentation(blur_probability=1.0, blur_sigma=(1.0, 1.0), noise_probability=0.0)(images)
    step = (out[..., 1:] - out[..., :-1]).abs().mean() / (images[..., 1:] - images[..., :-1]).abs().mean()
    assert step < 0.5, "neighbouring pixels come closer"
    assert abs(float(out.mean() - images.mean())) < 0.01


def test_noise_alone_has_the_configured_spread():
    torch.manual_seed(0)
    images = torch.full((4, 3, 32, 32), 0.5)
    out = PhotoAugmentation(blur_probability=0.0, noise_probability=1.0, noise_std=(0.02, 0.02))(images)
    difference = out - images
    assert abs(float(difference.std()) - 0.02) < 0.002 and abs(float(difference.mean())) < 0.002


def test_probability_zero_is_identity():
    images = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(0))
    aug = PhotoAugmentation(blur_probability=0.0, noise_probability=0.0)
    assert torch.equal(aug(images), images)
    assert "blur_probability=0.0" in repr(aug)


def test_bad_arguments():
    with pytest.raises(ValueError, match="blur_probability"):
        PhotoAugmentation(blur_probability=2.0)
    with pytest.raises(ValueError, match="noise_std"):
        PhotoAugmentation(noise_std=(0.1, 0.0))
    with pytest.raises(ValueError, match=r"images: expected shape \(B, 3, H, W\)"):
        PhotoAugmentation()(torch.rand(2, 4, 8, 8))


def test_numpy_images_are_refused():
    import numpy as np

    with pytest.raises(ValueError, match="images: expected a torch.Tensor, got ndarray"):
        PhotoAugmentation()(np.zeros((1, 3, 8, 8), np.float32))


@pytest.mark.parametrize("kwargs, match", [
    (dict(blur_sigma=(0.5, float("inf"))), r"blur_sigma: expected a finite number, got inf"),  # was OverflowError
    (dict(blur_sigma=(float("nan"), 1.0)), r"blur_sigma: expected a finite number, got nan"),
    (dict(blur_sigma=1.0), r"blur_sigma: expected a \(low, high\) pair of numbers, got float 1.0"),  # was TypeError
    (dict(blur_sigma=(0.5, 1.0, 2.0)), r"blur_sigma: expected a \(low, high\) pair"),
    (dict(blur_sigma=(0.5, "1")), r"blur_sigma: expected a real number, got str '1'"),
    (dict(blur_sigma=(0.5, 1e4)), r"blur_sigma: expected 0 < low <= high <= 10 pixels"),  # a 60001-wide kernel
    (dict(blur_probability="0.5"), r"blur_probability: expected a real number, got str '0.5'"),  # was TypeError
    (dict(noise_probability=True), r"noise_probability: expected a real number, got bool"),
    (dict(noise_probability=float("nan")), r"noise_probability: expected a finite number, got nan"),
    (dict(noise_std=(0.0, float("inf"))), r"noise_std: expected a finite number, got inf"),  # images became 0/1
    (dict(noise_std=(0.0, 2.0)), r"noise_std: expected 0 <= low <= high <= 1"),
    (dict(noise_std=None), r"noise_std: expected a \(low, high\) pair of numbers, got NoneType"),
])
def test_non_finite_huge_or_mistyped_ranges_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PhotoAugmentation(**kwargs)


def test_the_largest_ranges_and_lists_are_accepted():
    aug = PhotoAugmentation(blur_probability=1, blur_sigma=[10, 10], noise_probability=0, noise_std=[0, 1])
    assert aug.blur_sigma == (10.0, 10.0) and aug.noise_std == (0.0, 1.0)
    assert aug(torch.rand(1, 3, 64, 64)).shape == (1, 3, 64, 64)


def _spoiled(value, shape=(2, 3, 8, 8)):
    images = torch.rand(shape)
    images.view(-1)[5] = value
    return images


@pytest.mark.parametrize(
    "images, match",
    [
        (_spoiled(float("nan")), "images: expected finite values, got 1 NaN or infinite entries"),
        (_spoiled(float("inf")), "images: expected finite values, got 1 NaN or infinite entries"),
        (_spoiled(float("-inf"), (3, 8, 8)), "images: expected finite values, got 1 NaN or infinite entries"),
        (torch.rand(2, 3, 8, 8) * 255, r"images: expected RGB values in \[0, 1\] \(an 8-bit image / 255\), got values in \[.*\]"),
        (_spoiled(-0.5), r"images: expected RGB values in \[0, 1\] .*got values in \[-0.5, "),
    ],
)
@pytest.mark.parametrize("probability", [0.0, 1.0])
def test_non_finite_or_0_255_images_are_refused(images, match, probability):
    """Regression: a NaN pixel stayed NaN, and inf or 0-255 values were silently clamped to 1 (white)."""
    aug = PhotoAugmentation(blur_probability=probability, noise_probability=probability)
    with pytest.raises(ValueError, match=match):
        aug(images)


def test_the_ends_of_the_unit_range_are_accepted():
    images = torch.zeros(1, 3, 8, 8)
    images[..., :4] = 1.0
    assert torch.equal(PhotoAugmentation(blur_probability=0.0, noise_probability=0.0)(images), images)
