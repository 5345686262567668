"""Batched LM vs scipy.optimize.least_squares on the head-sized problem, measured in one run.

The problem: the ICT head (11,248 vertices) with 100 shape + 6 pose parameters, fitted to the
2D projections of a random head (22,496 pixel residuals) plus the shape prior (100 residuals).
Both solvers get the same analytic Jacobian (torch for ours, numpy for scipy) and the same start.
Every solver is warmed up once, then the solvers run in turn ``--repeats`` times (medians), so that
load on the machine hits them alike. ``--threads N`` sets torch's threads *and* the BLAS/OpenMP pools
before the libraries load: like for like is ``--threads 1`` (with two threads torch uses both cores
while scipy's solver does not get faster).

    python benchmarks/bench_lm_head.py [--threads 1] [--repeats 5] [--batch 16] [--model ict]
"""

from __future__ import annotations

import argparse
import os
import platform

from _threads import add_threads_argument, pin_threads
from _timing import interleaved


def arguments() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5, help="interleaved runs of each solver")
    parser.add_argument("--batch", type=int, default=16, help="batch size of the batched-throughput run")
    parser.add_argument("--model", default="ict")
    add_threads_argument(parser)
    args = parser.parse_args()
    pin_threads(args)  # before numpy, scipy and torch create their thread pools
    return args


ARGS = arguments() if __name__ == "__main__" else None

import numpy as np  # noqa: E402
import scipy  # noqa: E402
import torch  # noqa: E402
from scipy.optimize import OptimizeResult, least_squares  # noqa: E402

from facenormals.geometry import (  # noqa: E402
    euler_rotation_derivatives,
    euler_to_rotation_matrix,
    project_points,
    projection_jacobian,
)
from facenormals.models import load_model  # noqa: E402
from facenormals.optim import levenberg_marquardt  # noqa: E402

PRIOR_WEIGHT = 0.4


class HeadProblem:
    """Residuals and analytic Jacobian of the projected-vertices fit, in torch and in numpy."""

    def __init__(self, model, batch: int, seed: int = 0, dtype=torch.float64, jacobian_dtype=None):
        g = torch.Generator().manual_seed(seed)
        self.model = model.to(dtype)
        self.K = model.num_shape
        self.jacobian_dtype = jacobian_dtype or dtype
        self.W = self.model.shape_basis.permute(1, 2, 0).contiguous()  # (N, 3, K)
        self.W_jac = self.W.to(self.jacobian_dtype)
        self.sqrt_w = PRIOR_WEIGHT**0.5
        self.intrinsics = torch.tensor([[300.0, 63.5, 63.5]], dtype=dtype).expand(batch, 3)
        y = self.model.sample_shape_coeffs(batch, generator=g)
        angles = (torch.rand(batch, 3, generator=g, dtype=dtype) * 2 - 1) * torch.tensor([0.1, 0.2, 0.5], dtype=dtype)
        R = euler_to_rotation_matrix(angles)
        t = (R.transpose(1, 2) @ torch.tensor([0.0, 0.0, 600.0], dtype=dtype))
        target, _ = project_points(self.model(y), R, t, self.intrinsics)
        self.target = target + 0.3 * torch.randn(target.shape, generator=g, dtype=dtype)
        x0 = torch.zeros(batch, self.K + 6, dtype=dtype)
        x0[:, self.K : self.K + 3] = angles + 0.08 * torch.randn(batch, 3, generator=g, dtype=dtype)
        x0[:, self.K + 3 :] = t + 10.0 * torch.randn(batch, 3, generator=g, dtype=dtype)
        self.x0 = x0

    def element(self, b: int) -> "HeadProblem":
        """Element ``b`` of the batch as a problem of its own (the same target and start)."""
        one = object.__new__(HeadProblem)
        one.__dict__.update(self.__dict__)
        one.intrinsics, one.target, one.x0 = self.intrinsics[b : b + 1], self.target[b : b + 1], self.x0[b : b + 1]
        return one

    def residuals(self, x: torch.Tensor) -> torch.Tensor:
        y, angles, t = x[:, : self.K], x[:, self.K : self.K + 3], x[:, self.K + 3 :]
        uv, _ = project_points(self.model(y), euler_to_rotation_matrix(angles), t, self.intrinsics[: x.shape[0]])
        prior = self.sqrt_w * y / self.model.shape_std
        return torch.cat([(uv - self.target[: x.shape[0]]).flatten(1), prior], dim=1)

    def jacobian(self, x: torch.Tensor) -> torch.Tensor:
        B, K = x.shape[0], self.K
        y, angles, t = x[:, :K], x[:, K : K + 3], x[:, K + 3 :]
        R = euler_to_rotation_matrix(angles)
        D = euler_rotation_derivatives(angles)  # (B, 3, 3, 3)
        Q = self.model(y) + t[:, None, :]  # p + t, (B, N, 3)
        P = projection_jacobian(Q @ R.transpose(1, 2), self.intrinsics[:B])  # (B, N, 2, 3)
        PR = P @ R[:, None]  # d uv / d (p + t), (B, N, 2, 3)
        N = Q.shape[1]
        J = x.new_empty(B, 2 * N + K, K + 6, dtype=self.jacobian_dtype)
        J_pix = J[:, : 2 * N].view(B, N, 2, K + 6)
        # d uv / d y = PR · W_n, as broadcast multiply-adds written in place rather than N tiny matmuls.
        J_y = J_pix[..., :K]
        PR_j = PR.to(self.jacobian_dtype)
        torch.mul(PR_j[..., 0:1], self.W_jac[None, :, None, 0, :], out=J_y)
        for k in (1, 2):
            J_y.addcmul_(PR_j[..., k : k + 1], self.W_jac[None, :, None, k, :])
        DQ = torch.einsum("bjkl,bnl->bnkj", D, Q)  # (B, N, 3, 3): column j is D_j (p + t)
        J_pix[..., K : K + 3] = P @ DQ
        J_pix[..., K + 3 :] = PR
        J[:, 2 * N :] = 0.0
        J[:, 2 * N :, :K] = torch.diag(self.sqrt_w / self.model.shape_std)
        return J


