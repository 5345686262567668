"""Tests of the energy residual functions."""

from __future__ import annotations

import math

import pytest
import torch

from facenormals.energy import landmark_residuals, normal_residuals, prior_residuals
from facenormals.sampling import sample_bicubic
from tests.conftest import assert_close


def disk_normal_map(B, H, W, dtype=torch.float64, device="cpu", seed=0):
    """Smooth unit normals on a disk (a sphere seen from the camera), exactly zero outside."""
    g = torch.Generator().manual_seed(seed)
    vv, uu = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    maps = []
    for _ in range(B):
        cu = (W - 1) / 2 + torch.rand((), generator=g) - 0.5
        cv = (H - 1) / 2 + torch.rand((), generator=g) - 0.5
        radius = min(H, W) * 0.4
        x = (uu - cu) / radius
        y = (vv - cv) / radius
        r2 = x**2 + y**2
        z = -torch.sqrt((1 - r2).clamp(min=0))
        n = torch.stack([x, y, z])
        fg = r2 < 0.95
        maps.append(torch.where(fg, n / n.norm(dim=0).clamp(min=1e-12), torch.zeros(())))
    return torch.stack(maps).to(dtype=dtype, device=device)


def random_case(B=2, N=60, H=16, W=20, dtype=torch.float64, device="cpu", seed=0):
    g = torch.Generator().manual_seed(seed)
    normal_map = disk_normal_map(B, H, W, dtype, device, seed)
    u = torch.rand(B, N, generator=g, dtype=torch.float64) * (W + 3) - 2
    v = torch.rand(B, N, generator=g, dtype=torch.float64) * (H + 3) - 2
    pixels = torch.stack([u, v], -1)
    normals = torch.nn.functional.normalize(torch.randn(B, N, 3, generator=g, dtype=torch.float64), dim=-1)
    visible = torch.rand(B, N, generator=g) < 0.8
    return normal_map, pixels.to(dtype=dtype, device=device), normals.to(dtype=dtype, device=device), visible.to(device)


def naive_valid(normal_map, pixels, visible):
    B, _, H, W = normal_map.shape
    valid = torch.zeros(pixels.shape[:2], dtype=torch.bool)
    for b in range(B):
        for i in range(pixels.shape[1]):
            u, v = float(pixels[b, i, 0]), float(pixels[b, i, 1])
            if not (math.isfinite(u) and math.isfinite(v) and 0 <= u <= W - 1 and 0 <= v <= H - 1):
                continue
            rows = [min(math.floor(v) + dv, H - 1) for dv in (0, 1)]
            cols = [min(math.floor(u) + du, W - 1) for du in (0, 1)]
            corners = [(r, c) for r in rows for c in cols]
            fg = all(float(normal_map[b, :, r, c].norm()) > 0.5 for r, c in corners)
            valid[b, i] = fg and (visible is None or bool(visible[b, i]))
    return valid


# --------------------------------------------------------------------------------------------------
# normal residuals


def test_normal_residuals_against_naive(dtype, device):
    normal_map, pixels, normals, visible = random_case(dtype=dtype, device=device)
    weight = 2.5
    r, valid = normal_residuals(normal_map, pixels, normals, visible, weight=weight)
    assert r.shape == normals.shape and valid.shape == visible.shape
    assert r.dtype == dtype and r.device.type == device.type and valid.dtype == torch.bool
    ref_valid = naive_valid(normal_map.cpu(), pixels.cpu(), visible.cpu())
    assert torch.equal(valid.cpu(), ref_valid)
    assert 0 < int(ref_valid.sum()) < ref_valid.numel()  # the case exercises both branches
    sampled, _ = sample_bicubic(normal_map, pixels)
    expected = torch.where(valid[..., None], (sampled - normals) * math.sqrt(weight), torch.zeros((), dtype=dtype))
    assert_close(r, expected)
    assert (r[~valid] == 0).all()
    # energy identity: 1/2 |r|^2 = weight * 1/2 sum_valid |N(a) - n|^2
    energy = 0.5 * ((sampled - normals)[valid] ** 2).sum()
    assert_close(0.5 * (r**2).sum(), weight * energy)


