import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from facenormals.geometry import euler_to_rotation_matrix, rotation_matrix_to_euler
from tests.conftest import assert_close


def random_angles(n, dtype=torch.float64, device="cpu", seed=0):
    g = torch.Generator().manual_seed(seed)
    roll = (torch.rand(n, generator=g) * 2 - 1) * math.pi
    pitch = (torch.rand(n, generator=g) * 2 - 1) * (math.pi / 2 - 0.05)
    yaw = (torch.rand(n, generator=g) * 2 - 1) * math.pi
    return torch.stack([roll, pitch, yaw], -1).to(dtype=dtype, device=device)


def test_against_scipy_intrinsic_yxz(dtype, device):
    angles = random_angles(50, dtype, device)
    R = euler_to_rotation_matrix(angles)
    a = angles.double().cpu().numpy()
    # R = R_y(yaw) R_x(pitch) R_z(roll) is scipy's intrinsic "YXZ" with angles (yaw, pitch, roll).
    ref = Rotation.from_euler("YXZ", np.stack([a[:, 2], a[:, 1], a[:, 0]], -1)).as_matrix()
    assert R.dtype == dtype and R.device == device
    assert_close(R.cpu(), torch.from_numpy(ref), atol=1e-6 if dtype == torch.float32 else 1e-12)


def test_elementary_rotations_and_signs():
    # Face direction (-z) and head top (-y) in the model frame, see docs/conventions.md.
    face, top = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64), torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    yaw = euler_to_rotation_matrix(torch.tensor([[0.0, 0.0, 0.3]], dtype=torch.float64))[0]
    assert (yaw @ face)[0] < 0  # positive yaw turns the face to image left
    pitch = euler_to_rotation_matrix(torch.tensor([[0.0, 0.3, 0.0]], dtype=torch.float64))[0]
    assert (pitch @ face)[1] > 0  # positive pitch turns the face down
    roll = euler_to_rotation_matrix(torch.tensor([[0.3, 0.0, 0.0]], dtype=torch.float64))[0]
    assert (roll @ top)[0] > 0  # positive roll tilts the head top to image right
    c, s = math.cos(0.3), math.sin(0.3)
    assert_close(roll, torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=torch.float64))


def test_round_trip(dtype, device):
    angles = random_angles(200, dtype, device, seed=1)
    back = rotation_matrix_to_euler(euler_to_rotation_matrix(angles))
    assert_close(back, angles, atol=1e-5 if dtype == torch.float32 else 1e-10)


def test_round_trip_matrix_profile_views():
    angles = torch.tensor([[0.2, 0.1, math.pi / 2], [-0.3, -0.4, -math.pi / 2]], dtype=torch.float64)
    R = euler_to_rotation_matrix(angles)
    assert_close(euler_to_rotation_matrix(rotation_matrix_to_euler(R)), R)
    assert_close(rotation_matrix_to_euler(R), angles)


def test_orthonormal(dtype):
    R = euler_to_rotation_matrix(random_angles(20, dtype))
    eye = torch.eye(3, dtype=dtype).expand(20, 3, 3)
    assert_close(R @ R.transpose(1, 2), eye, atol=1e-6 if dtype == torch.float32 else 1e-12)
    assert_close(torch.linalg.det(R), torch.ones(20, dtype=dtype), atol=1e-5 if dtype == torch.float32 else 1e-12)


def test_gradcheck():
    angles = random_angles(3, seed=2).requires_grad_()
    assert torch.autograd.gradcheck(euler_to_rotation_matrix, (angles,))
    R = euler_to_rotation_matrix(random_angles(3, seed=3)).requires_grad_()
    assert torch.autograd.gradcheck(rotation_matrix_to_euler, (R,))


@pytest.mark.parametrize("bad", [torch.zeros(3), torch.zeros(2, 4), torch.zeros(2, 3, 1)])
def test_bad_angles(bad):
    with pytest.raises(ValueError, match=r"angles: expected shape \(B, 3\)"):
        euler_to_rotation_matrix(bad)


