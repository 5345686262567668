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
    problem.update_robust_weights(x, 0.1)
    J = problem.jacobian(x)
    reference = torch.func.jacfwd(problem.residuals)(x)[:, :, 0]
    assert J.shape == reference.shape == (1, problem.residuals(x).shape[1], problem.P)
    torch.testing.assert_close(J, reference, rtol=1e-7, atol=1e-7)
    assert (J[0].abs().sum(0) > 0).all()  # every parameter moves some residual


def test_pack_unpack_round_trip():
    model = small_model()
    obs = render_oracle_views(model, model.shape_std[None], [0.0, 20.0, 40.0], image_size=32)
    problem = HeadFitProblem(model, obs.normal_maps, obs.landmarks, obs.landmark_mask, obs.intrinsics)
    y = torch.randn(1, 6, dtype=torch.float64)
    x = problem.pack(y, obs.angles, obs.translation, obs.intrinsics)
    p = problem.unpack(x)
    assert x.shape == (1, 6 + 3 * 9)
    assert torch.equal(p["shape"], y) and torch.equal(p["angles"], obs.angles)
    assert torch.equal(p["translation"], obs.translation) and torch.equal(p["intrinsics"], obs.intrinsics)