def test_normal_residuals_foreground_support_on_a_speckled_map():
    """Every corner of the bilinear support counts, at the last row and column too (clamped)."""
    g = torch.Generator().manual_seed(5)
    H, W = 7, 9
    normal_map = torch.zeros(2, 3, H, W, dtype=torch.float64)
    normal_map[:, 2] = torch.where(torch.rand(2, H, W, generator=g) < 0.75, -1.0, 0.0)
    pixels = torch.stack([torch.rand(2, 400, generator=g, dtype=torch.float64) * (W - 1),
                          torch.rand(2, 400, generator=g, dtype=torch.float64) * (H - 1)], -1)
    pixels[:, :H * W] = torch.stack(torch.meshgrid(torch.arange(W), torch.arange(H), indexing="xy"), -1).reshape(-1, 2)
    _, valid = normal_residuals(normal_map, pixels, torch.zeros(2, 400, 3, dtype=torch.float64))
    ref = naive_valid(normal_map, pixels, None)
    assert torch.equal(valid, ref) and 0 < int(ref.sum()) < ref.numel()


def test_normal_residuals_hand_computed():
    normal_map = torch.zeros(1, 3, 5, 5, dtype=torch.float64)
    normal_map[:, 2, :, :4] = -1.0  # foreground everywhere except the last column
    pixels = torch.tensor([[[1.0, 2.0], [1.5, 2.5], [2.5, 2.5], [3.5, 2.0], [3.0, 2.0], [-0.5, 1.0], [1.0, 1.0]]],
                          dtype=torch.float64)
    normals = torch.tensor([[[0.0, 0.6, -0.8]] * 7], dtype=torch.float64)
    visible = torch.tensor([[True, True, True, True, True, True, False]])
    r, valid = normal_residuals(normal_map, pixels, normals, visible)
    # (3.5, 2) and (3, 2): the bilinear support reaches column 4 (background; at u = 3 the support
    # is floor(u) + {0, 1} = {3, 4}); (-0.5, 1) is outside; (1, 1) is invisible
    assert valid.tolist() == [[True, True, True, False, False, False, False]]
    assert_close(r[0, 0], torch.tensor([0.0, -0.6, -0.2], dtype=torch.float64))
    assert_close(r[0, 1], torch.tensor([0.0, -0.6, -0.2], dtype=torch.float64))
    # valid, but the 4x4 bicubic support reaches the background column: with the Keys weights
    # (-3/32, 19/32, 19/32, -3/32) at t = 1/2 the sample overshoots to -(1 + 3/32)
    assert_close(r[0, 2], torch.tensor([0.0, -0.6, -1.09375 + 0.8], dtype=torch.float64))
    assert (r[0, 3:] == 0).all()


def test_normal_residuals_last_pixel_is_inside():
    normal_map = torch.zeros(1, 3, 3, 4)
    normal_map[:, 2] = -1.0
    pixels = torch.tensor([[[3.0, 2.0], [0.0, 0.0], [3.0001, 2.0]]])
    r, valid = normal_residuals(normal_map, pixels, torch.zeros(1, 3, 3))
    assert valid.tolist() == [[True, True, False]]
    assert_close(r[0, :2], torch.tensor([[0.0, 0.0, -1.0]] * 2))


def test_normal_residuals_visible_none_and_weight_zero():
    normal_map, pixels, normals, _ = random_case()
    r, valid = normal_residuals(normal_map, pixels, normals)
    assert torch.equal(valid, naive_valid(normal_map, pixels, None))
    r0, _ = normal_residuals(normal_map, pixels, normals, weight=0.0)
    assert (r0 == 0).all()
    r4, _ = normal_residuals(normal_map, pixels, normals, weight=4.0)
    assert_close(r4, 2 * r)


def test_normal_residuals_masked_entries_have_zero_gradient():
    normal_map, pixels, normals, visible = random_case()
    # invisible vertices may carry garbage: NaN normals and NaN / inf pixels
    visible[0, 0] = visible[1, 1] = False
    normals = torch.where(visible[..., None], normals, torch.full_like(normals, float("nan")))
    pixels[0, 0] = float("nan")
    pixels[1, 1, 0] = float("inf")
    normal_map.requires_grad_()
    pixels.requires_grad_()
    normals.requires_grad_()
    r, valid = normal_residuals(normal_map, pixels, normals, visible)
    assert not valid[0, 0] and not valid[1, 1]
    assert torch.isfinite(r).all() and (r[~valid] == 0).all()
    (0.5 * (r**2).sum()).backward()
    for x in (normal_map, pixels, normals):
        assert torch.isfinite(x.grad).all()
    assert (pixels.grad[~valid] == 0).all() and (normals.grad[~valid] == 0).all()
    assert (pixels.grad[valid] != 0).any() and (normals.grad[valid] != 0).any()


