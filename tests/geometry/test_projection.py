import cv2
import numpy as np
import pytest
import torch

from facenormals.geometry import euler_to_rotation_matrix, project_points, transform_points
from tests.conftest import assert_close


def random_problem(batch, n, dtype=torch.float64, device="cpu", seed=0):
    g = torch.Generator().manual_seed(seed)
    points = (torch.rand(batch, n, 3, generator=g) * 2 - 1) * 100
    angles = (torch.rand(batch, 3, generator=g) * 2 - 1) * torch.tensor([0.4, 0.6, 1.5])
    R = euler_to_rotation_matrix(angles.double()).float()
    t = torch.rand(batch, 3, generator=g) * 20 - 10
    # put the object ~600 mm in front of the camera: R (p + t) has z ~ 600
    t = t + (R.transpose(1, 2) @ torch.tensor([0.0, 0.0, 600.0]))
    K = torch.stack([torch.rand(batch, generator=g) * 500 + 300, 64 + torch.randn(batch, generator=g),
                     60 + torch.randn(batch, generator=g)], -1)
    to = dict(dtype=dtype, device=device)
    return points.to(**to), R.to(**to), t.to(**to), K.to(**to)


def test_against_cv2_project_points(dtype, device):
    points, R, t, K = random_problem(8, 100, dtype, device)
    uv, z = project_points(points, R, t, K)
    assert uv.shape == (8, 100, 2) and z.shape == (8, 100)
    assert uv.dtype == dtype and uv.device == device
    for b in range(8):
        Rb = R[b].double().cpu().numpy()
        rvec, _ = cv2.Rodrigues(Rb)
        tvec = Rb @ t[b].double().cpu().numpy()  # paper: R (p + t) = R p + (R t)
        f, u0, v0 = K[b].double().cpu().numpy()
        cam = np.array([[f, 0, u0], [0, f, v0], [0, 0, 1]])
        ref, _ = cv2.projectPoints(points[b].double().cpu().numpy(), rvec, tvec, cam, None)
        err = np.abs(uv[b].double().cpu().numpy() - ref[:, 0, :]).max()
        assert err < (1e-4 if dtype == torch.float64 else 5e-3), err


def test_naive_loop_and_depth():
    points, R, t, K = random_problem(2, 10)
    uv, z = project_points(points, R, t, K)
    for b in range(2):
        for i in range(10):
            Xc = R[b] @ (points[b, i] + t[b])
            f, u0, v0 = K[b]
            assert_close(uv[b, i], torch.stack([f * Xc[0] / Xc[2] + u0, f * Xc[1] / Xc[2] + v0]))
            assert_close(z[b, i], Xc[2])
    assert_close(transform_points(points, R, t)[..., 2], z)


def test_pixel_centre_convention():
    # a point on the optical axis lands exactly on the principal point, in pixel-centre coordinates
    uv, _ = project_points(torch.zeros(1, 1, 3), torch.eye(3)[None], torch.tensor([[0.0, 0.0, 1.0]]),
                           torch.tensor([[100.0, 63.5, 31.0]]))
    assert uv.tolist() == [[[63.5, 31.0]]]
    # +x goes right, +y goes down
    uv, _ = project_points(torch.tensor([[[1.0, 2.0, 0.0]]]), torch.eye(3)[None], torch.tensor([[0.0, 0.0, 10.0]]),
                           torch.tensor([[10.0, 0.0, 0.0]]))
    assert uv.tolist() == [[[1.0, 2.0]]]


def test_translation_before_rotation():
    R = euler_to_rotation_matrix(torch.tensor([[0.0, 0.0, 0.5]], dtype=torch.float64))
    t = torch.tensor([[0.0, 0.0, 500.0]], dtype=torch.float64)
    _, z = project_points(torch.zeros(1, 1, 3, dtype=torch.float64), R, t,
                          torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64))
    assert_close(z, torch.tensor([[500.0 * np.cos(0.5)]], dtype=torch.float64))


def test_gradcheck():
    points, R, t, K = random_problem(2, 5)
    args = [x.clone().requires_grad_() for x in (points, R, t, K)]
    assert torch.autograd.gradcheck(lambda *a: project_points(*a), args)


