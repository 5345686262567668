"""Speed of the fitting recipe on the ICT head at 128x128 (100 shape + 9 view parameters).

1. landmark pre-alignment (SQPnP start + LM), median over random poses;
2. the full single-view fit including pre-alignment, median over random heads;
3. one LM round on fixed visibility: ours vs scipy.optimize.least_squares on the *same* residuals
   and analytic Jacobian, in the same run, to their stopping tests (``ftol = xtol = 1e-8``) and to
   within 1e-4 of the lowest energy any of them reached (relative; fit_head's rounds stop at 3e-2).
   The float32 residuals resolve the energy only to ~1e-5 relative, so the iterations below that,
   which decide when each solver stops, are rounding noise: one rounding change in the Jacobian
   took our round from 33 to 49 iterations, ending at the same energy;
4. B = 16 subjects fitted as one batch vs 16 sequential fits.

    python benchmarks/bench_fit.py [--heads 10] [--model ict] [--batch 16] [--threads 1] [--blas-threads 1]
                                   [--repeats 5]

Timings are medians; the solvers compared with each other run interleaved, ``--repeats`` times
each, so that load on the machine hits them alike. ``--threads N`` sets torch's threads *and* the
BLAS/OpenMP pools that numpy and scipy use (set before they load): scipy's solver calls the same
torch residuals, and two thread pools on two cores fight. On a machine shared with other
CPU-heavy jobs, ``--threads 1`` avoids threads spinning against them. ``--blas-threads 1`` pins only
numpy's and scipy's OpenBLAS (torch computes with its own MKL and OpenMP): at two threads scipy's
idle OpenBLAS threads otherwise slow the torch residuals it calls, a cost our solver never pays, so
the scipy ratio is judged on the faster of the two scipy configurations.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

from _threads import add_threads_argument, pin_threads
from _timing import interleaved


def arguments() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--heads", type=int, default=10)
    parser.add_argument("--model", default="ict")
    parser.add_argument("--batch", type=int, default=16)
    add_threads_argument(parser)
    parser.add_argument("--blas-threads", type=int, default=None,
                        help="OpenBLAS threads of numpy and scipy alone (torch uses its own MKL pool); 1 keeps "
                             "scipy's idle BLAS threads from spinning against torch's in its residual calls")
    parser.add_argument("--repeats", type=int, default=5, help="interleaved runs of each compared solver")
    args = parser.parse_args()
    pin_threads(args)  # before numpy, scipy and torch create their thread pools
    if args.blas_threads:
        os.environ["OPENBLAS_NUM_THREADS"] = str(args.blas_threads)
    return args


ARGS = arguments() if __name__ == "__main__" else None

import torch  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

from facenormals.fitting import HeadFitProblem, fit_head, prealign_pose  # noqa: E402
from facenormals.fitting.oracle import render_oracle_views  # noqa: E402
from facenormals.models import load_model  # noqa: E402
from facenormals.optim import levenberg_marquardt  # noqa: E402

#: relative energy tolerance of the time-to-target comparison, ~10x the float32 residuals' resolution here
TARGET_TOLERANCE = 1e-4


def timed(fn):
    start = time.perf_counter()
    out = fn()
    return time.perf_counter() - start, out


def main(args: argparse.Namespace) -> None:
    if args.threads:
        torch.set_num_threads(args.threads)
    model = load_model(args.model, dtype=torch.float32)
    blas = os.environ.get("OPENBLAS_NUM_THREADS", "library default")  # numpy's and scipy's OpenBLAS
    print(f"machine: {platform.machine()}, torch {torch.__version__} ({torch.get_num_threads()} threads, BLAS {blas}); "
          f"model {model.name}: {model.num_vertices} vertices, {model.num_shape} shape components")
    g = torch.Generator().manual_seed(0)
    heads = []
    for _ in range(max(args.heads, args.batch)):
        yaw = float((torch.rand(1, generator=g) * 2 - 1) * 30.0)
        heads.append(render_oracle_views(model, model.sample_shape_coeffs(1, generator=g), [yaw]))
    rows = []

    # 1. Pre-alignment.
    points, normals = model.mean[model.landmark_indices], model.landmark_normals()
    pre = [timed(lambda h=h: prealign_pose(h.landmarks[0], points, h.intrinsics[0], model_normals=normals))[0]
           for h in heads[: args.heads] * 3]
    rows.append(("landmark pre-alignment (6 DoF LM from SQPnP, facing test)", statistics.median(pre) * 1e3, "<= 5"))
    robust = [timed(lambda h=h: prealign_pose(h.landmarks[0], points, h.intrinsics[0], robust_scale=3.0,
                                              model_normals=normals))[0]
              for h in heads[: args.heads] * 3]
    rows.append(("  as fit_head runs it: plus up to 2 Cauchy-reweighted re-solves", statistics.median(robust) * 1e3,
                 "<= 5"))

    # 2. Full fits.
    fit_head(heads[0].normal_maps, heads[0].landmarks, model, intrinsics=heads[0].intrinsics)  # warm-up
    fits = [timed(lambda h=h: fit_head(h.normal_maps, h.landmarks, model, intrinsics=h.intrinsics))
            for h in heads[: args.heads] * 2]
    rows.append(("single-view fit incl. pre-alignment", statistics.median(t for t, _ in fits) * 1e3, "<= 150"))
    iterations = statistics.median(int(r.iterations[0]) for _, r in fits)

    # 3. One LM round on fixed visibility, ours vs scipy, same residuals and Jacobian.
    h = heads[0]
    pose = prealign_pose(h.landmarks[0], points, h.intrinsics[0])
    problem = HeadFitProblem(model, h.normal_maps, h.landmarks, h.landmark_mask, h.intrinsics)
    x0 = problem.pack(torch.zeros(1, model.num_shape), pose.angles[None], pose.translation[None], h.intrinsics)
    problem.update_visibility(x0, min_facing=0.2)
    problem.update_robust_weights(x0, 0.1, landmark_scale=3.0)
    options = dict(max_iterations=100, ftol=1e-8, xtol=1e-8, damping=1e-4, jacobian_dtype=torch.float32)

    def fun(x):
        return problem.residuals(torch.from_numpy(x).float()[None])[0].double().numpy()

    def jac(x):
        return problem.jacobian(torch.from_numpy(x).float()[None])[0].double().numpy()

    traces: dict[str, list[list[tuple[float, float]]]] = {"jacobian_fn": [], "normal_equations_fn": [], "scipy": []}

    def traced(name, solve):
        """``solve(record)`` as a timed run that appends (seconds since its start, energy) of every
        residual evaluation to ``traces[name]``; ``record`` wraps a residual function."""
        def run():
            trace, start = [], time.perf_counter()

            def record(residual_fn):
                def evaluate(x):
                    r = residual_fn(x)
                    energy = 0.5 * float(r.double().square().sum() if torch.is_tensor(r) else (r * r).sum())
                    trace.append((time.perf_counter() - start, energy))
                    return r
                return evaluate
            out = solve(record)
            traces[name].append(trace)
            return out
        return run

    solvers = interleaved({
        "jacobian_fn": traced("jacobian_fn", lambda record: levenberg_marquardt(
            record(problem.residuals), x0, jacobian_fn=lambda z: problem.jacobian(z, dtype=torch.float32), **options)),
        "normal_equations_fn": traced("normal_equations_fn", lambda record: levenberg_marquardt(
            record(problem.residuals), x0,
            normal_equations_fn=lambda z, r: problem.normal_equations(z, r, dtype=torch.float32), **options)),
        "scipy": traced("scipy", lambda record: least_squares(
            record(fun), x0[0].double().numpy(), jac=jac, ftol=1e-8, xtol=1e-8)),
    }, args.repeats)
    lowest = min(energy for runs in traces.values() for trace in runs for _, energy in trace)
    target = lowest * (1.0 + TARGET_TOLERANCE)

    def time_to_target(name: str) -> float:
        """Median over the runs of the time at which the energy first came within the tolerance."""
        return statistics.median(next((t for t, energy in trace if energy <= target), float("inf"))
                                 for trace in traces[name])
    to_target = {name: time_to_target(name) for name in traces}
    (ours_t, ours), (fused_t, fused), (scipy_t, sp) = solvers.values()
    cost = {name: float(0.5 * problem.residuals(r.x).double().square().sum()) for name, r in
            (("jacobian_fn", ours), ("normal_equations_fn", fused))}
    rows.append((f"one LM round, facenormals, jacobian_fn ({int(ours.iterations[0])} iterations)", ours_t * 1e3, ""))
    rows.append((f"one LM round, facenormals, normal_equations_fn ({int(fused.iterations[0])} iterations)",
                 fused_t * 1e3, ""))
    rows.append((f"one LM round, scipy least_squares trf ({sp.njev} Jacobians)", scipy_t * 1e3, ">= 10x ours"))

    # Analytic vs autograd Jacobian of the same residuals, each at a new x (the problem caches the
    # geometry of the last x, which the residuals before a Jacobian would have computed).
    fresh = (x0 + 1e-6 * k for k in range(1, 100))
    analytic_t = statistics.median(timed(lambda: problem.jacobian(next(fresh), dtype=torch.float32))[0] for _ in range(5))
    autograd_t = statistics.median(timed(lambda: torch.func.jacfwd(problem.residuals)(next(fresh)))[0]
                                   for _ in range(2))
    rows.append(("Jacobian, analytic (geometry computed too)", analytic_t * 1e3, ""))
    rows.append(("Jacobian, autograd (torch.func.jacfwd)", autograd_t * 1e3, ""))

    # 4. Batch of subjects (after a warm-up of both), interleaved.
    batch = heads[: args.batch]
    maps = torch.cat([b.normal_maps for b in batch])
    lms = torch.cat([b.landmarks for b in batch])
    K = torch.cat([b.intrinsics for b in batch])
    fit_head(maps, lms, model, intrinsics=K)  # warm-up at the batch's own size
    batched = interleaved({
        "batch": lambda: fit_head(maps, lms, model, intrinsics=K),
        "sequential": lambda: [fit_head(b.normal_maps, b.landmarks, model, intrinsics=b.intrinsics) for b in batch],
    }, max(3, args.repeats // 2))  # at least 3: the median of 2 runs is their mean
    (batch_t, batch_fit), (seq_t, seq_fits) = batched.values()
    rows.append((f"B={args.batch} subjects as one batch, per subject", batch_t / args.batch * 1e3, ""))
    rows.append((f"{args.batch} sequential fits, per subject", seq_t / args.batch * 1e3, ""))

    print("\n| measurement | median ms | target |\n|---|---|---|")
    for name, ms, target in rows:
        print(f"| {name} | {ms:.1f} | {target} |")
    print(f"\nfull fit: median {iterations} LM iterations")
    print(f"scipy / ours (normal_equations_fn) on the same round: {scipy_t / fused_t:.1f}x")
    print(f"scipy / ours (jacobian_fn) on the same round: {scipy_t / ours_t:.1f}x")
    print(f"time to within {TARGET_TOLERANCE:g} of the lowest energy reached ({lowest:.5f}): "
          + ", ".join(f"{name} {t * 1e3:.1f} ms" for name, t in to_target.items())
          + f"; scipy / ours {to_target['scipy'] / to_target['normal_equations_fn']:.1f}x (normal_equations_fn), "
          f"{to_target['scipy'] / to_target['jacobian_fn']:.1f}x (jacobian_fn)")
    for name, value in cost.items():
        print(f"final energy, {name}: {value:.4f} vs {float(sp.cost):.4f} (scipy), relative difference "
              f"{abs(value - sp.cost) / sp.cost:.1e}")
    batch_iterations = batch_fit.iterations.float().mean()
    seq_iterations = torch.cat([f.iterations for f in seq_fits]).float().mean()
    print(f"batch throughput vs sequential: {seq_t / batch_t:.2f}x (mean LM iterations per subject "
          f"{float(batch_iterations):.1f} in the batch, {float(seq_iterations):.1f} sequential)")


if __name__ == "__main__":
    main(ARGS)
