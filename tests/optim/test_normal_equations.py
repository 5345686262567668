"""Tests of ``normal_equations`` against a naive loop and numpy."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from facenormals.optim import normal_equations
from tests.conftest import assert_close

F64 = torch.float64


def naive(J: torch.Tensor, r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """JᵀJ and Jᵀr entry by entry."""
    B, M, P = J.shape
    H = torch.zeros(B, P, P, dtype=J.dtype)
    g = torch.zeros(B, P, dtype=J.dtype)
    for b in range(B):
        for i in range(P):
            g[b, i] = sum(J[b, m, i] * r[b, m] for m in range(M))
            for j in range(P):
                H[b, i, j] = sum(J[b, m, i] * J[b, m, j] for m in range(M))
    return H, g


@pytest.mark.parametrize("P", [1, 2, 5, 7])
def test_matches_naive_loop(P: int) -> None:
    g = torch.Generator().manual_seed(P)
    J, r = torch.randn(2, 6, P, generator=g, dtype=F64), torch.randn(2, 6, generator=g, dtype=F64)
    H, grad = normal_equations(J, r)
    H_ref, g_ref = naive(J, r)
    assert_close(H, H_ref, atol=1e-12, rtol=0)
    assert_close(grad, g_ref, atol=1e-12, rtol=0)


def test_matches_numpy_and_is_exactly_symmetric() -> None:
    g = torch.Generator().manual_seed(0)
    J, r = torch.randn(3, 500, 100, generator=g), torch.randn(3, 500, generator=g)
    H, grad = normal_equations(J, r)
    Jn, rn = J.double().numpy(), r.double().numpy()
    np.testing.assert_allclose(H.numpy(), np.einsum("bmi,bmj->bij", Jn, Jn), rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(grad.numpy(), np.einsum("bmi,bm->bi", Jn, rn), rtol=1e-4, atol=1e-3)
    assert torch.equal(H, H.transpose(1, 2))  # mirrored, not computed twice


def test_no_rows_gives_zeros() -> None:
    H, grad = normal_equations(torch.zeros(2, 0, 4), torch.zeros(2, 0))
    assert torch.equal(H, torch.zeros(2, 4, 4)) and torch.equal(grad, torch.zeros(2, 4))


def test_gradcheck() -> None:
    g = torch.Generator().manual_seed(1)
    J = torch.randn(2, 5, 4, generator=g, dtype=F64, requires_grad=True)
    r = torch.randn(2, 5, generator=g, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(normal_equations, (J, r))
    # P >= 16 takes the split product whose lower-left block is mirrored from the upper-right one
    J = torch.randn(2, 20, 17, generator=g, dtype=F64, requires_grad=True)
    r = torch.randn(2, 20, generator=g, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(normal_equations, (J, r))


@pytest.mark.parametrize(
    "J, r, match",
    [
        (torch.zeros(5, 3), torch.zeros(1, 5), r"jacobian: expected shape \(B, M, P\)"),
        (torch.zeros(1, 5, 3), torch.zeros(1, 4), r"residuals: expected shape \(B, M\) with M=5.*got \(1, 4\)"),
        (torch.zeros(1, 5, 3, dtype=torch.long), torch.zeros(1, 5), "jacobian: expected a floating"),
        (torch.zeros(1, 5, 3), torch.zeros(1, 5, dtype=F64), "residuals: expected dtype"),
        # regression: NaN spread through JᵀJ and Jᵀr silently
        (torch.zeros(1, 5, 3).index_fill(1, torch.tensor([2]), float("nan")), torch.zeros(1, 5),
         "jacobian: expected finite values, got 3 NaN or infinite entries"),
        (torch.zeros(1, 5, 3), torch.tensor([[0.0, float("inf"), 0, 0, 0]]),
         "residuals: expected finite values, got 1 NaN or infinite entries"),
    ],
)
def test_bad_inputs_name_the_argument(J, r, match) -> None:
    with pytest.raises(ValueError, match=match):
        normal_equations(J, r)
