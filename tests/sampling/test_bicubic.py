"""Tests of the OpenCV-compatible bicubic sampler.

Findings about the cv2 reference (opencv-contrib-python-headless 5.0.0, float32 maps):

* ``cv2.remap`` with float32 maps evaluates the Keys weights in floating point (OpenCV 4.x rounds
  float maps to 1/32 pixel first, so with OpenCV 4 the points compared are put on that grid:
  :func:`on_cv2_grid`); on float32 images it agrees with ``sample_bicubic`` to ~3e-7 everywhere,
  border and outside points included, so no interior restriction is needed there.
* On float64 images opencv 5.0.0 is exact in the interior but returns 0 for every point whose 4x4
  support touches the border (a bug of its 64-bit path), so float64 is compared on interior points
  only, and at the border against cv2 on a float32 copy of the image.
* ``cv2.remap`` with ``INTER_CUBIC`` accepts at most 4 channels; more channels are compared one
  channel at a time.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from facenormals.sampling import BicubicSampler, sample_bicubic, sample_bicubic_with_gradient
from tests.conftest import assert_close

A = -0.75


def keys_kernel(x: float) -> float:
    """Keys' cubic convolution kernel with a = -0.75, written from its textbook definition."""
    x = abs(x)
    if x <= 1:
        return (A + 2) * x**3 - (A + 3) * x**2 + 1
    if x < 2:
        return A * x**3 - 5 * A * x**2 + 8 * A * x - 4 * A
    return 0.0


def naive_sample(image: np.ndarray, u: float, v: float) -> np.ndarray:
    """Per-point loop over the 4x4 support, border replicated. ``image`` is (C, H, W)."""
    C, H, W = image.shape
    u0, v0 = math.floor(u), math.floor(v)
    out = np.zeros(C)
    for i in range(v0 - 1, v0 + 3):
        for j in range(u0 - 1, u0 + 3):
            w = keys_kernel(v - i) * keys_kernel(u - j)
            out += w * image[:, min(max(i, 0), H - 1), min(max(j, 0), W - 1)]
    return out


