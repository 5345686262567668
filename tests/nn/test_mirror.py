"""Test-time mirroring: the maths of mapping a mirrored prediction back, against naive loops."""

import pytest
import torch
from torch import nn

from facenormals.models import LANDMARK_NAMES, LANDMARK_PAIRS
from facenormals.nn import NormalLandmarkUNet, UNetOutput, mirror_averaged, mirror_output, mirror_permutation


def test_permutation_swaps_every_pair_and_keeps_the_midline():
    perm = mirror_permutation()
    assert sorted(perm) == list(range(24)) and all(perm[perm[i]] == i for i in range(24))
    for right, left in LANDMARK_PAIRS:
        assert LANDMARK_NAMES[perm[LANDMARK_NAMES.index(right)]] == left
    for name in ("nose_tip", "chin", "upper_lip"):
        assert perm[LANDMARK_NAMES.index(name)] == LANDMARK_NAMES.index(name)
    with pytest.raises(ValueError, match="pairs"):
        mirror_permutation(("a", "b"), [("a", "c")])


def test_mirror_output_against_a_pixel_loop():
    g = torch.Generator().manual_seed(0)
    n = torch.nn.functional.normalize(torch.randn(2, 3, 5, 7, generator=g), dim=1)
    out = UNetOutput(n, torch.rand(2, 24, 5, 7, generator=g), torch.randn(2, 1, 5, 7, generator=g))
    perm = mirror_permutation()
    back = mirror_output(out, perm)
    W = 7
    for x in range(W):
        xm = W - 1 - x  # pixel centres: x -> W - 1 - x
        assert torch.equal(back.normals[:, 0, :, x], -out.normals[:, 0, :, xm])
        assert torch.equal(back.normals[:, 1:, :, x], out.normals[:, 1:, :, xm])
        assert torch.equal(back.foreground_logits[..., x], out.foreground_logits[..., xm])
        for c in range(24):
            assert torch.equal(back.landmarks[:, c, :, x], out.landmarks[:, perm[c], :, xm])
    with pytest.raises(ValueError, match="output.landmarks"):
        mirror_output(out, [0, 1])
    with pytest.raises(ValueError, match="permutation: expected a permutation of 0..23"):
        mirror_output(out, [0] * 24)


class _Mirrorable(nn.Module):
    """Predicts a fixed scene: a sphere's normals and one landmark Gaussian per channel."""

    def __init__(self, equivariant: bool):
        super().__init__()
        self.equivariant = equivariant
        ys, xs = torch.meshgrid(torch.arange(16.0), torch.arange(16.0), indexing="ij")
        nx, ny = (xs - 7.5) / 12, (ys - 7.5) / 12
        self.n = torch.stack([nx, ny, -(1 - nx**2 - ny**2).sqrt()])[None]
        self.z = torch.rand(1, 24, 16, 16, generator=torch.Generator().manual_seed(1))

    def forward(self, images):
        flipped = images[:, 0, 0, 0] < 0.5  # the marker pixel tells the mirrored input apart
        n = self.n.expand(images.shape[0], -1, -1, -1).clone()
        z = self.z.expand(images.shape[0], -1, -1, -1).clone()
        if self.equivariant:
            z[flipped] = mirror_output(UNetOutput(n[flipped], z[flipped], n[flipped, :1]), mirror_permutation()).landmarks
        return UNetOutput(n, z, torch.zeros_like(n[:, :1]))


def test_an_equivariant_network_is_unchanged_and_a_blind_one_is_averaged():
    images = torch.zeros(1, 3, 16, 16)
    images[..., 0] = 1.0  # the marker pixel (0, 0) is 1 in the original and 0 in the mirrored image
    eq = _Mirrorable(equivariant=True)
    avg = mirror_averaged(eq, images)
    torch.testing.assert_close(avg.normals, eq.n)  # the sphere's normals are mirror-symmetric
    torch.testing.assert_close(avg.landmarks, eq.z)
    blind = _Mirrorable(equivariant=False)
    avg = mirror_averaged(blind, images)
    expected = 0.5 * (blind.z + blind.z.flip(-1)[:, mirror_permutation()])
    torch.testing.assert_close(avg.landmarks, expected)


def test_bad_input_names_the_argument():
    net = NormalLandmarkUNet(base_channels=4, depth=2).eval()
    with pytest.raises(ValueError, match="images"):
        mirror_averaged(net, torch.rand(3, 16, 16))
    with pytest.raises(ValueError, match="images"):
        mirror_averaged(net, torch.zeros(1, 3, 16, 16, dtype=torch.uint8))
    n = torch.nn.functional.normalize(torch.randn(1, 3, 4, 5), dim=1)
    with pytest.raises(ValueError, match=r"output.landmarks: expected shape \(B, 2, H, W\) with H=4 .*got \(1, 2, 6, 7\)"):
        mirror_output(UNetOutput(n, torch.rand(1, 2, 6, 7), torch.randn(1, 1, 4, 5)), [1, 0])
    with pytest.raises(ValueError, match=r"output.foreground_logits: expected shape \(B, 1, H, W\) with B=1 .*got \(2, 1, 4, 5\)"):
        mirror_output(UNetOutput(n, torch.rand(1, 2, 4, 5), torch.randn(2, 1, 4, 5)), [1, 0])


