r"""Batched Levenberg-Marquardt for many small, independent non-linear least-squares problems.

:func:`levenberg_marquardt` minimises, for every batch element ``b`` independently,

.. math::

    F_b(x_b) = \tfrac12 \lVert r_b(x_b) \rVert^2,

where ``residual_fn`` maps the stacked parameters ``x`` of shape ``(B, P)`` to the stacked
residuals of shape ``(B, M)``. Every element keeps its own damping, gain ratio, convergence tests
and status; elements that have converged or failed are frozen while the others continue.

Each iteration linearises the residuals once (``JᵀJ`` and ``Jᵀr`` with batched matrix products),
solves the damped normal equations with a batched Cholesky factorisation and evaluates the
residuals once at the trial point. The Jacobian is only recomputed after an accepted step, so a
rejected step costs one residual evaluation and one small ``(P, P)`` solve.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from facenormals.core.check import (check_finite, check_flag, check_integer, check_nonnegative, check_positive,
                                    check_shape)
from facenormals.optim.normal_equations import gram

__all__ = ["LMResult", "LMStatus", "levenberg_marquardt"]


class LMStatus(enum.IntEnum):
    """Final state of one batch element of :func:`levenberg_marquardt`."""

    CONVERGED = 0
    """A convergence test (gtol, ftol or xtol) was met."""
    MAX_ITERATIONS = 1
    """The element was still improving when ``max_iterations`` was reached."""
    FAILED = 2
    """The element could not be solved (non-finite residuals or Jacobian, runaway damping, or every
    trial step, however short, leaving the residuals' domain)."""


# Reason codes, used as an integer tensor inside the loop (no host syncs) and turned into strings
# at the end. Code 0 is the default: an element that never stops reaches max_iterations.
_REASONS: tuple[tuple[LMStatus, str], ...] = (
    (LMStatus.MAX_ITERATIONS, "max_iterations reached"),
    (LMStatus.CONVERGED, "gradient norm below gtol"),
    (LMStatus.CONVERGED, "relative cost reduction below ftol"),
    (LMStatus.CONVERGED, "step below xtol"),
    (LMStatus.CONVERGED, "step below floating-point resolution"),
    (LMStatus.FAILED, "non-finite residuals or cost at x0"),
    (LMStatus.FAILED, "non-finite Jacobian"),
    (LMStatus.FAILED, "damping exceeded max_damping"),
    (LMStatus.FAILED, "non-finite residuals at every trial step"),
)
_GTOL, _FTOL, _XTOL, _RESOLUTION, _BAD_X0, _BAD_JACOBIAN, _DAMPING, _BLOCKED = range(1, 9)


@dataclass(repr=False)
class LMResult:
    """Result of :func:`levenberg_marquardt`, one entry per batch element.

    Attributes:
        x: the solution, shape ``(B, P)``; dtype and device of ``x0``.
        cost: :math:`\\tfrac12 \\lVert r(x) \\rVert^2` at ``x``, shape ``(B,)`` (NaN or inf for
            elements whose residuals were not finite at ``x0``).
        initial_cost: the cost at ``x0``, shape ``(B,)``.
        iterations: iterations used by each element (accepted and rejected steps), shape ``(B,)``,
            ``torch.long``.
        status: :class:`LMStatus` values, shape ``(B,)``, ``torch.long``.
        reasons: a human-readable reason for each element's status.
        num_iterations: the number of iterations the batched loop ran.
        damping: the final damping factor λ of each element, shape ``(B,)``.
        residuals: :math:`r(x)` at the solution, shape ``(B, M)`` (what ``residual_fn`` returned
            there; not finite for elements whose residuals were not finite at ``x0``).
    """

    x: Tensor
    cost: Tensor
    initial_cost: Tensor
    iterations: Tensor
    status: Tensor
    reasons: list[str]
    num_iterations: int
    damping: Tensor
    residuals: Tensor

    @property
    def converged(self) -> Tensor:
        """Boolean mask ``(B,)`` of the elements with status :attr:`LMStatus.CONVERGED`."""
        return self.status == LMStatus.CONVERGED

    def _counts(self) -> dict[str, int]:
        status = self.status.tolist()
        return {s.name.lower(): sum(1 for v in status if v == s) for s in LMStatus}

    def __repr__(self) -> str:
        counts = ", ".join(f"{k}={v}" for k, v in self._counts().items())
        cost = self.cost.detach().double().cpu()
        finite = cost[torch.isfinite(cost)]
        cost_str = (
            f"cost mean={finite.mean().item():.6g} max={finite.max().item():.6g}"
            if finite.numel()
            else "cost not finite"
        )
        batch, params = self.x.shape
        return (
            f"LMResult(batch={batch}, params={params}, num_iterations={self.num_iterations}, "
            f"{counts}, {cost_str})"
        )

    def summary(self) -> str:
        """A table with one line per batch element: status, iterations, costs and reason."""
        lines = [repr(self), f"{'b':>4}  {'status':<14} {'iters':>5}  {'initial cost':>13}  "
                 f"{'final cost':>13}  reason"]
        rows = zip(
            self.status.tolist(),
            self.iterations.tolist(),
            self.initial_cost.tolist(),
            self.cost.tolist(),
            self.reasons,
        )
        for b, (status, iters, c0, c1, reason) in enumerate(rows):
            lines.append(
                f"{b:>4}  {LMStatus(status).name:<14} {iters:>5}  {c0:>13.6g}  {c1:>13.6g}  {reason}"
            )
        return "\n".join(lines)


def _check_output(
    value: object, shape: list, name: str, dims: dict[str, int], like: Tensor, other_dtype: torch.dtype | None = None
) -> None:
    if (isinstance(value, Tensor) and value.dtype in (like.dtype, other_dtype) and value.device == like.device
            and all(k in dims for k in shape if isinstance(k, str))
            and value.shape == tuple(dims[k] if isinstance(k, str) else k for k in shape)):
        return  # the common case, every call of a loop: checked without building messages
    check_shape(value, shape, name, dims)
    if value.dtype not in (like.dtype, other_dtype):  # type: ignore[union-attr]
        also = f" or {other_dtype} (jacobian_dtype)" if other_dtype not in (None, like.dtype) else ""
        raise ValueError(f"{name}: expected dtype {like.dtype} (the dtype of x0){also}, got {value.dtype}")  # type: ignore[union-attr]
    if value.device != like.device:
        raise ValueError(
            f"{name}: expected device {like.device} (the device of x0), got {value.device}"
        )


def _check_options(
    max_iterations: int,
    damping: float,
    damping_mode: str,
    ftol: float,
    xtol: float,
    gtol: float,
    min_damping: float,
    max_damping: float,
    jacobian_mode: str,
) -> None:
    check_integer(max_iterations, "max_iterations", minimum=0)
    if damping_mode not in ("marquardt", "levenberg"):
        raise ValueError(f"damping_mode: expected 'marquardt' or 'levenberg', got {damping_mode!r}")
    if jacobian_mode not in ("forward", "reverse"):
        raise ValueError(f"jacobian_mode: expected 'forward' or 'reverse', got {jacobian_mode!r}")
    if isinstance(damping, Tensor) and damping.dim() != 0:  # a 0-d tensor is a number, checked below
        if damping.dim() != 1 or not bool(torch.isfinite(damping).all()) or bool((damping < 0).any()):
            raise ValueError(f"damping: expected a finite number >= 0 or a (B,) tensor of them, got {damping!r}")
        damping = 0.0
    for name, value in (("ftol", ftol), ("xtol", xtol), ("gtol", gtol), ("damping", damping)):
        check_nonnegative(value, name)
    check_positive(min_damping, "min_damping")
    if not check_positive(max_damping, "max_damping") > min_damping:
        raise ValueError(
            f"max_damping: expected a number > min_damping={min_damping!r}, got {max_damping!r}"
        )


def levenberg_marquardt(
    residual_fn: Callable[[Tensor], Tensor],
    x0: Tensor,
    *,
    jacobian_fn: Callable[[Tensor], Tensor] | None = None,
    normal_equations_fn: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]] | None = None,
    max_iterations: int = 100,
    damping: float | Tensor = 1e-3,
    damping_mode: str = "marquardt",
    ftol: float = 1e-10,
    xtol: float = 1e-10,
    gtol: float = 1e-10,
    min_damping: float = 1e-15,
    max_damping: float = 1e15,
    jacobian_mode: str = "forward",
    chunk_size: int | None = None,
    jacobian_dtype: torch.dtype | None = None,
    active_subset: bool = False,
    verbose: bool = False,
) -> LMResult:
    r"""Solve a batch of independent non-linear least-squares problems with Levenberg-Marquardt.

    For every batch element ``b`` this minimises :math:`\tfrac12\lVert r_b(x_b)\rVert^2`. One
    iteration builds :math:`H = J^\top J` and :math:`g = J^\top r` (one batched matrix product),
    solves the damped normal equations :math:`(H + \lambda D)\,\delta = -g` with a batched Cholesky
    factorisation, and evaluates the residuals at :math:`x + \delta`. The step is accepted when the
    gain ratio :math:`\rho = (F(x) - F(x + \delta)) / (L(0) - L(\delta))` of the actual to the
    predicted cost reduction is positive. The damping follows Nielsen's rule: on acceptance
    :math:`\lambda \leftarrow \lambda \max(1/3, 1 - (2\rho - 1)^3)` and :math:`\nu \leftarrow 2`,
    on rejection :math:`\lambda \leftarrow \lambda \nu` and :math:`\nu \leftarrow 2\nu`. A trial
    point with non-finite residuals is rejected (:math:`\rho = -\infty`), so the damping grows.
    The Jacobian is only recomputed after an accepted step.

    Everything is per element: damping, acceptance, convergence and status. An element that
    converged or failed is frozen (its ``x`` no longer changes) while the others continue; the loop
    ends when no element is left or after ``max_iterations`` iterations. An element stops with
    :attr:`LMStatus.CONVERGED` when, in this order of checks,

    - the gradient :math:`\lVert g \rVert_\infty \le` ``gtol`` (at ``x0`` or after an accepted step),
    - a step (accepted or rejected) is small, :math:`\lVert\delta\rVert \le`
      ``xtol`` :math:`(\lVert x\rVert +` ``xtol``:math:`)`, or leaves ``x`` bit-for-bit unchanged
      (below the floating-point resolution, which ends float32 runs near the noise floor), unless
      a trial since the last accepted step had non-finite residuals (see below),
    - an accepted step with :math:`\rho > 1/4` reduces the cost by at most ``ftol`` times the cost,
      or (MINPACK's test, for accepted and rejected steps alike) both the predicted reduction and the
      absolute actual change are at most ``ftol`` times the cost with :math:`\rho \le 2`: near a
      minimum of a slightly noisy or piecewise-smooth cost (a sampled image, a changing mask) the
      steps then stop, instead of being rejected until ``max_iterations`` while the damping grows;

    with :attr:`LMStatus.FAILED` when its residuals (or the cost ½‖r‖²) are not finite at ``x0``,
    its Jacobian is not finite at an accepted point, its damping exceeds ``max_damping``, or its steps
    shrink to nothing while trials since the last accepted step left the residuals' domain (reason
    "non-finite residuals at every trial step": the element is stuck at the edge of the domain
    where its residuals are finite, with the cost still falling beyond it, which is no minimum);
    and with
    :attr:`LMStatus.MAX_ITERATIONS` otherwise. :attr:`LMResult.reasons` says which.

    **Batch independence.** Row ``b`` of ``residual_fn(x)`` must depend on ``x[b]`` only (the
    problems are independent). By default ``residual_fn`` and ``jacobian_fn`` are always called with
    the full batch ``(B, P)`` (frozen rows hold their final values), so they may close over
    per-element data of batch size ``B``. With ``active_subset=True`` they are called as
    ``fn(x[index], index)`` instead, where ``index`` ``(K,)`` (``torch.long``, ascending) lists the
    elements that need a value: all of them at the start, then only the unfinished ones, so that
    elements which stopped early cost nothing while the slowest ones finish. They return the ``K``
    rows of those elements; the results are those of the full evaluation. The autograd Jacobians rely on the independence: forward mode pushes ``P``
    tangents, each one-hot in column ``p`` for *all* batch elements at once, through
    :func:`torch.func.jvp` (vmapped), which yields column ``p`` of every element's Jacobian; reverse
    mode pulls ``M`` one-hot cotangents through the batch-summed residuals with
    :func:`torch.func.jacrev`. Forward mode costs ``P`` tangent passes and suits ``M >> P``;
    reverse mode costs ``M`` backward passes (and an ``(M, M)`` one-hot basis unless
    ``chunk_size`` is set) and suits ``M`` not much larger than ``P``. Both need
    a ``residual_fn`` that :func:`torch.func.vmap` can trace (no ``.item()``, no data-dependent
    Python control flow); pass ``jacobian_fn`` otherwise, or for speed.

    **Damping.** ``"marquardt"`` scales the damping by the curvature of each parameter,
    :math:`D = \operatorname{diag}(\max(d, \epsilon \max_j d_j))`, where :math:`d` is the running
    maximum of :math:`\operatorname{diag}(J^\top J)` over the accepted points (Moré's scaling, as in
    MINPACK: a parameter whose column shrinks near a point keeps its damping; on Rosenbrock's valley
    from the classic start (−1.2, 1) it takes 20 iterations where the plain
    :math:`\operatorname{diag}(J^\top J)` takes 33, but from far starts such as (100, −100) both
    crawl, 123 and 88 iterations, where ``"levenberg"`` takes 8 and scipy's MINPACK ``lm`` 4
    evaluations). The damping is invariant to the units of the parameters, and a parameter with a
    zero Jacobian column gets a tiny positive damping and a zero step. ``"levenberg"`` uses
    :math:`D = I`. Where the
    Cholesky factorisation of :math:`H + \lambda D` fails, that element's step is computed with the
    pseudo-inverse (:func:`torch.linalg.pinv`, hermitian) instead and judged by its gain ratio like
    any other step; a bad step is rejected and raises the damping. No element can crash the batch
    through the solver: an element with non-finite residuals or Jacobian stops (``FAILED``) and the
    others go on. Without ``active_subset`` the user's functions are called for every element,
    including those stopped as non-finite, so a function that refuses non-finite values (such as
    :func:`normal_equations`, which raises) fails the whole call there; with ``active_subset=True``
    they are called only for the elements still being solved.

    The solver runs under :func:`torch.no_grad`: the result is not differentiable with respect to
    ``x0`` or tensors captured by ``residual_fn``. The loop synchronises with the device about
    twice per iteration (termination and the rare Cholesky fallback test).

    Args:
        residual_fn: maps ``x`` of shape ``(B, P)`` to residuals of shape ``(B, M)`` with the dtype
            and device of ``x0``; row ``b`` may depend only on ``x[b]``.
        x0: the starting points, a finite float32 or float64 tensor of shape ``(B, P)``. Dtype and device of
            all computations and results follow it.
        jacobian_fn: optional analytic Jacobian, mapping ``x`` ``(B, P)`` to
            :math:`\partial r / \partial x` of shape ``(B, M, P)``. Autograd is used without it.
        normal_equations_fn: instead of ``jacobian_fn``, a function mapping ``x`` ``(B, P)`` and
            its residuals ``r`` ``(B, M)`` to :math:`J^\top J` ``(B, P, P)`` and :math:`J^\top r`
            ``(B, P)`` (in the dtype of ``x0`` or ``jacobian_dtype``), for problems that form them
            cheaper than :math:`J` (e.g. without its zero blocks). With ``active_subset`` it is
            called as ``fn(x[index], r[index], index)``.
        max_iterations: the maximum number of iterations (accepted or rejected steps).
        damping: the initial damping factor λ (``0`` makes the first step Gauss-Newton), or one per
            element ``(B,)``, e.g. :attr:`LMResult.damping` of a previous solve to warm-start it.
        damping_mode: ``"marquardt"`` (scaled by ``diag(JᵀJ)``, see above) or ``"levenberg"``
            (identity).
        ftol: relative cost reduction tolerance.
        xtol: relative step size tolerance, against ``‖x‖`` as in scipy's ``trf`` (so not invariant
            to the parameters' units: next to a parameter of 1e8 every step below ~0.01 counts as
            small, and a fit of a 1e-3 parameter then stops short, reported converged; give the
            parameters comparable magnitudes, or ``xtol=0`` to stop on ``ftol``/``gtol`` alone).
        gtol: absolute tolerance on the gradient's infinity norm.
        min_damping: lower bound of λ after an update (must be > 0).
        max_damping: an element whose λ grows beyond this fails.
        jacobian_mode: ``"forward"`` or ``"reverse"`` autograd, ignored with ``jacobian_fn``.
        chunk_size: optional chunk size of the vmapped autograd Jacobian (bounds its memory).
        jacobian_dtype: dtype in which :math:`J^\top J` and :math:`J^\top r` are formed (default:
            the dtype of ``x0``); ``jacobian_fn`` may return this dtype directly. ``torch.float32``
            on a float64 problem makes the normal equations about 3× cheaper on a CPU. The
            residuals, costs, gain ratios and the solve stay in the dtype of ``x0``, so steps are
            inexact Gauss-Newton steps that still converge to the float64 optimum (with float32 the
            final cost agrees to far better than 1e-6 relative, ``x`` to about 1e-6; ``bfloat16``,
            8 bits of mantissa, leaves ~1e-7 in the cost and ~3e-5 in ``x``).
        active_subset: call ``residual_fn`` and ``jacobian_fn`` as ``fn(x[index], index)`` on the
            elements that need them only (see *Batch independence*).
        verbose: print one line per iteration (iteration, mean cost, active elements).

    Returns:
        An :class:`LMResult`.

    Raises:
        ValueError: if ``x0`` is not a finite floating tensor of shape ``(B, P)`` with ``B, P >= 1``,
            if ``residual_fn`` or ``jacobian_fn`` return a wrong shape, dtype or device, or on
            invalid options.

    Shape:
        - x0: :math:`(B, P)`
        - residual_fn output: :math:`(B, M)`
        - jacobian_fn output: :math:`(B, M, P)`

    Example:
        A batch of two linear least-squares problems ``A x ≈ b_k``:

        >>> A = torch.tensor([[1.0, 0.0], [0.0, 2.0], [1.0, 1.0]], dtype=torch.float64)
        >>> b = torch.tensor([[1.0, 2.0, 3.0], [0.0, 1.0, -1.0]], dtype=torch.float64)
        >>> result = levenberg_marquardt(lambda x: x @ A.T - b, torch.zeros(2, 2, dtype=torch.float64))
        >>> torch.allclose(result.x, torch.linalg.lstsq(A, b.T).solution.T)
        True
        >>> print(*(LMStatus(s).name for s in result.status.tolist()))
        CONVERGED CONVERGED
    """
    _check_options(
        max_iterations, damping, damping_mode, ftol, xtol, gtol, min_damping, max_damping,
        jacobian_mode,
    )
    if not callable(residual_fn):
        raise ValueError(f"residual_fn: expected a callable, got {type(residual_fn).__name__}")
    for name, fn in (("jacobian_fn", jacobian_fn), ("normal_equations_fn", normal_equations_fn)):
        if fn is not None and not callable(fn):
            raise ValueError(f"{name}: expected a callable, got {type(fn).__name__}")
    if jacobian_fn is not None and normal_equations_fn is not None:
        raise ValueError("normal_equations_fn: expected at most one of jacobian_fn and normal_equations_fn")
    dims = check_shape(x0, ["B", "P"], "x0")
    if x0.dtype not in (torch.float32, torch.float64):  # the batched Cholesky needs them
        raise ValueError(f"x0: expected a float32 or float64 tensor, got dtype {x0.dtype}")
    if dims["B"] < 1 or dims["P"] < 1:
        raise ValueError(f"x0: expected at least one batch element and one parameter, got {tuple(x0.shape)}")
    check_finite(x0, "x0")
    if chunk_size is not None:
        chunk_size = check_integer(chunk_size, "chunk_size", minimum=1)
    active_subset, verbose = check_flag(active_subset, "active_subset"), check_flag(verbose, "verbose")
    if isinstance(damping, Tensor) and damping.dim() == 0:  # checked by _check_options as a number
        damping = float(damping)
    if jacobian_dtype is not None and not (isinstance(jacobian_dtype, torch.dtype) and jacobian_dtype.is_floating_point):
        raise ValueError(f"jacobian_dtype: expected a floating torch.dtype or None, got {jacobian_dtype!r}")
    with torch.no_grad():
        return _solve(
            residual_fn, x0.detach().clone(), jacobian_fn, normal_equations_fn, max_iterations, damping,
            damping_mode == "marquardt", ftol, xtol, gtol, min_damping, max_damping,
            jacobian_mode, chunk_size, verbose, jacobian_dtype, active_subset,
        )


