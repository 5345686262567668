import pytest
import torch

from facenormals.core import check_finite, check_floating, check_same_dims, check_shape, check_tensor


def test_binds_named_dims():
    dims = check_shape(torch.zeros(2, 7, 3), ["B", "N", 3], "points")
    assert dims == {"B": 2, "N": 7}
    check_shape(torch.zeros(2, 3), ["B", 3], "translation", dims)


def test_wildcard():
    assert check_shape(torch.zeros(4, 5, 6, 3), ["*", "N", 3], "x") == {"N": 6}
    with pytest.raises(ValueError, match=r"x: expected shape \(\*, N, 3\), got \(2,\)"):
        check_shape(torch.zeros(2), ["*", "N", 3], "x")


@pytest.mark.parametrize(
    "shape,match",
    [
        ((2, 7), r"points: expected shape \(B, N, 3\) \(3 dimensions\), got \(2, 7\) \(2 dimensions\)"),
        ((2, 7, 4), r"points: expected shape \(B, N, 3\), got \(2, 7, 4\)"),
    ],
)
def test_messages_name_argument_and_shapes(shape, match):
    with pytest.raises(ValueError, match=match):
        check_shape(torch.zeros(shape), ["B", "N", 3], "points")


def test_batch_mismatch():
    dims = check_shape(torch.zeros(2, 7, 3), ["B", "N", 3], "points")
    with pytest.raises(ValueError, match=r"rotation: expected shape \(B, 3, 3\) with B=2 .* got \(3, 3, 3\)"):
        check_shape(torch.zeros(3, 3, 3), ["B", 3, 3], "rotation", dims)


def test_repeated_name_within_one_tensor():
    check_shape(torch.zeros(3, 3), ["P", "P"], "matrix")
    with pytest.raises(ValueError, match="equal P"):
        check_shape(torch.zeros(3, 4), ["P", "P"], "matrix")


def test_non_tensor_and_dtype_and_finite():
    with pytest.raises(ValueError, match="x: expected a torch.Tensor, got list"):
        check_tensor([1.0], "x")
    with pytest.raises(ValueError, match="x: expected a torch.Tensor"):
        check_shape([1.0], ["N"], "x")
    with pytest.raises(ValueError, match="x: expected a floating-point tensor, got dtype torch.int64"):
        check_floating(torch.zeros(2, dtype=torch.long), "x")
    with pytest.raises(ValueError, match="x: expected finite values, got 1 NaN"):
        check_finite(torch.tensor([1.0, float("nan")]), "x")
    check_finite(torch.ones(3), "x")


def test_check_same_dims():
    check_same_dims({"B": 2}, "x", B=2)
    with pytest.raises(ValueError, match="x: expected B=3, got B=2"):
        check_same_dims({"B": 2}, "x", B=3)


def test_integers_from_numpy_and_torch_are_integers():
    import numpy as np

    from facenormals.core.check import check_image_size, check_integer

    assert check_integer(np.int64(2), "scale", minimum=1) == 2
    assert check_integer(torch.tensor(3), "radius") == 3
    assert check_image_size(torch.tensor([8, 6])) == (8, 6)
    for bad in (True, np.bool_(True), 2.0, torch.tensor(2.0), "2"):
        with pytest.raises(ValueError, match="radius: expected an integer"):
            check_integer(bad, "radius")


def test_check_finite_may_allow_inf_but_never_nan():
    check_finite(torch.tensor([1.0, float("inf")]), "zbuffer", allow_inf=True)
    with pytest.raises(ValueError, match="zbuffer: expected finite values, got 1 NaN or infinite entries"):
        check_finite(torch.tensor([1.0, float("inf")]), "zbuffer")
    with pytest.raises(ValueError, match="zbuffer: expected no NaN values, got 2 NaN entries"):
        check_finite(torch.tensor([float("nan"), float("nan"), float("inf")]), "zbuffer", allow_inf=True)


@pytest.mark.parametrize("value", [0.5, -2, torch.tensor(1.5)])
def test_check_real_accepts_numbers(value):
    from facenormals.core.check import check_real

    assert check_real(value, "x") == float(value)


@pytest.mark.parametrize("value,match", [("0.2", "expected a real number, got str"), (True, "expected a real number"),
                                         (float("nan"), "expected a finite number, got nan"),
                                         (torch.ones(2), "expected a real number, got Tensor")])
def test_check_real_refuses_the_rest(value, match):
    from facenormals.core.check import check_real

    with pytest.raises(ValueError, match=f"x: {match}"):
        check_real(value, "x")


