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
    images = torch.rand(2, 3, 16, 16)
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