def test_normal_residuals_refuse_nan_where_a_vertex_counts():
    # a NaN pixel would sample as "outside" and a NaN normal poison the energy: both are errors for
    # a visible vertex (and for every vertex without a mask), never a silently dropped residual
    normal_map, pixels, normals, visible = random_case()
    visible[0, 3] = True
    bad_pixels, bad_normals = pixels.clone(), normals.clone()
    bad_pixels[0, 3, 1] = float("nan")
    bad_normals[0, 3, 0] = float("inf")
    with pytest.raises(ValueError, match="pixels: expected finite values, got 1 NaN"):
        normal_residuals(normal_map, bad_pixels, normals, visible)
    with pytest.raises(ValueError, match="normals: expected finite values"):
        normal_residuals(normal_map, pixels, bad_normals)
    visible[0, 3] = False
    r, valid = normal_residuals(normal_map, bad_pixels, bad_normals, visible)
    assert torch.isfinite(r).all() and not valid[0, 3]


def test_normal_residuals_gradcheck():
    normal_map, pixels, normals, visible = random_case(B=2, N=25, H=10, W=12)
    # keep finite differences away from integer coordinates (floor jumps, foreground changes)
    frac = pixels - pixels.floor()
    pixels = torch.where((frac < 0.02) | (frac > 0.98), pixels + 0.1, pixels)
    _, valid = normal_residuals(normal_map, pixels, normals, visible)
    assert valid.any()
    args = [x.clone().requires_grad_() for x in (normal_map, pixels, normals)]
    assert torch.autograd.gradcheck(lambda m, p, n: normal_residuals(m, p, n, visible, weight=3.0)[0], args)


def test_normal_residuals_bad_inputs():
    normal_map, pixels, normals, visible = random_case(B=2, N=5)
    with pytest.raises(ValueError, match="normal_map: expected shape"):
        normal_residuals(normal_map[:, :2], pixels, normals)
    with pytest.raises(ValueError, match="normal_map: expected shape"):
        normal_residuals(normal_map[0], pixels, normals)
    with pytest.raises(ValueError, match="pixels: expected shape"):
        normal_residuals(normal_map, pixels[..., :1], normals)
    with pytest.raises(ValueError, match="pixels: expected shape"):
        normal_residuals(normal_map, pixels[:1], normals)
    with pytest.raises(ValueError, match="normals: expected shape"):
        normal_residuals(normal_map, pixels, normals[:, :4])
    with pytest.raises(ValueError, match="normals: expected shape"):
        normal_residuals(normal_map, pixels, normals[..., :2])
    with pytest.raises(ValueError, match="visible: expected shape"):
        normal_residuals(normal_map, pixels, normals, visible[:, :4])
    with pytest.raises(ValueError, match="visible: expected a bool"):
        normal_residuals(normal_map, pixels, normals, visible.float())
    with pytest.raises(ValueError, match="floating"):
        normal_residuals(normal_map, pixels.long(), normals)
    with pytest.raises(ValueError, match="floating"):
        normal_residuals(normal_map.long(), pixels, normals)
    with pytest.raises(ValueError, match="dtype"):
        normal_residuals(normal_map, pixels, normals.float())
    nan_map = normal_map.clone()
    nan_map[0, :, 1, 1] = float("nan")  # would read as background and drop its vertices silently
    with pytest.raises(ValueError, match="normal_map: expected finite values, got 3 NaN"):
        normal_residuals(nan_map, pixels, normals)
    with pytest.raises(ValueError, match="weight"):
        normal_residuals(normal_map, pixels, normals, weight=-1.0)
    with pytest.raises(ValueError, match="weight"):
        normal_residuals(normal_map, pixels, normals, weight=float("nan"))


# --------------------------------------------------------------------------------------------------
# landmark residuals


def test_landmark_residuals_values(dtype, device):
    g = torch.Generator().manual_seed(0)
    pixels = (torch.rand(3, 7, 2, generator=g) * 100).to(dtype=dtype, device=device)
    targets = (torch.rand(3, 7, 2, generator=g) * 100).to(dtype=dtype, device=device)
    mask = (torch.rand(3, 7, generator=g) < 0.7).to(device)
    weight = 0.3
    r = landmark_residuals(pixels, targets, mask, weight=weight)
    assert r.shape == (3, 7, 2) and r.dtype == dtype and r.device.type == device.type
    for b in range(3):
        for j in range(7):
            want = (pixels[b, j] - targets[b, j]) * math.sqrt(weight) if mask[b, j] else torch.zeros(2, dtype=dtype)
            assert_close(r[b, j], want)
    energy = 0.5 * ((pixels - targets)[mask] ** 2).sum()
    assert_close(0.5 * (r**2).sum(), weight * energy)
    assert_close(landmark_residuals(pixels, targets), pixels - targets)