def test_zero_depth_is_finite():
    uv, z = project_points(torch.zeros(1, 1, 3), torch.eye(3)[None], torch.zeros(1, 3), torch.tensor([[1.0, 0.0, 0.0]]))
    assert torch.isfinite(uv).all() and z.item() == 0.0


@pytest.mark.parametrize(
    "which,bad,match",
    [
        ("points", torch.zeros(2, 5), r"points: expected shape \(B, N, 3\)"),
        ("points", torch.zeros(2, 5, 2), r"points: expected shape \(B, N, 3\)"),
        ("rotation", torch.zeros(3, 3, 3), r"rotation: expected shape \(B, 3, 3\) with B=2"),
        ("translation", torch.zeros(2, 2), r"translation: expected shape \(B, 3\)"),
        ("intrinsics", torch.zeros(1, 3), r"intrinsics: expected shape \(B, 3\) with B=2"),
        ("intrinsics", torch.zeros(2, 4), r"intrinsics: expected shape \(B, 3\)"),
        ("points", torch.zeros(2, 5, 3, dtype=torch.long), "points: expected a floating-point"),
        ("rotation", torch.eye(3, dtype=torch.float64).expand(2, 3, 3),
         r"rotation: expected dtype torch.float32 \(the dtype of points\), got torch.float64"),
        ("intrinsics", torch.ones(2, 3, dtype=torch.float64), "intrinsics: expected dtype torch.float32"),
        # a NaN gives NaN pixels that later ops read as "outside", and f <= 0 mirrors the image
        ("points", torch.zeros(2, 5, 3).index_fill(1, torch.tensor([2]), float("nan")),
         "points: expected finite values, got 6 NaN"),
        ("rotation", torch.eye(3).repeat(2, 1, 1).index_fill(2, torch.tensor([0]), float("inf")),
         "rotation: expected finite values"),
        ("translation", torch.tensor([[0.0, 0.0, 500.0], [0.0, float("nan"), 500.0]]), "translation: expected finite"),
        ("intrinsics", torch.tensor([[1.0, 1.0, 1.0], [float("nan"), 1.0, 1.0]]), "intrinsics: expected finite"),
        ("intrinsics", torch.tensor([[1.0, 1.0, 1.0], [-1000.0, 64.0, 64.0]]),
         r"intrinsics: expected focal lengths f > 0, got -1000"),
        ("intrinsics", torch.tensor([[0.0, 64.0, 64.0], [1.0, 1.0, 1.0]]), r"f > 0, got 0"),
    ],
)
def test_bad_input(which, bad, match):
    args = dict(points=torch.zeros(2, 5, 3), rotation=torch.eye(3).expand(2, 3, 3), translation=torch.zeros(2, 3),
                intrinsics=torch.ones(2, 3))
    args[which] = bad
    with pytest.raises(ValueError, match=match):
        project_points(**args)


def test_transform_points_refuses_nan():
    with pytest.raises(ValueError, match="translation: expected finite values"):
        transform_points(torch.zeros(1, 2, 3), torch.eye(3)[None], torch.tensor([[0.0, float("nan"), 1.0]]))


def test_compile_smoke():
    points, R, t, K = random_problem(2, 5)
    fn = torch.compile(project_points, backend="eager")
    assert_close(fn(points, R, t, K)[0], project_points(points, R, t, K)[0])


def test_vmap_and_jacfwd_over_the_intrinsics():
    """Regression: the f > 0 check read values of a tensor vmap wraps (RuntimeError: data-dependent
    control flow); like the finiteness checks it is now skipped there."""
    from facenormals.geometry import projection_jacobian

    points, R, t, K = random_problem(1, 4)
    intrinsics = torch.cat([K, K * 1.1])
    pixels = torch.func.vmap(lambda k: project_points(points, R, t, k[None])[0])(intrinsics)
    for b in range(2):
        assert_close(pixels[b], project_points(points, R, t, intrinsics[b : b + 1])[0])
    cam = transform_points(points, R, t)
    jac = torch.func.vmap(lambda k: projection_jacobian(cam, k[None]))(intrinsics)
    assert_close(jac[1], projection_jacobian(cam, intrinsics[1:]))
    assert torch.func.jacfwd(lambda k: project_points(points, R, t, k)[0])(K).shape == (1, 4, 2, 1, 3)
    with pytest.raises(ValueError, match="intrinsics: expected focal lengths f > 0"):
        project_points(points, R, t, -K)  # still checked outside the transforms