def numpy_problem(problem: HeadProblem, b: int):
    """The same residuals and Jacobian written in numpy for scipy (element ``b`` of the batch)."""
    mean = problem.model.mean.numpy()
    basis = problem.model.shape_basis.numpy().reshape(problem.K, -1)
    W = problem.W.numpy()
    std = problem.model.shape_std.numpy()
    f, u0, v0 = problem.intrinsics[b].numpy()
    target = problem.target[b].numpy()
    K, w = problem.K, problem.sqrt_w

    def rot(angles):
        return euler_to_rotation_matrix(torch.from_numpy(angles)[None])[0].numpy()

    def drot(angles):
        return euler_rotation_derivatives(torch.from_numpy(angles)[None])[0].numpy()

    def fun(x):
        Q = mean + (x[:K] @ basis).reshape(-1, 3) + x[K + 3 :]
        C = Q @ rot(x[K : K + 3]).T
        uv = f * C[:, :2] / C[:, 2:3] + np.array([u0, v0])
        return np.concatenate([(uv - target).ravel(), w * x[:K] / std])

    def jac(x):
        R, D = rot(x[K : K + 3]), drot(x[K : K + 3])
        Q = mean + (x[:K] @ basis).reshape(-1, 3) + x[K + 3 :]
        C = Q @ R.T
        z = C[:, 2]
        P = np.zeros((len(C), 2, 3))
        P[:, 0, 0] = P[:, 1, 1] = f / z
        P[:, 0, 2] = -f * C[:, 0] / z**2
        P[:, 1, 2] = -f * C[:, 1] / z**2
        PR = P @ R
        J_y = np.einsum("nik,nkq->niq", PR, W)
        J_a = np.einsum("nik,jkl,nl->nij", P, D, Q)
        J = np.concatenate([J_y, J_a, PR], axis=-1).reshape(-1, K + 6)
        J_prior = np.zeros((K, K + 6))
        J_prior[:, :K] = np.diag(w / std)
        return np.concatenate([J, J_prior])

    return fun, jac