def test_finite_checks_are_exact_despite_their_fast_path():
    # the fast path tests the sum: a sum that overflows must fall through to the exact test, and
    # NaN or inf anywhere must still be found and named
    from facenormals.core.check import check_all_finite

    large = torch.full((4,), 3e38)  # finite, but its float32 sum is inf
    check_finite(large, "large")
    check_all_finite(a=large, b=-large, c=torch.zeros(2, dtype=torch.float16) + 6e4)
    for bad in (float("nan"), float("inf"), -float("inf")):
        x = torch.zeros(3, 5)
        x[1, 2] = bad
        with pytest.raises(ValueError, match="x: expected finite values, got 1 NaN or infinite entries"):
            check_finite(x, "x")
        with pytest.raises(ValueError, match="x: expected finite values"):
            check_all_finite(ok=large, x=x)
    both = torch.tensor([float("inf"), -float("inf")])  # their sum is NaN, each is infinite
    with pytest.raises(ValueError, match="got 2 NaN or infinite entries"):
        check_finite(both, "both")


def test_outward_share_of_closed_open_and_flat_meshes():
    """+1 / -1 for a closed mesh wound outward / inward, clearly positive for a cap, and 0 for a flat mesh
    in any orientation (each face's sign there is rounding noise: a tilted flat square read as inward
    in half of its orientations, and MorphableModel refused it)."""
    import math

    from facenormals.core.check import outward_share
    from facenormals.geometry import euler_to_rotation_matrix
    from facenormals.models import MorphableModel, builtin_head_model

    head = builtin_head_model()
    assert outward_share(head.mean, head.faces) > 0.9 and outward_share(head.mean, head.faces[:, [0, 2, 1]]) < -0.9
    front = head.mean[:, 2] < float(head.mean[:, 2].quantile(0.3))
    cap = head.faces[front[head.faces].all(1)]
    assert outward_share(head.mean, cap) > 0.3
    n = 6
    xs = torch.linspace(-50.0, 50.0, n, dtype=torch.float64)
    gy, gx = torch.meshgrid(xs, xs, indexing="ij")
    flat = torch.stack([gx, gy, torch.zeros_like(gx)], -1).reshape(-1, 3)
    idx = torch.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].reshape(-1), idx[:-1, 1:].reshape(-1), idx[1:, :-1].reshape(-1), idx[1:, 1:].reshape(-1)
    faces = torch.cat([torch.stack([a, c, b], 1), torch.stack([b, c, d], 1)])
    g = torch.Generator().manual_seed(0)
    for _ in range(100):
        angles = (torch.rand(1, 3, generator=g, dtype=torch.float64) * 2 - 1) * math.pi
        tilted = flat @ euler_to_rotation_matrix(angles)[0].T + 1000 * torch.rand(3, generator=g, dtype=torch.float64)
        assert outward_share(tilted, faces) == 0.0
        assert outward_share(tilted.float(), faces) == 0.0
        MorphableModel(tilted, torch.zeros(1, n * n, 3, dtype=torch.float64), faces)
    assert outward_share(torch.rand(3, 3, generator=g), torch.tensor([[0, 1, 2]])) == 0.0  # one triangle: no inside


def test_huge_integers_and_non_tensors_are_named():
    """float(10**400) raised a bare OverflowError; a numpy array reached torch internals."""
    import numpy as np

    from facenormals.core.check import check_all_finite, check_finite, check_floating, check_nonnegative, check_positive, check_real

    for check in (check_real, check_nonnegative, check_positive):
        with pytest.raises(ValueError, match="min_facing: expected a finite number, got an integer of 401 digits"):
            check(10**400, "min_facing")
    for check in (check_finite, check_floating):
        with pytest.raises(ValueError, match="x: expected a torch.Tensor, got ndarray"):
            check(np.array([np.nan]), "x")
    with pytest.raises(ValueError, match="y: expected a torch.Tensor, got list"):
        check_all_finite(x=torch.zeros(2), y=[1.0])


def test_zero_dimensional_tensors_are_numbers_and_others_are_not():
    from facenormals.core.check import check_integer, check_nonnegative, check_real

    assert check_nonnegative(torch.tensor(0.5), "weight") == 0.5 == check_real(torch.tensor(0.5), "weight")
    assert check_integer(torch.tensor(3), "count") == 3
    with pytest.raises(ValueError, match="count: expected an integer, got Tensor"):
        check_integer(torch.tensor([[3]]), "count")
    with pytest.raises(ValueError, match="weight: expected a real number"):
        check_nonnegative(torch.tensor([0.5, 1.0]), "weight")


def test_check_device_takes_cpu_and_cuda_names_and_devices_only():
    import re

    from facenormals.core.check import check_device

    assert check_device("cpu") == torch.device("cpu") == check_device(torch.device("cpu"))
    assert check_device("cpu:0") == torch.device("cpu", 0)
    for bad in ("mps", "meta", "bogus", "", "cuda:x", None, 3.5, torch.device("meta")):
        with pytest.raises(ValueError, match=re.escape(f"dev: expected 'cpu', 'cuda' or 'cuda:N', got {bad!r}")):
            check_device(bad, "dev")
    if not torch.cuda.is_available():
        for cuda in ("cuda", "cuda:1", torch.device("cuda", 0)):
            with pytest.raises(ValueError, match=re.escape(f"dev: {cuda!r} requested but this torch build "
                                                            f"({torch.__version__}) has no CUDA device; use X")):
                check_device(cuda, "dev", hint="; use X")
    else:
        assert check_device("cuda").type == "cuda"
