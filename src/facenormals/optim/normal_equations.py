r"""The Gauss-Newton normal equations :math:`J^\top J` and :math:`J^\top r` of a batched Jacobian."""

from __future__ import annotations

from torch import Tensor

from facenormals.core.check import check_all_finite, check_floating, check_same_dtype_device, check_shape

__all__ = ["normal_equations"]


def normal_equations(jacobian: Tensor, residuals: Tensor) -> tuple[Tensor, Tensor]:
    r"""``JᵀJ`` and ``Jᵀr`` of a batch of Jacobians, e.g. for a
    :func:`~facenormals.optim.levenberg_marquardt` ``normal_equations_fn``.

    ``JᵀJ`` is symmetric, so only its upper block rows and its lower-right block are multiplied out
    (about 3/4 of a full product's work, see ``docs/performance.md``) and the rest is mirrored: the
    off-diagonal blocks are exact mirrors, the two diagonal blocks symmetric to rounding (the
    solver's Cholesky factorisation reads one triangle).

    Args:
        jacobian: ``J``, the derivatives of the residuals with respect to the parameters.
        residuals: ``r``.

    Returns:
        ``(JᵀJ, Jᵀr)``.

    Raises:
        ValueError: naming the argument on wrong shapes, a non-floating ``jacobian``, mismatched
            dtypes or devices, or NaN or infinite values (one device synchronisation; not checked
            under ``torch.compile`` or ``torch.func`` transforms).

    Shape:
        - jacobian: :math:`(B, M, P)`; residuals: :math:`(B, M)`
        - output: :math:`(B, P, P)` and :math:`(B, P)`

    Example:
        >>> import torch
        >>> J = torch.tensor([[[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]])
        >>> H, g = normal_equations(J, torch.tensor([[1.0, 0.0, -1.0]]))
        >>> H, g
        (tensor([[[35., 44.],
                 [44., 56.]]]), tensor([[-4., -4.]]))
    """
    dims = check_shape(jacobian, ["B", "M", "P"], "jacobian")
    check_shape(residuals, ["B", "M"], "residuals", dims)
    check_floating(jacobian, "jacobian")
    check_same_dtype_device(jacobian, "jacobian", residuals=residuals)
    check_all_finite(jacobian=jacobian, residuals=residuals)  # NaN would spread through JᵀJ silently
    # rᵀJ rather than Jᵀr: a batched row-vector product reads J in its own layout (a transposed
    # matrix-vector product is several times slower on CPU).
    return gram(jacobian), (residuals.unsqueeze(1) @ jacobian).squeeze(1)


def gram(jacobian: Tensor) -> Tensor:
    """``JᵀJ`` ``(B, P, P)`` of ``(B, M, P)`` without input checks (for callers that have checked)."""
    P = jacobian.shape[-1]
    if P < 16:  # a small product: the split's extra operations would cost more than they save
        return jacobian.transpose(1, 2) @ jacobian
    k = (3 * P) // 5  # of the splits measured on the fit's Jacobians (P = 100), 60/40 was fastest
    top = jacobian[..., :k].transpose(1, 2) @ jacobian  # block rows :k, all columns
    out = top.new_empty(jacobian.shape[0], P, P)
    out[:, :k] = top
    out[:, k:, :k] = top[..., k:].transpose(1, 2)
    out[:, k:, k:] = jacobian[..., k:].transpose(1, 2) @ jacobian[..., k:]
    return out
