import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from facenormals.eval import DEFAULT_ALIGNMENT_LANDMARKS, apply_similarity, fit_similarity, landmark_correspondences
from facenormals.models import LANDMARK_NAMES
from tests.conftest import assert_close


def umeyama_numpy(src, dst, w=None, with_scale=True):
    """Hand-written reference (Umeyama 1991), one problem, float64."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    w = np.full(len(src), 1.0 / len(src)) if w is None else np.asarray(w, np.float64) / np.sum(w)
    mx, my = w @ src, w @ dst
    xs, ys = src - mx, dst - my
    cov = (ys * w[:, None]).T @ xs
    u, sv, vt = np.linalg.svd(cov)
    d = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        d[2, 2] = -1
    rot = u @ d @ vt
    scale = np.trace(np.diag(sv) @ d) / (w @ (xs**2).sum(1)) if with_scale else 1.0
    return scale, rot, my - scale * rot @ mx


def random_similarity(generator, batch, dtype=torch.float64):
    rot = torch.from_numpy(Rotation.random(batch, random_state=int(torch.randint(0, 10**6, (1,), generator=generator))).as_matrix())
    s = 0.5 + torch.rand(batch, generator=generator, dtype=torch.float64)
    t = 100 * torch.randn(batch, 3, generator=generator, dtype=torch.float64)
    return s.to(dtype), rot.to(dtype), t.to(dtype)


@pytest.mark.parametrize("scale", [True, False])
def test_round_trip_known_transform(dtype, scale):
    g = torch.Generator().manual_seed(0)
    source = 50 * torch.randn(4, 6, 3, generator=g, dtype=torch.float64)
    s, rot, t = random_similarity(g, 4)
    if not scale:
        s = torch.ones(4, dtype=torch.float64)
    target = apply_similarity(source, s, rot, t)
    s_fit, r_fit, t_fit = fit_similarity(source.to(dtype), target.to(dtype), scale=scale)
    assert s_fit.dtype == r_fit.dtype == t_fit.dtype == dtype
    tol = {"rtol": 1e-4, "atol": 1e-3} if dtype == torch.float32 else {}
    assert_close(s_fit, s.to(dtype), **tol)
    assert_close(r_fit, rot.to(dtype), **({"rtol": 1e-4, "atol": 1e-5} if dtype == torch.float32 else {}))
    assert_close(t_fit, t.to(dtype), **tol)


def test_matches_numpy_umeyama_with_noise_and_weights():
    g = torch.Generator().manual_seed(1)
    source = 30 * torch.randn(3, 40, 3, generator=g, dtype=torch.float64)
    s, rot, t = random_similarity(g, 3)
    target = apply_similarity(source, s, rot, t) + torch.randn(3, 40, 3, generator=g, dtype=torch.float64)
    weights = torch.rand(3, 40, generator=g, dtype=torch.float64)
    for with_scale in (True, False):
        for w in (None, weights):
            s_fit, r_fit, t_fit = fit_similarity(source, target, w, scale=with_scale)
            for b in range(3):
                ref = umeyama_numpy(source[b].numpy(), target[b].numpy(), None if w is None else w[b].numpy(), with_scale)
                assert s_fit[b].item() == pytest.approx(ref[0], rel=1e-10)
                np.testing.assert_allclose(r_fit[b].numpy(), ref[1], atol=1e-10)
                np.testing.assert_allclose(t_fit[b].numpy(), ref[2], atol=1e-8)


def test_rotation_matches_scipy_align_vectors():
    g = torch.Generator().manual_seed(2)
    source = torch.randn(1, 25, 3, generator=g, dtype=torch.float64)
    _, rot, _ = random_similarity(g, 1)
    target = source @ rot.transpose(1, 2) + 0.05 * torch.randn(1, 25, 3, generator=g, dtype=torch.float64)
    weights = torch.rand(1, 25, generator=g, dtype=torch.float64)
    _, r_fit, _ = fit_similarity(source, target, weights, scale=False)
    # align_vectors(a, b) minimises sum w |a - R b|^2; compare on centred points
    ws = weights / weights.sum()
    a = (target - (ws[..., None] * target).sum(1, keepdim=True))[0].numpy()
    b = (source - (ws[..., None] * source).sum(1, keepdim=True))[0].numpy()
    expected, _ = Rotation.align_vectors(a, b, weights=weights[0].numpy())
    np.testing.assert_allclose(r_fit[0].numpy(), expected.as_matrix(), atol=1e-10)


def test_reflection_safe():
    g = torch.Generator().manual_seed(3)
    source = torch.randn(2, 10, 3, generator=g, dtype=torch.float64)
    mirrored = source * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    _, r_fit, _ = fit_similarity(source, mirrored)
    assert_close(torch.det(r_fit), torch.ones(2, dtype=torch.float64))
    assert_close(r_fit @ r_fit.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(2, 3, 3))


def test_differentiable():
    g = torch.Generator().manual_seed(4)
    source = torch.randn(1, 8, 3, generator=g, dtype=torch.float64, requires_grad=True)
    target = (2 * source.detach() + 1).requires_grad_()
    s, r, t = fit_similarity(source, target)
    (s.sum() + r.sum() + t.sum()).backward()
    assert torch.isfinite(source.grad).all() and torch.isfinite(target.grad).all()


def test_gradcheck():
    """The docstring promises gradients: finite ones alone would pass a detached centroid or scale."""
    g = torch.Generator().manual_seed(5)
    source = torch.randn(2, 7, 3, generator=g, dtype=torch.float64, requires_grad=True)
    rotation = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))[0]
    noise = 0.05 * torch.randn(2, 7, 3, generator=g, dtype=torch.float64)
    target = (1.7 * source.detach() @ rotation.T + torch.tensor([1.0, -2.0, 3.0]) + noise).requires_grad_()
    weights = (0.5 + torch.rand(2, 7, generator=g, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda s, t, w: fit_similarity(s, t, w), (source, target, weights))


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"source": torch.zeros(1, 5, 2)}, r"source: expected shape \(B, N, 3\), got \(1, 5, 2\)"),
        ({"target": torch.zeros(1, 4, 3)}, r"target: expected shape \(B, N, 3\) with N=5"),
        ({"source": torch.zeros(1, 2, 3), "target": torch.zeros(1, 2, 3)}, r"source: expected at least 3 points"),
        ({"source": torch.full((1, 5, 3), float("nan"))}, r"source: expected finite values"),
        ({"target": torch.zeros(1, 5, 3, dtype=torch.long)}, r"target: expected a floating-point tensor"),
        ({"weights": -torch.ones(1, 5)}, r"weights: expected non-negative"),
        ({"weights": torch.zeros(1, 5)}, r"weights: expected a positive sum"),
        ({"weights": torch.ones(1, 4)}, r"weights: expected shape \(B, N\) with N=5"),
        ({"source": torch.ones(1, 5, 3)}, r"source, target: expected corresponding points that span a plane"),
        ({"source": torch.arange(15.0).reshape(1, 5, 3)}, r"got degenerate points in problem\(s\) \[0\]"),
        ({"weights": torch.tensor([[1.0, 1.0, 0.0, 0.0, 0.0]])}, r"span a plane"),
    ],
)
def test_bad_inputs(kwargs, match):
    args = {"source": torch.randn(1, 5, 3), "target": torch.randn(1, 5, 3), "weights": None}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        fit_similarity(**args)


def test_landmark_correspondences():
    assert set(DEFAULT_ALIGNMENT_LANDMARKS) <= set(LANDMARK_NAMES) and len(DEFAULT_ALIGNMENT_LANDMARKS) == 6
    named = {name: i for i, name in enumerate(LANDMARK_NAMES)}
    ibug = {f"ibug_{i:02d}": 1000 + i for i in range(68)}
    pairs = landmark_correspondences(named, ibug)
    assert pairs.shape == (6, 2) and pairs.dtype == torch.long
    assert pairs[:, 0].tolist() == [named[n] for n in DEFAULT_ALIGNMENT_LANDMARKS]
    assert pairs[:, 1].tolist() == [1036, 1039, 1042, 1045, 1030, 1008]
    with pytest.raises(ValueError, match=r"target_landmarks: expected landmark 'right_ear_top'"):
        landmark_correspondences(named, ibug, ["right_ear_top"])


def test_apply_similarity_names_a_mismatched_dtype():
    points = torch.zeros(1, 4, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="rotation: expected dtype torch.float64"):
        apply_similarity(points, torch.ones(1, dtype=torch.float64), torch.eye(3)[None], torch.zeros(1, 3, dtype=torch.float64))


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(s=torch.tensor([float("nan")])), "s: expected finite values, got 1 NaN or infinite entries"),
        (dict(s=torch.tensor([-2.0])), r"s: expected scales > 0, got 1 of 1 <= 0 \(smallest -2\)"),
        (dict(s=torch.tensor([0.0])), "s: expected scales > 0"),
        (dict(rotation=5 * torch.eye(3)[None]), "rotation: expected rotation matrices, orthonormal with det \\+1"),
        (dict(rotation=torch.diag(torch.tensor([1.0, 1.0, -1.0]))[None]), "rotation: expected rotation matrices"),
        (dict(rotation=torch.full((1, 3, 3), float("nan"))), "rotation: expected finite values"),
        (dict(translation=torch.tensor([[0.0, float("inf"), 0.0]])), "translation: expected finite values"),
    ],
)
def test_apply_similarity_refuses_a_transform_that_is_not_a_similarity(change, match):
    """Regression: a NaN scale mapped every point to NaN, and a negative scale or a matrix 5 I that
    is no rotation were applied silently."""
    args = dict(points=torch.ones(1, 2, 3), s=torch.tensor([1.0]), rotation=torch.eye(3)[None], translation=torch.zeros(1, 3))
    args.update(change)
    with pytest.raises(ValueError, match=match):
        apply_similarity(**args)


def test_three_points_in_a_plane_are_enough():
    source = torch.tensor([[[0.0, 0, 0], [10, 0, 0], [0, 5, 0]]], dtype=torch.float64)
    R = torch.from_numpy(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix())[None]
    target = 1.5 * source @ R.transpose(1, 2) + 2.0
    s, R_fit, t = fit_similarity(source, target)
    assert_close(s, torch.tensor([1.5], dtype=torch.float64))
    assert_close(R_fit, R)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_is_solved_in_float32(dtype):
    """torch has no half-precision SVD: the fit runs in float32 and returns the input's dtype."""
    g = torch.Generator().manual_seed(3)
    source = torch.randn(2, 20, 3, generator=g)
    R = torch.from_numpy(Rotation.random(2, random_state=1).as_matrix()).float()
    target = 1.5 * source @ R.transpose(1, 2) + torch.tensor([1.0, -2.0, 0.5])
    s, R_fit, t = fit_similarity(source.to(dtype), target.to(dtype))
    assert s.dtype == R_fit.dtype == t.dtype == dtype
    assert_close(R_fit.float(), R, atol=0.05, rtol=0)
    assert_close(s.float(), torch.full((2,), 1.5), atol=0.05, rtol=0)