def test_non_finite_angles_and_rotations_are_errors():
    from facenormals.geometry import euler_rotation_derivatives

    nan = torch.tensor([[0.0, float("nan"), 0.0]])
    for op in (euler_to_rotation_matrix, euler_rotation_derivatives):
        with pytest.raises(ValueError, match="angles: expected finite values, got 1 NaN"):
            op(nan)
    with pytest.raises(ValueError, match="rotation: expected finite values"):
        rotation_matrix_to_euler(torch.eye(3)[None] * float("inf"))


def test_bad_rotation():
    with pytest.raises(ValueError, match="rotation"):
        rotation_matrix_to_euler(torch.zeros(2, 3, 4))
    with pytest.raises(ValueError, match="floating"):
        euler_to_rotation_matrix(torch.zeros(2, 3, dtype=torch.long))


def test_compile_smoke():
    fn = torch.compile(euler_to_rotation_matrix, backend="eager")
    angles = random_angles(4)
    assert_close(fn(angles), euler_to_rotation_matrix(angles))


def test_rotation_derivatives_match_autograd():
    from facenormals.geometry import euler_rotation_derivatives

    angles = random_angles(4, seed=5)
    D = euler_rotation_derivatives(angles)
    J = torch.autograd.functional.jacobian(euler_to_rotation_matrix, angles)  # (B,3,3,B,3)
    for b in range(4):
        for j in range(3):
            assert_close(D[b, j], J[b, :, :, b, j])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_angles_stay_in_the_documented_half_open_range(dtype):
    """roll and yaw lie in (-π, π]: a half turn is +π, also when atan2 meets a signed zero."""
    angles = torch.tensor([[math.pi, 0.1, -math.pi]], dtype=dtype)
    back = rotation_matrix_to_euler(euler_to_rotation_matrix(angles)).double()
    assert bool((back > -math.pi).all()) and bool((back <= math.pi + 1e-6).all())
    wrapped = torch.remainder(back - angles.double() + math.pi, 2 * math.pi) - math.pi
    assert float(wrapped.abs().max()) < 1e-5
    half_turn = torch.tensor([[[-1.0, 0.0, 0.0], [-0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]], dtype=dtype)  # roll π
    assert rotation_matrix_to_euler(half_turn)[0, 0].item() == pytest.approx(math.pi)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("pitch_sign", [1.0, -1.0])
def test_gimbal_lock_gives_angles_that_rebuild_the_matrix(dtype, pitch_sign):
    """At |pitch| = 90 deg only yaw -/+ roll is determined: roll is 0 and yaw carries it (both
    atan2 used to see 0/0 there and return (0, ±90°, 0), 0.1 off the matrix); near the singularity
    the angles still rebuild the matrix."""
    roll, yaw = 0.3, 0.4
    cr, sr, cy, sy = math.cos(roll), math.sin(roll), math.cos(yaw), math.sin(yaw)
    Rz = torch.tensor([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]], dtype=dtype)
    Rx = torch.tensor([[1, 0, 0], [0, 0, -pitch_sign], [0, pitch_sign, 0]], dtype=dtype)  # cos(pitch) exactly 0
    Ry = torch.tensor([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]], dtype=dtype)
    R = (Ry @ Rx @ Rz)[None]
    angles = rotation_matrix_to_euler(R)
    assert angles[0, 0] == 0 and abs(float(angles[0, 1]) - pitch_sign * math.pi / 2) < 1e-6
    assert abs(float(angles[0, 2]) - (yaw - pitch_sign * roll)) < 1e-6
    assert_close(euler_to_rotation_matrix(angles), R, rtol=0, atol=1e-6)
    for offset in (1e-9, 1e-6, 1e-4, 1e-2):
        near = euler_to_rotation_matrix(torch.tensor([[roll, pitch_sign * (math.pi / 2 - offset), yaw]], dtype=dtype))
        assert_close(euler_to_rotation_matrix(rotation_matrix_to_euler(near)), near, rtol=0,
                     atol=1e-4 if dtype == torch.float32 else 1e-9)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("pitch_sign", [1.0, -1.0])