def cv2_sample(image: torch.Tensor, pixels: torch.Tensor) -> np.ndarray:
    """cv2.remap reference for a (C, H, W) image and (N, 2) float32-representable pixels."""
    img = image.detach().cpu().numpy().transpose(1, 2, 0)
    mapx = pixels[:, 0].detach().cpu().numpy().astype(np.float32)[None]
    mapy = pixels[:, 1].detach().cpu().numpy().astype(np.float32)[None]
    channels = []
    for c in range(0, img.shape[2], 4):
        chunk = np.ascontiguousarray(img[:, :, c:c + 4])
        out = cv2.remap(chunk, mapx, mapy, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        channels.append(out.reshape(pixels.shape[0], -1))
    return np.concatenate(channels, axis=1)


def on_cv2_grid(pixels: torch.Tensor) -> torch.Tensor:
    """``pixels`` where ``cv2.remap`` evaluates them exactly: as they are with OpenCV >= 5, on the
    1/32-pixel grid that OpenCV 4 rounds float maps to."""
    if int(cv2.__version__.split(".")[0]) >= 5:
        return pixels
    return torch.round(pixels * 32) / 32


def random_pixels(batch, n, H, W, margin, seed=0, dtype=torch.float32):
    """Uniform pixels in [-margin, W-1+margin] x [-margin, H-1+margin] (margin < 0 shrinks)."""
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(batch, n, generator=g) * (W - 1 + 2 * margin) - margin
    v = torch.rand(batch, n, generator=g) * (H - 1 + 2 * margin) - margin
    # float32-representable, so that cv2's float32 maps see exactly the same coordinates
    return torch.stack([u, v], -1).float().to(dtype)


def random_image(batch, C, H, W, dtype=torch.float32, device="cpu", seed=1):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(batch, C, H, W, generator=g, dtype=torch.float64).to(dtype=dtype, device=device)


@pytest.mark.parametrize("channels", [1, 3, 4, 6])
def test_against_cv2_float32_everywhere(channels, device):
    B, H, W = 2, 13, 17
    image = random_image(B, channels, H, W, torch.float32, device)
    # the whole image plus 3 pixels of replicated border on every side
    pixels = on_cv2_grid(random_pixels(B, 500, H, W, margin=3.0)).to(device)
    values, inside = sample_bicubic(image, pixels)
    assert values.shape == (B, 500, channels) and inside.shape == (B, 500)
    for b in range(B):
        ref = cv2_sample(image[b], pixels[b])
        err = np.abs(values[b].cpu().numpy() - ref).max()
        assert err < 1e-5, err  # measured ~3e-7 with opencv 5.0.0


def test_float32_is_accurate_to_its_rounding():
    """float32 samples of a [-1, 1] image (a normal map's range) within a few float32 steps of the
    exact (float64) samples of the same image: the outer Keys weights, expanded as cubics, cancel
    to ~1.7e-6 here."""
    image = random_image(2, 3, 13, 17, torch.float64) * 2 - 1
    image = image.float()
    pixels = random_pixels(2, 2000, 13, 17, margin=3.0)
    values, grad, _ = sample_bicubic_with_gradient(image, pixels)
    exact, exact_grad, _ = sample_bicubic_with_gradient(image.double(), pixels.double())
    assert (values.double() - exact).abs().max() < 6e-7
    assert (grad.double() - exact_grad).abs().max() < 1e-6


def test_against_cv2_float64(device):
    B, C, H, W = 2, 3, 12, 15
    image = random_image(B, C, H, W, torch.float64, device)
    # interior: the 4x4 support is inside the image (opencv 5.0.0 float64 is wrong elsewhere)
    g = torch.Generator().manual_seed(3)
    u = 1 + torch.rand(B, 400, generator=g) * (W - 3 - 1e-3)
    v = 1 + torch.rand(B, 400, generator=g) * (H - 3 - 1e-3)
    pixels = on_cv2_grid(torch.stack([u, v], -1).float().double()).to(device)
    values, _ = sample_bicubic(image, pixels)
    for b in range(B):
        ref = cv2_sample(image[b], pixels[b])
        assert np.abs(values[b].cpu().numpy() - ref).max() < 1e-6
    # near and beyond the border: cv2 on a float32 copy of the image
    pixels = on_cv2_grid(random_pixels(B, 400, H, W, margin=3.0, dtype=torch.float64)).to(device)
    values, _ = sample_bicubic(image, pixels)
    for b in range(B):
        ref = cv2_sample(image[b].float(), pixels[b])
        assert np.abs(values[b].cpu().numpy() - ref).max() < 1e-5


def test_integer_coordinates_reproduce_pixels(dtype, device):
    B, C, H, W = 2, 3, 5, 7
    image = random_image(B, C, H, W, dtype, device)
    vv, uu = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    pixels = torch.stack([uu, vv], -1).reshape(1, H * W, 2).expand(B, -1, -1).to(dtype=dtype, device=device)
    values, inside = sample_bicubic(image, pixels)
    assert torch.equal(values, image.reshape(B, C, H * W).transpose(1, 2))
    assert inside.all()
    values2, grad, _ = sample_bicubic_with_gradient(image, pixels)
    assert torch.equal(values2, values)
    # at a pixel centre dI/du = 0.75 (I[u+1] - I[u-1]) (border replicated)
    padded = torch.nn.functional.pad(image, (1, 1, 1, 1), mode="replicate")
    du = 0.75 * (padded[:, :, 1:-1, 2:] - padded[:, :, 1:-1, :-2])
    dv = 0.75 * (padded[:, :, 2:, 1:-1] - padded[:, :, :-2, 1:-1])
    assert_close(grad[..., 0], du.reshape(B, C, H * W).transpose(1, 2))
    assert_close(grad[..., 1], dv.reshape(B, C, H * W).transpose(1, 2))


def test_naive_loop_including_border():
    C, H, W = 2, 6, 8
    image = random_image(1, C, H, W, torch.float64)
    points = [
        (2.3, 3.7), (0.1, 0.2), (6.9, 4.95), (7.0, 5.0), (0.0, 0.0), (-0.4, 2.5), (7.6, -0.3),
        (-5.2, 9.1), (3.5, 5.5), (1.999, 0.001), (4.0, 2.25),
    ]
    pixels = torch.tensor([points], dtype=torch.float64)
    values, inside = sample_bicubic(image, pixels)
    values2, _, inside2 = sample_bicubic_with_gradient(image, pixels)
    img = image[0].numpy()
    for n, (u, v) in enumerate(points):
        ref = naive_sample(img, u, v)
        np.testing.assert_allclose(values[0, n].numpy(), ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(values2[0, n].numpy(), ref, rtol=0, atol=1e-12)
        assert bool(inside[0, n]) == (0 <= u <= W - 1 and 0 <= v <= H - 1)
    assert torch.equal(inside, inside2)


def test_constant_image_and_partition_of_unity(dtype, device):
    image = torch.full((1, 2, 4, 5), 0.3, dtype=dtype, device=device)
    pixels = random_pixels(1, 50, 4, 5, margin=4.0, dtype=dtype).to(device)
    values, grad, _ = sample_bicubic_with_gradient(image, pixels)
    assert_close(values, torch.full_like(values, 0.3))
    assert_close(grad, torch.zeros_like(grad))


def test_inside_mask():
    image = torch.zeros(1, 1, 4, 6)
    eps = 1e-3
    pixels = torch.tensor([[[0.0, 0.0], [5.0, 3.0], [-eps, 1.0], [5 + eps, 1.0], [2.0, -eps], [2.0, 3 + eps],
                            [2.5, 1.5]]])
    _, inside = sample_bicubic(image, pixels)
    assert inside.tolist() == [[True, True, False, False, False, False, True]]


def test_non_finite_pixels():
    image = random_image(1, 3, 5, 6, torch.float64).requires_grad_()
    pixels = torch.tensor([[[1.5, 2.5], [float("nan"), 1.0], [2.0, float("inf")], [-float("inf"), 0.5],
                            [2.25, 1.75]]], dtype=torch.float64, requires_grad=True)
    values, inside = sample_bicubic(image, pixels)
    assert inside.tolist() == [[True, False, False, False, True]]
    assert torch.isfinite(values).all()
    assert (values[0, 1:4] == 0).all()
    values.sum().backward()
    assert torch.isfinite(pixels.grad).all() and torch.isfinite(image.grad).all()
    assert (pixels.grad[0, 1:4] == 0).all()
    values2, grad, inside2 = sample_bicubic_with_gradient(image.detach(), pixels.detach())
    assert torch.equal(values2, values.detach()) and torch.equal(inside2, inside)
    assert torch.isfinite(grad).all() and (grad[0, 1:4] == 0).all()


def test_huge_coordinates_replicate_border():
    image = random_image(1, 2, 4, 5, torch.float64)
    pixels = torch.tensor([[[1e30, 2.0], [-1e30, -1e30], [2.0, 1e18]]], dtype=torch.float64)
    values, inside = sample_bicubic(image, pixels)
    assert not inside.any()
    assert_close(values[0, 0], image[0, :, 2, 4])
    assert_close(values[0, 1], image[0, :, 0, 0])
    assert_close(values[0, 2], image[0, :, 3, 2])


def test_gradcheck():
    B, C, H, W = 2, 2, 5, 6
    image = random_image(B, C, H, W, torch.float64).requires_grad_()
    pixels = random_pixels(B, 12, H, W, margin=1.5, dtype=torch.float64, seed=5)
    # keep finite differences away from the integer coordinates where floor jumps
    frac = pixels - pixels.floor()
    pixels = torch.where((frac < 0.01) | (frac > 0.99), pixels + 0.05, pixels).requires_grad_()
    assert torch.autograd.gradcheck(lambda i, p: sample_bicubic(i, p)[0], (image, pixels))
    assert torch.autograd.gradgradcheck(lambda i, p: sample_bicubic(i, p)[0], (image, pixels))
    assert torch.autograd.gradcheck(lambda i, p: sample_bicubic_with_gradient(i, p)[1], (image, pixels))


def test_analytic_gradient_matches_autograd(dtype, device):
    B, C, H, W = 2, 3, 6, 7
    image = random_image(B, C, H, W, dtype, device)
    pixels = random_pixels(B, 40, H, W, margin=2.5, dtype=dtype, seed=7).to(device)
    # integer and half-integer coordinates too: the Keys kernel is C1
    extra = torch.tensor([[3.0, 2.0], [0.0, 5.0], [6.0, 0.0], [2.5, 3.0], [-1.0, 1.5]], dtype=dtype, device=device)
    pixels = torch.cat([pixels, extra.expand(B, -1, -1)], 1)
    values, grad, inside = sample_bicubic_with_gradient(image, pixels)
    ref_values, ref_inside = sample_bicubic(image, pixels)
    assert_close(values, ref_values)
    assert torch.equal(inside, ref_inside)
    assert grad.shape == (B, pixels.shape[1], C, 2)
    p = pixels.clone().requires_grad_()
    out, _ = sample_bicubic(image, p)
    for c in range(C):
        (g,) = torch.autograd.grad(out[..., c].sum(), p, retain_graph=True)
        assert_close(grad[..., c, :], g)


def test_torch_func_transforms():
    B, C, H, W = 2, 3, 6, 7
    image = random_image(B, C, H, W, torch.float64)
    pixels = random_pixels(B, 5, H, W, margin=0.5, dtype=torch.float64, seed=9)
    _, grad, _ = sample_bicubic_with_gradient(image, pixels)

    def one(img, px):  # unbatched (C, H, W), (2,) -> (C,)
        return sample_bicubic(img[None], px[None, None])[0][0, 0]

    jac = torch.func.vmap(torch.func.jacfwd(one, argnums=1), in_dims=(None, 0))
    for b in range(B):
        assert_close(jac(image[b], pixels[b]), grad[b])
    # jvp and vmap over an extra leading batch
    tangent = torch.randn(pixels.shape, generator=torch.Generator().manual_seed(0), dtype=pixels.dtype)
    _, jvp_out = torch.func.jvp(lambda p: sample_bicubic(image, p)[0], (pixels,), (tangent,))
    assert_close(jvp_out, (grad * tangent[:, :, None, :]).sum(-1))
    stacked = torch.func.vmap(lambda i, p: sample_bicubic(i, p)[0])(
        torch.stack([image, 2 * image]), torch.stack([pixels, pixels])
    )
    values, _ = sample_bicubic(image, pixels)
    assert_close(stacked[0], values)
    assert_close(stacked[1], 2 * values)


def test_dtype_and_device_follow_input(dtype, device):
    image = random_image(1, 2, 4, 5, dtype, device)
    pixels = random_pixels(1, 3, 4, 5, margin=0.0, dtype=dtype).to(device)
    values, inside = sample_bicubic(image, pixels)
    values2, grad, inside2 = sample_bicubic_with_gradient(image, pixels)
    for x in (values, values2, grad):
        assert x.dtype == dtype and x.device.type == device.type
    assert inside.dtype == torch.bool and inside.device.type == device.type
    assert inside2.dtype == torch.bool


def test_empty_and_single_pixel_images():
    values, inside = sample_bicubic(random_image(2, 3, 4, 4), torch.zeros(2, 0, 2))
    assert values.shape == (2, 0, 3) and inside.shape == (2, 0)
    image = random_image(1, 2, 1, 1)
    values, inside = sample_bicubic(image, torch.tensor([[[0.0, 0.0], [0.3, -0.4]]]))
    assert_close(values, image[:, :, 0, 0][:, None].expand(1, 2, 2))
    assert inside.tolist() == [[True, False]]


@pytest.mark.parametrize("fn", [sample_bicubic, sample_bicubic_with_gradient])
def test_bad_inputs(fn):
    image = torch.rand(2, 3, 4, 5)
    pixels = torch.rand(2, 6, 2)
    with pytest.raises(ValueError, match="image: expected shape"):
        fn(torch.rand(3, 4, 5), pixels)
    with pytest.raises(ValueError, match="pixels: expected shape"):
        fn(image, torch.rand(2, 6))
    with pytest.raises(ValueError, match="pixels: expected shape"):
        fn(image, torch.rand(2, 6, 3))
    with pytest.raises(ValueError, match="B=2"):
        fn(image, torch.rand(3, 6, 2))
    with pytest.raises(ValueError, match="floating"):
        fn(image.to(torch.uint8), pixels)
    with pytest.raises(ValueError, match="floating"):
        fn(image, pixels.long())
    with pytest.raises(ValueError, match="dtype"):
        fn(image, pixels.double())
    with pytest.raises(ValueError, match="H >= 1"):
        fn(torch.rand(2, 3, 0, 5), pixels)
    with pytest.raises(ValueError, match="torch.Tensor"):
        fn(image, pixels.numpy())


def test_torch_compile_smoke():
    image = random_image(2, 3, 6, 7)
    pixels = random_pixels(2, 9, 6, 7, margin=1.0)
    compiled = torch.compile(sample_bicubic, fullgraph=True)
    values, inside = compiled(image, pixels)
    ref, ref_inside = sample_bicubic(image, pixels)
    assert_close(values, ref)
    assert torch.equal(inside, ref_inside)
    compiled_grad = torch.compile(sample_bicubic_with_gradient, fullgraph=True)
    _, grad, _ = compiled_grad(image, pixels)
    assert_close(grad, sample_bicubic_with_gradient(image, pixels)[1])


def test_a_non_finite_image_is_named_and_nan_positions_still_sample_nothing():
    """Regression: a NaN pixel spread NaN over its 4x4 neighbourhood of samples, silently."""
    image = random_image(1, 2, 6, 7, torch.float64)
    pixels = torch.tensor([[[2.5, 3.0], [float("nan"), 1.0]]], dtype=torch.float64)
    values, inside = sample_bicubic(image, pixels)
    assert inside.tolist() == [[True, False]] and values[0, 1].tolist() == [0.0, 0.0]  # (B, N, C)
    image[0, 1, 3, 2] = float("nan")
    for sample in (sample_bicubic, sample_bicubic_with_gradient):
        with pytest.raises(ValueError, match="image: expected finite values, got 1 NaN or infinite entries"):
            sample(image, pixels)


# --- BicubicSampler: the same interpolant from a precomputed table of 4x4 neighbourhoods ---


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("size", [(13, 17), (1, 1), (1, 6), (5, 2)])
def test_sampler_equals_the_functions(dtype, size):
    H, W = size
    image = random_image(2, 3, H, W, dtype)
    pixels = random_pixels(2, 300, H, W, margin=4.0, dtype=dtype)
    pixels[0, :4] = torch.tensor([[1e9, 0.0], [-1e9, 2.0], [0.0, float("nan")], [float("inf"), 1.0]], dtype=dtype)
    pixels[1, :3] = torch.tensor([[0.0, 0.0], [W - 1.0, H - 1.0], [W - 1.0, 0.0]], dtype=dtype)  # corners
    sampler = BicubicSampler(image)
    tol = dict(atol=1e-6, rtol=0) if dtype == torch.float32 else dict(atol=1e-13, rtol=0)
    values, inside = sampler(pixels)
    ref, ref_inside = sample_bicubic(image, pixels)
    assert_close(values, ref, **tol)
    assert torch.equal(inside, ref_inside)
    values, grad, inside = sampler.with_gradient(pixels)
    ref, ref_grad, ref_inside = sample_bicubic_with_gradient(image, pixels)
    assert_close(values, ref, **tol)
    assert_close(grad, ref_grad, **tol)
    assert torch.equal(inside, ref_inside)
    assert values.dtype == grad.dtype == dtype


def test_sampler_against_cv2_and_naive_loop():
    H, W = 9, 11
    image = random_image(1, 4, H, W)
    pixels = on_cv2_grid(random_pixels(1, 200, H, W, margin=3.0))
    values, _ = BicubicSampler(image)(pixels)
    assert np.abs(values[0].numpy() - cv2_sample(image[0], pixels[0])).max() < 1e-5
    image64 = image.double()
    values, _ = BicubicSampler(image64)(pixels.double())
    for n in range(0, 200, 17):
        u, v = pixels[0, n].tolist()
        np.testing.assert_allclose(values[0, n].numpy(), naive_sample(image64[0].numpy(), u, v), atol=1e-12)


def test_sampler_image_index_picks_the_image_per_row():
    image = random_image(3, 2, 6, 7)
    sampler = BicubicSampler(image)
    pixels = random_pixels(4, 20, 6, 7, margin=1.0)
    index = torch.tensor([2, 0, 2, 1])
    values, grad, inside = sampler.with_gradient(pixels, index)
    for k, b in enumerate(index.tolist()):
        ref, ref_grad, ref_inside = sample_bicubic_with_gradient(image[b : b + 1], pixels[k : k + 1])
        assert_close(values[k : k + 1], ref, atol=1e-6, rtol=0)
        assert_close(grad[k : k + 1], ref_grad, atol=1e-6, rtol=0)
        assert torch.equal(inside[k : k + 1], ref_inside)
    assert_close(sampler(pixels[:2], torch.tensor([1, 1]))[0][1], sample_bicubic(image[1:2], pixels[1:2])[0][0])


def test_sampler_gradcheck_and_analytic_gradient():
    image = random_image(1, 2, 5, 6, torch.float64)
    sampler = BicubicSampler(image)
    pixels = random_pixels(1, 7, 5, 6, margin=0.5, dtype=torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: sampler(p)[0], (pixels,))
    jac = torch.autograd.functional.jacobian(lambda p: sampler(p)[0], pixels)  # (1, N, C, 1, N, 2)
    _, grad, _ = sampler.with_gradient(pixels.detach())
    diagonal = torch.stack([jac[0, n, :, 0, n] for n in range(7)])  # (N, C, 2)
    assert_close(grad[0], diagonal, atol=1e-12, rtol=0)


def test_sampler_under_torch_func():
    image = random_image(1, 3, 6, 7, torch.float64)
    sampler = BicubicSampler(image)
    pixels = random_pixels(1, 5, 6, 7, margin=0.0, dtype=torch.float64)
    jac = torch.func.jacfwd(lambda p: sampler(p)[0])(pixels)
    ref = torch.func.jacfwd(lambda p: sample_bicubic(image, p)[0])(pixels)
    assert_close(jac, ref, atol=1e-12, rtol=0)


def test_sampler_follows_to_and_handles_empty_inputs():
    image = random_image(1, 2, 4, 5)
    sampler = BicubicSampler(image).to(torch.float64)
    values, inside = sampler(random_pixels(1, 3, 4, 5, margin=0.0, dtype=torch.float64))
    assert values.dtype == torch.float64 and values.shape == (1, 3, 2)
    values, inside = sampler(torch.zeros(1, 0, 2, dtype=torch.float64))
    assert values.shape == (1, 0, 2) and inside.shape == (1, 0)
    values, inside = BicubicSampler(torch.zeros(2, 0, 3, 3))(torch.zeros(2, 4, 2))
    assert values.shape == (2, 4, 0)
    values, inside = BicubicSampler(torch.zeros(0, 3, 3, 3))(torch.zeros(0, 4, 2))
    assert values.shape == (0, 4, 3)


def test_sampler_bad_inputs_name_the_argument():
    image = torch.rand(2, 3, 4, 5)
    sampler = BicubicSampler(image)
    with pytest.raises(ValueError, match="image: expected shape"):
        BicubicSampler(torch.rand(3, 4, 5))
    with pytest.raises(ValueError, match="image: expected a floating"):
        BicubicSampler(image.to(torch.uint8))
    with pytest.raises(ValueError, match="H >= 1"):
        BicubicSampler(torch.rand(2, 3, 0, 5))
    bad = image.clone()
    bad[1, 2, 3, 4] = float("nan")
    with pytest.raises(ValueError, match="image: expected finite values"):
        BicubicSampler(bad)
    with pytest.raises(ValueError, match=r"pixels: expected shape \(K, N, 2\)"):
        sampler(torch.rand(2, 6, 3))
    with pytest.raises(ValueError, match=r"B=2 \(the number of images\) or an image_index, got \(3, 6, 2\)"):
        sampler(torch.rand(3, 6, 2))
    with pytest.raises(ValueError, match="pixels: expected dtype torch.float32"):
        sampler.with_gradient(torch.rand(2, 6, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="pixels: expected a floating"):
        sampler(torch.zeros(2, 6, 2, dtype=torch.long))
    with pytest.raises(ValueError, match=r"image_index: expected shape \(3,\), got \(2,\)"):
        sampler(torch.rand(3, 6, 2), torch.tensor([0, 1]))
    with pytest.raises(ValueError, match=r"image_index: expected int64 indices in \[0, 2\), got torch.int64 \[0, 2, 1\]"):
        sampler(torch.rand(3, 6, 2), torch.tensor([0, 2, 1]))
    with pytest.raises(ValueError, match="image_index: expected int64"):
        sampler(torch.rand(3, 6, 2), torch.tensor([0.0, 1.0, 1.0]))