def _cost_and_count(result) -> tuple[float, int]:
    """Final cost and iterations of our LMResult (batch of one), or cost and nfev of SciPy's result."""
    if isinstance(result, OptimizeResult):
        return float(result.cost), int(result.nfev)
    return float(result.cost[0]), int(result.iterations[0])


def main(args: argparse.Namespace) -> None:
    torch.manual_seed(0)
    model = load_model(args.model, dtype=torch.float64)
    problem = HeadProblem(model, batch=1)
    x0 = problem.x0
    print(f"machine: {platform.machine()} {platform.processor() or ''}, torch {torch.__version__} "
          f"({torch.get_num_threads()} threads; OMP/BLAS {os.environ.get('OMP_NUM_THREADS', 'default')}), "
          f"scipy {scipy.__version__}")
    print(f"problem: {model.name}, {model.num_vertices} vertices, P = {x0.shape[1]}, "
          f"M = {problem.residuals(x0).shape[1]}")

    J_auto = torch.func.jacfwd(lambda z: problem.residuals(z[None])[0])(x0[0])
    J_err = float((problem.jacobian(x0)[0] - J_auto).abs().max() / J_auto.abs().max())
    print(f"analytic vs autograd Jacobian: max relative difference {J_err:.1e}")

    def ours(prob, jacobian_dtype=None):
        return levenberg_marquardt(
            prob.residuals, prob.x0, jacobian_fn=prob.jacobian, max_iterations=50, ftol=1e-8, xtol=1e-8,
            damping=1e-5, jacobian_dtype=jacobian_dtype,
        )

    problem32 = HeadProblem(model, batch=1, jacobian_dtype=torch.float32)
    fun, jac = numpy_problem(problem, 0)
    x0_np = x0[0].numpy()
    results = interleaved({
        "facenormals LM, float64 J": lambda: ours(problem),
        "facenormals LM, float32 J (jacobian_dtype)": lambda: ours(problem32, torch.float32),
        "scipy least_squares method='trf'": lambda: least_squares(fun, x0_np, jac=jac, method="trf"),
        "scipy least_squares method='lm'": lambda: least_squares(fun, x0_np, jac=jac, method="lm"),
    }, args.repeats, warm_up=True)
    rows = [(name, t, *_cost_and_count(out)) for name, (t, out) in results.items()]
    t_trf = rows[2][1]
    print()
    print(f"{args.repeats} interleaved runs after a warm-up, medians:")
    print("| solver | median time (ms) | final cost | iterations / nfev | SciPy `trf` / this |")
    print("|---|---|---|---|---|")
    for name, t, cost, it in rows:
        print(f"| {name} | {t * 1e3:.1f} | {cost:.6f} | {it} | {t_trf / t:.1f}x |")
    for name, t, cost, _ in rows[:2]:
        for sname, st, scost, _ in rows[2:]:
            print(f"{name} vs {sname}: speed-up {st / t:.1f}x, relative cost difference {abs(cost - scost) / scost:.1e}")

    batch = HeadProblem(model, batch=args.batch, seed=1, jacobian_dtype=torch.float32)  # as the float32 row above
    elements = [batch.element(b) for b in range(args.batch)]
    timing = interleaved({
        "batch": lambda: ours(batch, torch.float32),
        "one at a time": lambda: [ours(one, torch.float32) for one in elements],
    }, max(3, args.repeats // 2), warm_up=True)  # at least 3: the median of 2 runs is their mean
    t_batch, res_b = timing["batch"]
    t_seq, _ = timing["one at a time"]
    iterations = res_b.iterations.float()
    print(f"batched (float32 J, damping 1e-5): B={args.batch} in {t_batch * 1e3:.0f} ms = "
          f"{t_batch / args.batch * 1e3:.1f} ms per problem ({res_b.converged.sum().item()}/{args.batch} converged; "
          f"iterations per element {int(iterations.min())}-{int(iterations.max())}, mean {float(iterations.mean()):.1f}); "
          f"the same problems one at a time: {t_seq / args.batch * 1e3:.1f} ms per problem; "
          f"throughput batch / one at a time {t_seq / t_batch:.2f}x")


if __name__ == "__main__":
    main(ARGS)