def test_gradients_stay_finite_at_an_exact_gimbal_lock(dtype, pitch_sign):
    """Regression: at pitch exactly ±90 deg, R[1,0] = R[1,1] = 0 and the derivative of
    sqrt(R[1,0]² + R[1,1]²) is infinite: the gradient of the angles was NaN."""
    R = torch.tensor([[[1.0, 0, 0], [0, 0, -pitch_sign], [0, pitch_sign, 0]]], dtype=dtype, requires_grad=True)
    angles = rotation_matrix_to_euler(R)
    assert abs(float(angles[0, 1].detach()) - pitch_sign * math.pi / 2) < 1e-6
    for k in range(3):
        (grad,) = torch.autograd.grad(angles[0, k], R, retain_graph=True)
        assert torch.isfinite(grad).all(), k
    (grad,) = torch.autograd.grad(angles[0, 1], R)
    assert grad[0, 1, :2].abs().max() == 0  # a kink (|x|): the where-pattern's subgradient 0


def test_gradients_stay_finite_where_the_unused_branch_has_zero_arguments():
    """yaw 90 deg, pitch and roll 0: R[0,0] = R[0,1] = 0, the arguments of the gimbal-lock branch's
    atan2, which is not taken; its 0/0 must not reach the gradient through torch.where."""
    angles = torch.tensor([[0.0, 0.0, math.pi / 2]], dtype=torch.float64, requires_grad=True)
    rotation_matrix_to_euler(euler_to_rotation_matrix(angles)).sum().backward()
    assert torch.isfinite(angles.grad).all()
    assert_close(angles.grad, torch.ones_like(angles.grad), rtol=0, atol=1e-9)


def test_matrices_that_are_not_rotations_are_errors():
    """Regression: a reflection gave (0, 0, π) and 2 I gave (0, 0, 0), silently; neither gives the
    matrix back. Now a matrix off orthonormal by more than 1e-3, or with det <= 0, is an error naming
    how many of the batch."""
    good = euler_to_rotation_matrix(random_angles(3, torch.float32, seed=7))
    for bad in (torch.diag(torch.tensor([1.0, 1.0, -1.0])), 2 * torch.eye(3), -torch.eye(3), torch.zeros(3, 3),
                good[0] * 1.002):
        batch = torch.cat([good[:2], bad[None], good[2:]])
        with pytest.raises(ValueError, match=r"rotation: expected rotation matrices, orthonormal with det \+1 "
                                             r"\(max \|R\^T R - I\| <= 0.001\), got 1 of 4 that are not"):
            rotation_matrix_to_euler(batch)
    with pytest.raises(ValueError, match="got 2 of 2 that are not"):
        rotation_matrix_to_euler(torch.stack([torch.diag(torch.tensor([-1.0, 1.0, 1.0])), 0.5 * torch.eye(3)]))
    assert rotation_matrix_to_euler(torch.zeros(0, 3, 3)).shape == (0, 3)


def test_near_orthonormal_float32_and_half_precision_rotations_are_accepted():
    """float32 rotations from an SVD (or cv2.Rodrigues) are ~1e-6 off orthonormal; rounding to
    bfloat16 puts them ~5e-3 off, within its 8 ulps: all give their angles."""
    angles = random_angles(50, torch.float64, seed=8)
    R = euler_to_rotation_matrix(angles)
    g = torch.Generator().manual_seed(9)
    U, _, Vh = torch.linalg.svd((R + 1e-2 * torch.randn(R.shape, generator=g, dtype=R.dtype)).float())
    projected = U @ Vh  # the nearest orthonormal matrix; det +1 this close to a rotation
    assert_close(euler_to_rotation_matrix(rotation_matrix_to_euler(projected)), projected, atol=1e-5, rtol=0)
    assert_close(rotation_matrix_to_euler(R.float()).double(), angles, atol=1e-5, rtol=0)
    cv2 = pytest.importorskip("cv2")
    vector = np.array([0.3, -0.2, 0.5], np.float32)
    rodrigues = torch.from_numpy(cv2.Rodrigues(vector)[0].astype(np.float32))[None]
    assert_close(euler_to_rotation_matrix(rotation_matrix_to_euler(rodrigues)), rodrigues, atol=1e-5, rtol=0)
    for dtype in (torch.float16, torch.bfloat16):
        back = rotation_matrix_to_euler(R.to(dtype))  # no error
        assert back.dtype == dtype
        away = angles[:, 1].abs() < 1.0  # bfloat16 loses roll and yaw near the gimbal lock
        assert_close(euler_to_rotation_matrix(back[away].double()), R[away], atol=0.05, rtol=0)