def test_projection_jacobian_matches_autograd():
    from facenormals.geometry import projection_jacobian

    points, R, t, K = random_problem(2, 4)
    cam = transform_points(points, R, t)
    J = projection_jacobian(cam, K)
    ref = torch.autograd.functional.jacobian(
        lambda c: project_points(c, torch.eye(3, dtype=c.dtype).expand(2, 3, 3), torch.zeros(2, 3, dtype=c.dtype), K)[0],
        cam)  # (B,N,2,B,N,3)
    for b in range(2):
        for i in range(4):
            assert_close(J[b, i], ref[b, i, :, b, i])
    with pytest.raises(ValueError, match="camera_points"):
        projection_jacobian(torch.zeros(2, 4, 2), K)


def test_projection_jacobian_checks_the_intrinsics():
    from facenormals.geometry import projection_jacobian

    points = torch.ones(1, 1, 3)
    with pytest.raises(ValueError, match=r"intrinsics: expected dtype torch.float32 \(the dtype of camera_points\)"):
        projection_jacobian(points, torch.ones(1, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="intrinsics: expected dtype torch.float32"):
        projection_jacobian(points, torch.ones(1, 3, dtype=torch.long))


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_keeps_the_dtype_and_does_not_overflow(dtype):
    """f·x overflows float16 (f = 1000 px, x = 180 mm); the result keeps the input dtype."""
    from facenormals.geometry import projection_jacobian

    points = torch.tensor([[[-180.0, 120.0, 0.0]]])
    R, t, K = torch.eye(3)[None], torch.tensor([[0.0, 0.0, 600.0]]), torch.tensor([[1000.0, 64.0, 64.0]])
    expected, _ = project_points(points, R, t, K)
    pixels, depth = project_points(points.to(dtype), R.to(dtype), t.to(dtype), K.to(dtype))
    assert pixels.dtype == dtype and depth.dtype == dtype
    assert torch.isfinite(pixels).all()
    assert_close(pixels.float(), expected, rtol=1e-2, atol=0.5)
    jac = projection_jacobian(transform_points(points, R, t).to(dtype), K.to(dtype))
    assert jac.dtype == dtype
    assert_close(jac.float(), projection_jacobian(transform_points(points, R, t), K), rtol=1e-2, atol=1e-3)


def test_projection_jacobian_refuses_what_project_points_refuses():
    """Regression: NaN points gave a NaN Jacobian and f <= 0 a mirrored one, silently."""
    from facenormals.geometry import projection_jacobian

    points, K = torch.tensor([[[1.0, 2.0, 500.0]]]), torch.tensor([[300.0, 64.0, 64.0]])
    assert torch.isfinite(projection_jacobian(points, K)).all()
    with pytest.raises(ValueError, match="camera_points: expected finite values, got 1 NaN"):
        projection_jacobian(torch.tensor([[[1.0, float("nan"), 500.0]]]), K)
    with pytest.raises(ValueError, match="intrinsics: expected finite values"):
        projection_jacobian(points, torch.tensor([[float("inf"), 64.0, 64.0]]))
    with pytest.raises(ValueError, match="intrinsics: expected focal lengths f > 0, got -300"):
        projection_jacobian(points, torch.tensor([[-300.0, 64.0, 64.0]]))


@pytest.mark.parametrize("eps", [float("nan"), 0.0, -1.0, "1e-9", None])
def test_eps_must_be_a_positive_number(eps):
    """Regression: a NaN, zero or negative eps gave inf / NaN pixels and Jacobians silently."""
    from facenormals.geometry import projection_jacobian

    points, K = torch.tensor([[[1.0, 0.0, 0.0]]]), torch.tensor([[500.0, 32.0, 32.0]])
    with pytest.raises(ValueError, match="eps: expected"):
        project_points(points, torch.eye(3)[None], torch.zeros(1, 3), K, eps=eps)
    with pytest.raises(ValueError, match="eps: expected"):
        projection_jacobian(points, K, eps=eps)