def test_landmark_residuals_nan_targets_under_mask():
    pixels = torch.tensor([[[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]], dtype=torch.float64, requires_grad=True)
    targets = torch.tensor([[[0.5, 2.5], [float("nan"), float("nan")], [5.0, float("inf")]]], dtype=torch.float64,
                           requires_grad=True)
    mask = torch.tensor([[True, False, False]])
    r = landmark_residuals(pixels, targets, mask, weight=2.0)
    assert_close(r, torch.tensor([[[0.5 * math.sqrt(2), -0.5 * math.sqrt(2)], [0.0, 0.0], [0.0, 0.0]]],
                                 dtype=torch.float64))
    (0.5 * (r**2).sum()).backward()
    assert torch.isfinite(pixels.grad).all() and torch.isfinite(targets.grad).all()
    assert_close(pixels.grad, torch.tensor([[[1.0, -1.0], [0.0, 0.0], [0.0, 0.0]]], dtype=torch.float64))
    assert_close(targets.grad, -pixels.grad)


def test_landmark_residuals_refuse_nan_where_a_landmark_counts():
    pixels = torch.tensor([[[10.0, 20.0], [30.0, 40.0]]])
    targets = torch.tensor([[[11.0, 18.0], [30.0, 40.0]]])
    bad = targets.clone()
    bad[0, 1, 0] = float("nan")
    with pytest.raises(ValueError, match="targets: expected finite values, got 1 NaN"):
        landmark_residuals(pixels, bad)  # no mask: every landmark counts
    with pytest.raises(ValueError, match="targets: expected finite values"):
        landmark_residuals(pixels, bad, torch.tensor([[True, True]]))
    assert torch.equal(landmark_residuals(pixels, bad, torch.tensor([[True, False]]))[0, 1], torch.zeros(2))
    bad_pixels = pixels.clone()
    bad_pixels[0, 0, 1] = float("inf")
    with pytest.raises(ValueError, match="pixels: expected finite values, got 1 NaN or infinite"):
        landmark_residuals(bad_pixels, targets, torch.tensor([[True, False]]))
    assert torch.equal(landmark_residuals(bad_pixels, targets, torch.tensor([[False, True]])), torch.zeros(1, 2, 2))


def test_landmark_residuals_gradcheck():
    g = torch.Generator().manual_seed(1)
    pixels = torch.rand(2, 5, 2, generator=g, dtype=torch.float64, requires_grad=True)
    targets = torch.rand(2, 5, 2, generator=g, dtype=torch.float64, requires_grad=True)
    mask = torch.tensor([[True, False, True, True, False], [False, True, True, True, True]])
    assert torch.autograd.gradcheck(lambda p, t: landmark_residuals(p, t, mask, weight=1.7), (pixels, targets))
    assert torch.autograd.gradcheck(lambda p, t: landmark_residuals(p, t), (pixels, targets))


def test_landmark_residuals_bad_inputs():
    pixels = torch.rand(2, 5, 2)
    targets = torch.rand(2, 5, 2)
    with pytest.raises(ValueError, match="pixels: expected shape"):
        landmark_residuals(pixels[0], targets)
    with pytest.raises(ValueError, match="pixels: expected shape"):
        landmark_residuals(torch.rand(2, 5, 3), targets)
    with pytest.raises(ValueError, match="targets: expected shape"):
        landmark_residuals(pixels, targets[:1])
    with pytest.raises(ValueError, match="targets: expected shape"):
        landmark_residuals(pixels, targets[:, :4])
    with pytest.raises(ValueError, match="mask: expected shape"):
        landmark_residuals(pixels, targets, torch.ones(2, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match="mask: expected a bool"):
        landmark_residuals(pixels, targets, torch.ones(2, 5))
    with pytest.raises(ValueError, match="floating"):
        landmark_residuals(pixels.long(), targets)
    with pytest.raises(ValueError, match="dtype"):
        landmark_residuals(pixels, targets.double())
    with pytest.raises(ValueError, match="weight"):
        landmark_residuals(pixels, targets, weight=-0.1)
    with pytest.raises(ValueError, match="weight"):
        landmark_residuals(pixels, targets, weight="1")


# --------------------------------------------------------------------------------------------------
# prior residuals


def test_prior_residuals_values(dtype, device):
    g = torch.Generator().manual_seed(2)
    coeffs = torch.randn(3, 6, generator=g, dtype=torch.float64).to(dtype=dtype, device=device)
    std = (torch.rand(6, generator=g, dtype=torch.float64) + 0.1).to(dtype=dtype, device=device)
    weight = 5.0
    r = prior_residuals(coeffs, std, weight=weight)
    assert r.shape == (3, 6) and r.dtype == dtype and r.device.type == device.type
    assert_close(r, coeffs / std * math.sqrt(weight))
    # 1/2 |r|^2 = weight * 1/2 y^T C^-1 y with C = diag(std^2)
    C_inv = torch.diag(1 / std**2)
    quad = 0.5 * torch.einsum("bi,ij,bj->b", coeffs, C_inv, coeffs).sum()
    assert_close(0.5 * (r**2).sum(), weight * quad)
    # a per-sample std
    std_b = std[None].expand(3, 6) * torch.arange(1, 4, dtype=dtype, device=device)[:, None]
    assert_close(prior_residuals(coeffs, std_b), coeffs / std_b)


def test_prior_residuals_gradcheck():
    g = torch.Generator().manual_seed(3)
    coeffs = torch.randn(2, 4, generator=g, dtype=torch.float64, requires_grad=True)
    std = torch.rand(4, generator=g, dtype=torch.float64) + 0.5
    assert torch.autograd.gradcheck(lambda y: prior_residuals(y, std, weight=2.0), (coeffs,))


def test_prior_residuals_bad_inputs():
    coeffs = torch.randn(2, 4)
    std = torch.ones(4)
    with pytest.raises(ValueError, match="coeffs: expected shape"):
        prior_residuals(coeffs[0], std)
    with pytest.raises(ValueError, match="std: expected shape"):
        prior_residuals(coeffs, torch.ones(5))
    with pytest.raises(ValueError, match="std: expected shape"):
        prior_residuals(coeffs, torch.ones(3, 4))
    with pytest.raises(ValueError, match="std: expected shape"):
        prior_residuals(coeffs, torch.ones(1, 2, 4))
    with pytest.raises(ValueError, match="std: expected values > 0"):
        prior_residuals(coeffs, torch.tensor([1.0, 0.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="std: expected values > 0"):
        prior_residuals(coeffs, torch.tensor([1.0, -2.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="std: expected finite values, got 1 NaN"):
        prior_residuals(coeffs, torch.tensor([1.0, float("nan"), 1.0, 1.0]))
    with pytest.raises(ValueError, match="std: expected finite values, got 1 NaN or infinite"):
        prior_residuals(coeffs, torch.tensor([1.0, float("inf"), 1.0, 1.0]))  # would zero the prior silently
    with pytest.raises(ValueError, match="coeffs: expected finite values, got 1 NaN"):
        prior_residuals(torch.tensor([[float("nan"), 1.0, 0.0, 0.0]]), std)
    with pytest.raises(ValueError, match="floating"):
        prior_residuals(coeffs.long(), std)
    with pytest.raises(ValueError, match="dtype"):
        prior_residuals(coeffs, std.double())
    with pytest.raises(ValueError, match="torch.Tensor"):
        prior_residuals(coeffs, [1.0, 1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="weight"):
        prior_residuals(coeffs, std, weight=-1)


def test_residuals_under_torch_func():
    normal_map, pixels, normals, visible = random_case(B=2, N=10, H=10, W=12)

    def energy(p):
        r, _ = normal_residuals(normal_map, p, normals, visible)
        return 0.5 * (r**2).sum()

    grad_func = torch.func.grad(energy)(pixels)
    p = pixels.clone().requires_grad_()
    (grad_autograd,) = torch.autograd.grad(energy(p), p)
    assert_close(grad_func, grad_autograd)
    jac = torch.func.jacfwd(lambda y: prior_residuals(y, torch.full((3,), 2.0, dtype=y.dtype)))(
        torch.randn(1, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    )
    assert_close(jac.reshape(3, 3), torch.eye(3, dtype=torch.float64) / 2)


def test_prior_residuals_under_vmap_and_jacfwd_over_std():
    """Regression: the std > 0 check read values of a tensor vmap wraps (RuntimeError: data-dependent
    control flow); like the finiteness checks it is now skipped there."""
    g = torch.Generator().manual_seed(0)
    std = torch.rand(4, 3, generator=g, dtype=torch.float64) + 1
    coeffs = torch.randn(1, 3, generator=g, dtype=torch.float64)
    out = torch.func.vmap(lambda s: prior_residuals(coeffs, s))(std)
    assert_close(out[:, 0], coeffs / std)
    jac = torch.func.jacfwd(lambda s: prior_residuals(coeffs, s))(std[0])
    assert_close(jac[0], torch.diag(-coeffs[0] / std[0] ** 2))
    with pytest.raises(ValueError, match="std: expected values > 0"):
        prior_residuals(coeffs, -std[0])  # still checked outside the transforms
