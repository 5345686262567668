"""The analytic Jacobian of the fitting energy equals autograd's, for every parameter block."""

import pytest
import torch

from facenormals.fitting import FitWeights, HeadFitProblem
from facenormals.fitting.oracle import render_oracle_views
from facenormals.models import MorphableModel, builtin_head_model


def small_model(num_expressions: int = 0) -> MorphableModel:
    base = builtin_head_model(dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    expr = 2.0 * torch.randn(num_expressions, base.num_vertices, 3, generator=g, dtype=torch.float64)
    return MorphableModel(base.mean, base.shape_basis[:6], base.faces, shape_std=base.shape_std[:6],
                          expression_basis=expr if num_expressions else None, landmarks=base.landmarks)


@pytest.mark.parametrize("fit_intrinsics,fit_expression", [(True, False), (False, False), (True, True)])
def test_jacobian_matches_autograd(fit_intrinsics, fit_expression):
    model = small_model(2 if fit_expression else 0)
    y = 0.8 * model.shape_std[None]
    obs = render_oracle_views(model, y, [-30.0, 40.0], image_size=64)
    problem = HeadFitProblem(model, obs.normal_maps, obs.landmarks, obs.landmark_mask, obs.intrinsics,
                             weights=FitWeights(), fit_intrinsics=fit_intrinsics, fit_expression=fit_expression)
    expression = torch.full((1, 2), 0.3, dtype=torch.float64) if fit_expression else None
    x = problem.pack(0.5 * y, obs.angles + 0.02, obs.translation + 2.0, obs.intrinsics * 1.03, expression)
    problem.update_visibility(x, min_facing=0.1)
    problem.update_robust_weights(x, 0.1, landmark_scale=3.0)
    J = problem.jacobian(x)
    reference = torch.func.jacfwd(problem.residuals)(x)[:, :, 0]
    assert J.shape == reference.shape == (1, problem.residuals(x).shape[1], problem.P)
    torch.testing.assert_close(J, reference, rtol=1e-7, atol=1e-7)
    assert (J[0].abs().sum(0) > 0).all()  # every parameter moves some residual


def test_pack_unpack_round_trip():
    model = small_model()
    obs = render_oracle_views(model, model.shape_std[None], [0.0, 20.0, 40.0], image_size=32)
    problem = HeadFitProblem(model, obs.normal_maps, obs.landmarks, obs.landmark_mask, obs.intrinsics)
    y = torch.randn(1, 6, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    x = problem.pack(y, obs.angles, obs.translation, obs.intrinsics)
    p = problem.unpack(x)
    assert x.shape == (1, 6 + 3 * 9)
    assert torch.equal(p["shape"], y) and torch.equal(p["angles"], obs.angles)
    assert torch.equal(p["translation"], obs.translation)
    torch.testing.assert_close(p["intrinsics"], obs.intrinsics, rtol=1e-14, atol=0.0)
    # the focal length is stored as its logarithm: any step keeps it positive
    focal_slots = 6 + 9 * torch.arange(3) + 6
    torch.testing.assert_close(x[0, focal_slots], obs.intrinsics[0, :, 0].log())
    x_far = x.clone()
    x_far[0, focal_slots] -= 50.0
    assert (problem.unpack(x_far)["intrinsics"][..., 0] > 0).all()


def two_subject_problem(**options):
    model = small_model()
    g = torch.Generator().manual_seed(1)
    heads = [render_oracle_views(model, model.sample_shape_coeffs(1, generator=g), yaws, image_size=48)
             for yaws in ([-20.0, 30.0], [10.0, 50.0])]
    cat = lambda name: torch.cat([getattr(h, name) for h in heads])  # noqa: E731
    problem = HeadFitProblem(model, cat("normal_maps"), cat("landmarks"), cat("landmark_mask"), cat("intrinsics"),
                             **options)
    x = problem.pack(0.5 * cat("shape_coeffs"), cat("angles") + 0.02, cat("translation") + 2.0, cat("intrinsics") * 1.02)
    problem.update_visibility(x, min_facing=0.1)
    problem.update_robust_weights(x, 0.1, landmark_scale=3.0)
    return problem, x


def test_normal_equations_match_the_jacobian():
    problem, x = two_subject_problem()
    J, r = problem.jacobian(x), problem.residuals(x)
    H, g = problem.normal_equations(x, r)
    torch.testing.assert_close(H, J.transpose(1, 2) @ J, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(g, (r[:, None] @ J)[:, 0], rtol=1e-10, atol=1e-10)


def test_subject_subsets_match_the_full_batch():
    problem, x = two_subject_problem()
    r, J = problem.residuals(x), problem.jacobian(x)
    H, g = problem.normal_equations(x, r)
    for b in range(2):
        index = torch.tensor([b])
        torch.testing.assert_close(problem.residuals(x[index], index), r[index])
        torch.testing.assert_close(problem.jacobian(x[index], index=index), J[index])
        H_b, g_b = problem.normal_equations(x[index], r[index], index=index)
        torch.testing.assert_close(H_b, H[index])
        torch.testing.assert_close(g_b, g[index])


def test_the_problem_s_methods_are_the_solver_s_callbacks_with_active_subsets():
    """levenberg_marquardt calls jacobian_fn(x, index) and normal_equations_fn(x, r, index): the index
    landed in the dtype argument, and a batch of two failed with 'Boolean value of Tensor ...'."""
    from facenormals.optim import levenberg_marquardt

    problem, x = two_subject_problem()
    for fns in ({"jacobian_fn": problem.jacobian}, {"normal_equations_fn": problem.normal_equations}):
        result = levenberg_marquardt(problem.residuals, x, active_subset=True, max_iterations=3, **fns)
        assert result.x.shape == x.shape and bool(torch.isfinite(result.x).all())
    assert problem.jacobian(x, dtype=torch.float32).dtype == torch.float32


def test_an_in_place_change_of_x_does_not_reach_the_cached_geometry():
    """The cached geometry held views of the caller's x: after x.add_(), the residuals at the old
    values mixed the new shape and pose with the old vertices."""
    problem, x = two_subject_problem()
    saved = x.clone()
    expected_r, expected_J = problem.residuals(saved), problem.jacobian(saved)
    problem.residuals(x)
    x.add_(0.5)
    torch.testing.assert_close(problem.residuals(saved), expected_r, rtol=0, atol=0)
    torch.testing.assert_close(problem.jacobian(saved), expected_J, rtol=0, atol=0)


def test_vertex_subset_restricts_the_normal_rows():
    from facenormals.fitting.subsample import grid_subset

    full, x = two_subject_problem()
    subset = grid_subset(full.model.mean, 8.0)
    assert 0 < int(subset.sum()) < subset.shape[0]
    problem, _ = two_subject_problem(vertex_subset=subset)
    assert subset[problem.vis_index[problem.vis_valid]].all()
    assert int(problem.vis_valid.sum()) == int((full.vis_valid & subset[full.vis_index]).sum())
    J = problem.jacobian(x)
    torch.testing.assert_close(J, torch.func.jacfwd(problem.residuals)(x).diagonal(dim1=0, dim2=2).permute(2, 0, 1),
                               rtol=1e-7, atol=1e-7)


def test_per_subject_vertex_subsets():
    from facenormals.fitting.subsample import grid_subset

    full, _ = two_subject_problem()
    subsets = torch.stack([grid_subset(full.model.mean, 8.0), grid_subset(full.model.mean, 12.0)])
    problem, _ = two_subject_problem(vertex_subset=subsets)
    for b in range(2):  # each subject uses exactly its own subset's visible vertices
        used = problem.vis_index[b][problem.vis_valid[b]]
        assert subsets[b][used].all()
        assert int(problem.vis_valid[b].sum()) == int((full.vis_valid[b] & subsets[b][full.vis_index[b]]).sum())
    with pytest.raises(ValueError, match=r"vertex_subset: expected a bool tensor of shape \(N,\) or \(B, N\)"):
        two_subject_problem(vertex_subset=subsets[:1])


@pytest.mark.parametrize(
    "field,value,match",
    [("normals", -1.0, r"FitWeights.normals: expected a finite number >= 0, got -1.0"),
     ("prior", float("nan"), r"FitWeights.prior: expected a finite number, got nan"),
     ("landmarks", "a", r"FitWeights.landmarks: expected a real number, got str 'a'"),
     ("landmarks", "0.8", r"FitWeights.landmarks: expected a real number, got str '0.8'"),
     ("focal_std", "0.2", r"FitWeights.focal_std: expected a real number, got str '0.2'"),
     ("normals", True, r"FitWeights.normals: expected a real number, got bool"),
     ("center_std", 0.0, r"FitWeights.center_std: expected a finite number > 0, got 0.0")],
)
def test_fit_weights_check_their_values(field, value, match):
    with pytest.raises(ValueError, match=match):
        FitWeights(**{field: value})
    assert FitWeights(normals=0.0).normals == 0.0  # landmarks only is allowed


def test_fit_weights_hold_plain_floats():
    """Regression: FitWeights(landmarks="0.8") was accepted and the fit failed deep inside with a
    TypeError; numbers of other types are kept as plain floats."""
    import numpy as np

    weights = FitWeights(normals=np.float32(0.5), landmarks=torch.tensor(0.25, dtype=torch.float64), prior=2)
    assert (weights.normals, weights.landmarks, weights.prior) == (0.5, 0.25, 2.0)
    assert all(type(getattr(weights, name)) is float for name in ("normals", "landmarks", "prior"))


def test_problem_checks_its_inputs():
    model = small_model()
    obs = render_oracle_views(model, model.sample_shape_coeffs(1, generator=torch.Generator().manual_seed(2)), [0.0],
                              image_size=32)
    args = [obs.normal_maps, obs.landmarks, obs.landmark_mask, obs.intrinsics]
    cases = [
        (0, obs.normal_maps[0], r"normal_maps: expected shape \(B, V, 3, H, W\) \(5 dimensions\), got \(1, 3, 32, 32\)"),
        (1, obs.landmarks[..., :-1, :], r"landmarks: expected shape \(B, V, 24, 2\).*got \(1, 1, 23, 2\)"),
        (2, obs.landmark_mask.float(), r"landmark_mask: expected a bool tensor"),
        (3, obs.intrinsics[0], r"intrinsics_prior: expected shape \(B, V, 3\).*got \(1, 3\)"),
    ]
    for position, value, match in cases:
        bad = list(args)
        bad[position] = value
        with pytest.raises(ValueError, match=match):
            HeadFitProblem(model, *bad)
    with pytest.raises(ValueError, match=r"view_weights: expected finite values >= 0"):
        HeadFitProblem(model, *args, view_weights=-torch.ones(1, 1))
    nan_map = obs.normal_maps.clone()
    nan_map[0, 0, 2, 5, 5] = float("nan")
    with pytest.raises(ValueError, match="normal_maps: expected finite values, got 1 NaN"):
        HeadFitProblem(model, nan_map, *args[1:])
    nan_landmarks = obs.landmarks.clone()
    nan_landmarks[0, 0, 3] = float("nan")  # marked present: it counts as missing instead of poisoning the energy
    problem = HeadFitProblem(model, obs.normal_maps, nan_landmarks, torch.ones_like(obs.landmark_mask), obs.intrinsics)
    assert not bool(problem.landmark_mask[0, 0, 3])
    with pytest.raises(ValueError, match=r"vertex_subset: expected a bool tensor of shape \(N,\) or \(B, N\)"):
        HeadFitProblem(model, *args, vertex_subset=torch.ones(5, dtype=torch.bool))


def test_problem_refuses_non_float_inputs_empty_batches_and_a_non_model():
    """A bool prior became [1, 1, 1] and bool or integer landmarks were fitted as they came; an empty
    batch failed deep inside (``max()`` of no visible vertices)."""
    model = small_model()
    obs = render_oracle_views(model, model.sample_shape_coeffs(1, generator=torch.Generator().manual_seed(2)), [0.0],
                              image_size=32)
    args = [obs.normal_maps, obs.landmarks, obs.landmark_mask, obs.intrinsics]
    cases = [
        (1, obs.landmarks.bool(), "landmarks: expected a floating-point tensor, got dtype torch.bool"),
        (1, obs.landmarks.long(), "landmarks: expected a floating-point tensor, got dtype torch.int64"),
        (3, obs.intrinsics.bool(), "intrinsics_prior: expected a floating-point tensor, got dtype torch.bool"),
        (3, obs.intrinsics.long(), "intrinsics_prior: expected a floating-point tensor, got dtype torch.int64"),
    ]
    for position, value, match in cases:
        bad = list(args)
        bad[position] = value
        with pytest.raises(ValueError, match=match):
            HeadFitProblem(model, *bad)
    for empty, shape in (([a[:0] for a in args], r"\(0, 1, 3, 32, 32\)"),  # no subject
                         ([a[:, :0] for a in args], r"\(1, 0, 3, 32, 32\)")):  # a subject without views
        with pytest.raises(ValueError, match="normal_maps: expected at least one subject, one view and one pixel, "
                                             f"got shape {shape}"):
            HeadFitProblem(model, *empty)
    with pytest.raises(ValueError, match="model: expected a MorphableModel, got NoneType"):
        HeadFitProblem(None, *args)


def test_huber_scale_is_in_units_of_the_normals_whatever_the_view_weight():
    problem, x = two_subject_problem()
    reference = problem.update_robust_weights(x, 0.1).clone()
    heavy, _ = two_subject_problem(view_weights=torch.full((2, 2), 4.0, dtype=torch.float64))
    torch.testing.assert_close(heavy.update_robust_weights(x, 0.1), reference)
    assert float(reference[problem.vis_valid.bool()].min()) < 1.0  # some vertices are down-weighted at all