def test_permutation_of_non_integers_is_refused():
    """int() would truncate 1.5 to a valid index."""
    out = UNetOutput(torch.zeros(1, 3, 4, 4), torch.zeros(1, 4, 4, 4), torch.zeros(1, 1, 4, 4))
    with pytest.raises(ValueError, match=r"permutation: expected a permutation of 0..3, got \[1.5, 0, 3, 2\]"):
        mirror_output(out, [1.5, 0, 3, 2])


def test_mirror_output_names_an_output_that_is_not_a_unet_output():
    """Regression: a plain tuple failed with an AttributeError."""
    out = UNetOutput(torch.zeros(1, 3, 4, 4), torch.zeros(1, 2, 4, 4), torch.zeros(1, 1, 4, 4))
    with pytest.raises(ValueError, match="output: expected a UNetOutput, got tuple"):
        mirror_output(tuple(out), [1, 0])


@pytest.mark.parametrize("field", ["normals", "landmarks", "foreground_logits"])
@pytest.mark.parametrize("dtype", [torch.int64, torch.bool])
def test_mirror_output_refuses_integer_fields(field, dtype):
    """Regression: integer or bool maps were mirrored silently (and then averaged with rounding)."""
    out = UNetOutput(torch.zeros(1, 3, 4, 4), torch.zeros(1, 2, 4, 4), torch.zeros(1, 1, 4, 4))
    out = out._replace(**{field: getattr(out, field).to(dtype)})
    with pytest.raises(ValueError, match=f"output.{field}: expected a floating-point tensor, got dtype {dtype}"):
        mirror_output(out, [1, 0])


def test_mirror_averaged_refuses_non_finite_images():
    """Regression: one NaN pixel turned every map into NaN, silently."""
    net = NormalLandmarkUNet(num_landmarks=4, base_channels=4, depth=2).eval()
    images = torch.rand(1, 3, 8, 8)
    images[0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="images: expected finite values, got 1 NaN or infinite entries"):
        mirror_averaged(net, images, [1, 0, 3, 2])


def test_mirror_averaged_names_a_net_that_returns_no_unet_output():
    """Regression: a network returning a plain tensor failed with an AttributeError."""
    with pytest.raises(ValueError, match="net: expected a network returning a UNetOutput, got one returning Tensor"):
        mirror_averaged(nn.Conv2d(3, 4, 1), torch.rand(1, 3, 8, 8), [1, 0, 3, 2])
    with pytest.raises(ValueError, match="net: expected a network returning a UNetOutput, got one returning tuple"):
        mirror_averaged(lambda x: tuple(NormalLandmarkUNet(num_landmarks=2, base_channels=4, depth=2)(x)),
                        torch.rand(1, 3, 8, 8), [1, 0])


class _Fixed(nn.Module):
    """A network whose output does not depend on the image: asymmetric random maps, the same for the
    photo and its mirror image, so the average must mix each map with its mirrored copy."""

    def __init__(self):
        super().__init__()
        g = torch.Generator().manual_seed(3)
        self.n = torch.nn.functional.normalize(torch.randn(1, 3, 6, 8, generator=g), dim=1)
        self.z = torch.rand(1, len(LANDMARK_NAMES), 6, 8, generator=g)
        self.f = torch.randn(1, 1, 6, 8, generator=g)

    def forward(self, images):
        count = images.shape[0]
        return UNetOutput(self.n.expand(count, -1, -1, -1), self.z.expand(count, -1, -1, -1),
                          self.f.expand(count, -1, -1, -1))


def test_the_average_of_asymmetric_maps_follows_its_formula():
    """The sphere above is mirror-symmetric and its logits zero, so ignoring the mirrored normals or
    averaging the foreground wrongly passed; here each term is checked against the formula."""
    net = _Fixed()
    avg = mirror_averaged(net, torch.rand(1, 3, 6, 8, generator=torch.Generator().manual_seed(0)))
    mirrored_normals = net.n.flip(-1) * torch.tensor([-1.0, 1.0, 1.0]).view(1, 3, 1, 1)
    torch.testing.assert_close(avg.normals, torch.nn.functional.normalize(net.n + mirrored_normals, dim=1))
    torch.testing.assert_close(avg.foreground_logits, 0.5 * (net.f + net.f.flip(-1)))
    torch.testing.assert_close(avg.landmarks, 0.5 * (net.z + net.z.flip(-1)[:, mirror_permutation()]))