def _solve(
    residual_fn: Callable[[Tensor], Tensor],
    x: Tensor,
    jacobian_fn: Callable[[Tensor], Tensor] | None,
    normal_equations_fn: Callable[..., tuple[Tensor, Tensor]] | None,
    max_iterations: int,
    damping: float | Tensor,
    marquardt: bool,
    ftol: float,
    xtol: float,
    gtol: float,
    min_damping: float,
    max_damping: float,
    jacobian_mode: str,
    chunk_size: int | None,
    verbose: bool,
    jacobian_dtype: torch.dtype | None,
    active_subset: bool,
) -> LMResult:
    B, P = x.shape
    dtype, device = x.dtype, x.device
    jacobian_dtype = dtype if jacobian_dtype is None else jacobian_dtype
    info_ = torch.finfo(dtype)
    dims: dict[str, int] = {"B": B, "P": P}

    everyone = torch.arange(B, device=device)

    def residuals(x_: Tensor, index: Tensor) -> Tensor:
        """Residuals of the elements ``index`` (all rows without ``active_subset``)."""
        if active_subset:
            r_ = residual_fn(x_[index], index)
            _check_output(r_, [index.shape[0], "M"], "residual_fn output", dims, x)
        else:
            r_ = residual_fn(x_)
            _check_output(r_, ["B", "M"], "residual_fn output", dims, x)
        return r_

    def normal_equations(x_: Tensor, r_: Tensor, index: Tensor) -> tuple[Tensor, Tensor]:
        """``JᵀJ`` and ``Jᵀr`` of the elements ``index`` (all rows without ``active_subset``)."""
        if active_subset:
            x_, r_ = x_[index], r_[index]
            fn = lambda z: residual_fn(z, index)  # noqa: E731
        else:
            fn = residual_fn
        count = x_.shape[0]
        if normal_equations_fn is not None:
            hessian, gradient = normal_equations_fn(x_, r_, index) if active_subset else normal_equations_fn(x_, r_)
            _check_output(hessian, [count, "P", "P"], "normal_equations_fn output", dims, x, jacobian_dtype)
            _check_output(gradient, [count, "P"], "normal_equations_fn output", dims, x, jacobian_dtype)
            return hessian.to(dtype), gradient.to(dtype)
        if jacobian_fn is not None:
            jac = jacobian_fn(x_, index) if active_subset else jacobian_fn(x_)
            _check_output(jac, [count, "M", "P"], "jacobian_fn output", dims, x, jacobian_dtype)
        elif jacobian_mode == "forward":
            # P tangents, one-hot in column p for all batch elements at once: (P, B, M) -> (B, M, P).
            def column(tangent: Tensor) -> Tensor:
                return torch.func.jvp(fn, (x_,), (tangent.expand(count, P),))[1]

            jac = torch.func.vmap(column, chunk_size=chunk_size)(eye).permute(1, 2, 0)
        else:
            # M cotangents through the batch-summed residuals: (M, B, P) -> (B, M, P).
            jac = torch.func.jacrev(lambda z: fn(z).sum(0), chunk_size=chunk_size)(x_)
            jac = jac.permute(1, 0, 2)
        jac = jac.to(jacobian_dtype)  # its shape, dtype and device are checked
        gradient = (r_.to(jacobian_dtype).unsqueeze(1) @ jac).squeeze(1)  # rᵀJ: reads J in its own layout
        return gram(jac).to(dtype), gradient.to(dtype)

    def half_sq(r_: Tensor) -> Tensor:
        return 0.5 * r_.square().sum(-1)

    code = torch.zeros(B, dtype=torch.long, device=device)
    edge = torch.zeros(B, dtype=torch.bool, device=device)  # rejected for non-finite residuals since the last accepted step

    def stop(active_: Tensor, *tests: tuple[Tensor, int]) -> Tensor:
        """Record for each active element the reason of the first of the ``(mask, reason)`` tests
        that holds for it; return the new active mask."""
        nonlocal code
        mask, reason = tests[-1]
        first = torch.where(mask, reason, 0)
        for mask, reason in reversed(tests[:-1]):
            first = torch.where(mask, reason, first)
        hit = active_ & (first > 0)
        code = torch.where(hit, first, code)
        return active_ & ~hit

    r = residuals(x, everyone)
    cost = half_sq(r)
    initial_cost = cost.clone()
    active = torch.isfinite(cost)
    code = torch.where(active, code, _BAD_X0)
    if isinstance(damping, Tensor):
        lam = damping.detach().to(dtype=dtype, device=device).clone()
        check_shape(lam, [B], "damping")
    else:
        lam = torch.full((B,), float(damping), dtype=dtype, device=device)
    nu = torch.full((B,), 2.0, dtype=dtype, device=device)
    iterations = torch.zeros(B, dtype=torch.long, device=device)
    eye = torch.eye(P, dtype=dtype, device=device)

    def damping_scale(diag_max_: Tensor) -> Tensor:
        """The damping matrix's diagonal D (see the docstring); inactive elements ignore it."""
        if not marquardt:
            return torch.ones_like(diag_max_)
        floor = (info_.eps * diag_max_.amax(-1, keepdim=True)).clamp_min(info_.tiny)
        return torch.maximum(diag_max_, floor)

    if active_subset and not bool(active.all()):  # elements bad at x0 are not evaluated (a strict fn raises there)
        H = torch.full((B, P, P), float("nan"), dtype=dtype, device=device)
        g = torch.full((B, P), float("nan"), dtype=dtype, device=device)
        index = active.nonzero().squeeze(1)
        if index.numel():
            H_new, g_new = normal_equations(x, r, index)
            H, g = H.index_copy(0, index, H_new), g.index_copy(0, index, g_new)
    else:
        H, g = normal_equations(x, r, everyone)
    finite_jac = torch.isfinite(H).all(-1).all(-1) & torch.isfinite(g).all(-1)
    active = stop(active, (~finite_jac, _BAD_JACOBIAN), (g.abs().amax(-1) <= gtol, _GTOL))
    # Marquardt scaling: the running maximum of diag(JᵀJ) over the accepted points (Moré 1978).
    diag_max = H.diagonal(dim1=-2, dim2=-1).clone()
    scale = damping_scale(diag_max)

    num_iterations = 0
    any_active = bool(active.any())
    while any_active and num_iterations < max_iterations:
        num_iterations += 1
        iterations += active.long()
        act = active[:, None]

        # Damped normal equations; inactive elements solve I δ = -g (always factorisable), and their
        # step, predicted reduction and trial are discarded below.
        lam_d = lam[:, None] * scale
        A = torch.where(active[:, None, None], H + torch.diag_embed(lam_d), eye)
        rhs = -g
        L, info = torch.linalg.cholesky_ex(A)
        step = torch.cholesky_solve(rhs.unsqueeze(-1), L).squeeze(-1)
        # L(0) - L(δ) = ½ δᵀ(λDδ - g) for the exact solution of the damped system.
        pred = 0.5 * (step * (lam_d * step + rhs)).sum(-1)
        if bool(info.any()):  # inactive elements have A = I, which always factorises
            idx = (active & (info != 0)).nonzero().squeeze(1)
            A_bad, rhs_bad, H_bad = A[idx], rhs[idx], H[idx]
            try:
                step_bad = torch.matmul(torch.linalg.pinv(A_bad, hermitian=True), rhs_bad.unsqueeze(-1))
                step_bad = step_bad.squeeze(-1)
            except RuntimeError:
                step_bad = torch.full_like(rhs_bad, float("nan"))
            # Predicted reduction -(δᵀg + ½ δᵀHδ), computed directly since δ may not solve A δ = -g.
            quad = (step_bad.unsqueeze(-2) @ H_bad @ step_bad.unsqueeze(-1)).reshape(-1)
            pred_bad = (step_bad * rhs_bad).sum(-1) - 0.5 * quad
            step = step.index_copy(0, idx, step_bad)
            pred = pred.index_copy(0, idx, pred_bad)
        step = torch.where(act, step, 0.0)  # an inactive element's -g may be NaN: it never reaches x_trial

        # A non-finite step is rejected below; the residuals are evaluated at x instead, so that
        # residual functions that check their inputs (the library's ops do) never see NaN.
        finite_step = torch.isfinite(step).all(-1)
        x_trial = torch.where(finite_step[:, None], x + step, x)
        if active_subset:  # the others keep their residuals (their trial is discarded anyway)
            index = active.nonzero().squeeze(1)
            r_trial = r.index_copy(0, index, residuals(x_trial, index))
        else:
            r_trial = residuals(x_trial, everyone)
        cost_trial = half_sq(r_trial)
        actual = cost - cost_trial
        trial_ok = active & torch.isfinite(cost_trial) & finite_step & torch.isfinite(pred)
        rho = torch.where(trial_ok, actual / pred.clamp_min(info_.tiny), -math.inf)
        accepted = trial_ok & (rho > 0)
        rejected = active & ~accepted

        # Convergence tests on this step.
        # A step shrunk to nothing by rejections at the edge of the residuals' domain (non-finite
        # trials since the last accepted step) shows no minimum: that is reported as blocked.
        edge = torch.where(accepted, False, edge | (active & ~trial_ok))
        small_step = torch.linalg.vector_norm(step, dim=-1) <= xtol * (torch.linalg.vector_norm(x, dim=-1) + xtol)
        no_move = (x_trial == x).all(-1)
        tiny = ftol * cost
        small_reduction = accepted & (actual <= tiny) & (rho > 0.25)
        # MINPACK (lmder): predicted and actual relative changes both within ftol, rho <= 2.
        small_reduction |= trial_ok & (actual.abs() <= tiny) & (pred <= tiny) & (rho <= 2.0)

        # Accept.
        x = torch.where(accepted[:, None], x_trial, x)
        r = torch.where(accepted[:, None], r_trial, r)
        cost = torch.where(accepted, cost_trial, cost)

        # Nielsen's damping update.
        shrink = torch.clamp_min(1.0 - (2.0 * rho - 1.0) ** 3, 1.0 / 3.0)
        lam = torch.where(accepted, (lam * shrink).clamp_min(min_damping), lam)
        lam = torch.where(rejected, lam.clamp_min(min_damping) * nu, lam)
        nu = torch.where(accepted, 2.0, torch.where(rejected, 2.0 * nu, nu))

        runaway = rejected & ~(lam <= max_damping)
        active = stop(active, ((small_step | no_move) & edge, _BLOCKED), (small_step, _XTOL), (no_move, _RESOLUTION),
                      (small_reduction, _FTOL), (runaway & edge, _BLOCKED), (runaway, _DAMPING))

        need_jacobian = accepted & active
        flags = torch.stack([need_jacobian.any(), active.any()]).tolist()
        if flags[0]:
            if active_subset:
                index = need_jacobian.nonzero().squeeze(1)
                H_new, g_new = normal_equations(x, r, index)
                H, g = H.index_copy(0, index, H_new), g.index_copy(0, index, g_new)
            else:
                H_new, g_new = normal_equations(x, r, everyone)
                H = torch.where(need_jacobian[:, None, None], H_new, H)
                g = torch.where(need_jacobian[:, None], g_new, g)
            diag_max = torch.maximum(diag_max, H.diagonal(dim1=-2, dim2=-1))
            scale = damping_scale(diag_max)
            finite_jac = torch.isfinite(H).all(-1).all(-1) & torch.isfinite(g).all(-1)
            active = stop(active, (need_jacobian & ~finite_jac, _BAD_JACOBIAN),
                          (need_jacobian & (g.abs().amax(-1) <= gtol), _GTOL))
            flags[1] = bool(active.any())
        any_active = flags[1]
        if verbose:
            finite_cost = cost[torch.isfinite(cost)]
            mean = finite_cost.mean().item() if finite_cost.numel() else float("nan")
            print(
                f"levenberg_marquardt: iteration {num_iterations:4d}  mean cost {mean:.6e}  "
                f"active {int(active.sum())}/{B}"
            )

    codes = code.tolist()
    return LMResult(
        x=x,
        cost=cost,
        initial_cost=initial_cost,
        iterations=iterations,
        status=torch.tensor([int(_REASONS[c][0]) for c in codes], dtype=torch.long, device=device),
        reasons=[_REASONS[c][1] for c in codes],
        num_iterations=num_iterations,
        damping=lam,
        residuals=r,
    )
