"""The recipe end to end on oracle maps of the built-in head (the ICT accuracy study is
``benchmarks/accuracy_oracle.py``; its output is checked in as docs/accuracy.md)."""

import pytest
import torch

from facenormals.eval import evaluate_reconstruction
from facenormals.fitting import FitWeights, fit_head
from facenormals.fitting.oracle import render_oracle_views
from facenormals.models import builtin_head_model


@pytest.fixture(scope="module")
def model():
    return builtin_head_model()


@pytest.fixture(scope="module")
def head(model):
    g = torch.Generator().manual_seed(3)
    return model.sample_shape_coeffs(1, generator=g)


def p2p(model, vertices, truth):
    report = evaluate_reconstruction(vertices.double(), model.faces, truth.double(), model.faces, model.face_region,
                                     correspondences=model.landmarks)
    return report.similarity.point_to_plane_rmse


def test_single_view_beats_the_mean_head_and_landmarks_only(model, head, tmp_path):
    obs = render_oracle_views(model, head, [20.0])
    result = fit_head(obs.normal_maps[0], obs.landmarks[0], model, intrinsics=obs.intrinsics[0])
    landmarks_only = fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=obs.intrinsics,
                              weights=FitWeights(normals=0.0))
    truth = obs.vertices[0]
    fit_err, mean_err = p2p(model, result.vertices[0], truth), p2p(model, model.mean, truth)
    assert fit_err < 0.5 * mean_err
    assert fit_err < p2p(model, landmarks_only.vertices[0], truth)
    assert abs(float(result.angles[0, 0, 2]) - float(obs.angles[0, 0, 2])) < 0.03
    assert result.landmark_rms_px[0, 0] < 1.0
    assert set(result.energies) == {"normals", "landmarks", "prior", "intrinsics_prior"}
    assert result.export(tmp_path / "fit.ply").exists()
    assert "yaw" in result.summary()
    # camera-frame vertices X_c = R (p + t), written out here: a transposed rotation passed before
    R, t = result.rotation[0, 0], result.translation[0, 0]
    camera = torch.stack([R @ (p + t) for p in result.vertices[0]])
    torch.testing.assert_close(result.camera_vertices(0)[0], camera)
    f, u0, v0 = result.intrinsics[0, 0].tolist()
    seen = obs.landmark_mask[0, 0]
    lm = camera[model.landmark_indices][seen]
    uv = torch.stack([f * lm[:, 0] / lm[:, 2] + u0, f * lm[:, 1] / lm[:, 2] + v0], dim=-1)
    assert float((uv - obs.landmarks[0, 0][seen]).norm(dim=-1).max()) < 3.0  # projected onto the observations
    for call, name in ((lambda i: result.export(tmp_path / "x.ply", subject=i), "subject"),
                       (lambda i: result.summary(i), "subject"), (lambda i: result.camera_vertices(i), "view")):
        with pytest.raises(ValueError, match=rf"{name}: expected an index in \[0, 1\), got 1"):
            call(1)
        for index in (-1, True):  # -1 picked the last subject silently
            with pytest.raises(ValueError, match=f"{name}: expected an integer"):
                call(index)


def test_three_views_are_not_worse_than_one(model, head):
    one = render_oracle_views(model, head, [0.0])
    three = render_oracle_views(model, head, [-45.0, 0.0, 45.0])
    err1 = p2p(model, fit_head(one.normal_maps, one.landmarks, model, intrinsics=one.intrinsics).vertices[0], one.vertices[0])
    fit3 = fit_head(three.normal_maps, three.landmarks, model, intrinsics=three.intrinsics)
    assert fit3.angles.shape == (1, 3, 3) and fit3.intrinsics.shape == (1, 3, 3)
    assert p2p(model, fit3.vertices[0], one.vertices[0]) <= err1 * 1.05


def test_initial_yaw_off_by_30_degrees_still_converges(model, head):
    obs = render_oracle_views(model, head, [25.0])
    from facenormals.geometry import euler_to_rotation_matrix

    wrong = obs.angles.clone()
    wrong[..., 2] -= torch.deg2rad(torch.tensor(30.0))
    # same head position in the camera, orientation off by 30 degrees of yaw: t' = R'^T R t
    centre = euler_to_rotation_matrix(obs.angles[0]) @ obs.translation[0, :, :, None]
    moved = (euler_to_rotation_matrix(wrong[0]).transpose(1, 2) @ centre)[..., 0][None]
    result = fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=obs.intrinsics, initial_pose=(wrong, moved))
    assert abs(float(result.angles[0, 0, 2] - obs.angles[0, 0, 2])) < 0.05


def test_view_without_face_is_down_weighted_not_fatal(model, head):
    obs = render_oracle_views(model, head, [-30.0, 30.0])
    maps = obs.normal_maps.clone()
    maps[:, 1] = 0.0  # the second view's map has no foreground
    result = fit_head(maps, obs.landmarks, model, intrinsics=obs.intrinsics)
    assert torch.isfinite(result.vertices).all()
    assert p2p(model, result.vertices[0], obs.vertices[0]) < p2p(model, model.mean, obs.vertices[0])


def test_view_without_landmarks_names_the_view(model, head):
    obs = render_oracle_views(model, head, [0.0, 30.0])
    landmarks = obs.landmarks.clone()
    landmarks[:, 1] = float("nan")
    with pytest.raises(ValueError, match="view 1 has 0 visible landmarks"):
        fit_head(obs.normal_maps, landmarks, model, intrinsics=obs.intrinsics)


def test_batch_of_subjects_matches_individual_fits(model):
    g = torch.Generator().manual_seed(5)
    heads = [render_oracle_views(model, model.sample_shape_coeffs(1, generator=g), [yaw]) for yaw in (-10.0, 25.0)]
    maps = torch.cat([h.normal_maps for h in heads])
    lms = torch.cat([h.landmarks for h in heads])
    K = torch.cat([h.intrinsics for h in heads])
    batch = fit_head(maps, lms, model, intrinsics=K)
    for b, h in enumerate(heads):
        alone = fit_head(h.normal_maps, h.landmarks, model, intrinsics=h.intrinsics)
        torch.testing.assert_close(batch.vertices[b], alone.vertices[0], atol=0.05, rtol=0)


def test_one_subjects_views_against_a_batch_name_the_per_subject_shape(model):
    """With B = 2 subjects, (V, 3) intrinsics were refused by a message saying (V, 3) is accepted."""
    g = torch.Generator().manual_seed(5)
    heads = [render_oracle_views(model, model.sample_shape_coeffs(1, generator=g), [0.0], image_size=32)
             for _ in range(2)]
    maps, lms = torch.cat([h.normal_maps for h in heads]), torch.cat([h.landmarks for h in heads])
    with pytest.raises(ValueError, match=r"intrinsics: expected shape \(B, V, 3\) with B=2, V=1 \(one entry per "
                                         r"subject of normal_maps\), got \(1, 3\)"):
        fit_head(maps, lms, model, intrinsics=heads[0].intrinsics[0])


def test_inputs_on_another_device_than_the_model_are_named(model, head):
    """The fit runs on the model's device; maps elsewhere failed deep inside (seen with meta tensors,
    which stand in for a GPU here)."""
    obs = render_oracle_views(model, head, [0.0], image_size=32)
    with pytest.raises(ValueError, match="normal_maps: expected device cpu .*got meta"):
        fit_head(obs.normal_maps.to("meta"), obs.landmarks, model)
    with pytest.raises(ValueError, match="intrinsics: expected device cpu .*got meta"):
        fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=obs.intrinsics.to("meta"))


def test_non_finite_normal_maps_name_their_views(model, head):
    """A NaN in one of several views named only ``normal_maps``, leaving the user to search the views."""
    obs = render_oracle_views(model, head, [-30.0, 0.0, 30.0], image_size=32)
    maps = obs.normal_maps.clone()
    maps[0, 2, 1, 5, 7] = float("nan")
    with pytest.raises(ValueError, match=r"normal_maps: expected finite values, got 1 NaN or infinite entries, "
                                         r"in view 2$"):
        fit_head(maps, obs.landmarks, model)
    pair = torch.cat([obs.normal_maps, maps])
    pair[1, 0, 0, 0, 0] = float("inf")
    with pytest.raises(ValueError, match=r"got 2 NaN or infinite entries, in view 0 of subject 1, "
                                         r"view 2 of subject 1$"):
        fit_head(pair, torch.cat([obs.landmarks] * 2), model)


def test_bad_input(model, head):
    obs = render_oracle_views(model, head, [0.0], image_size=32)
    maps = obs.normal_maps.clone()
    maps[0, 0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="normal_maps: expected finite values"):
        fit_head(maps, obs.landmarks, model)
    with pytest.raises(ValueError, match=r"landmarks: expected shape \(V, 24, 2\) or \(B, V, 24, 2\) with B=1, V=1, "
                                         r"got \(1, 1, 10, 2\)"):
        fit_head(obs.normal_maps, obs.landmarks[..., :10, :], model)
    with pytest.raises(ValueError, match=r"intrinsics: expected shape \(V, 3\) or \(B, V, 3\) with B=1, V=1, got \(2, 3\)"):
        fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=obs.intrinsics[0].expand(2, 3))
    with pytest.raises(ValueError, match="landmark_mask: expected a bool tensor, got dtype torch.float32"):
        fit_head(obs.normal_maps, obs.landmarks, model, landmark_mask=torch.ones(1, 24))
    with pytest.raises(ValueError, match=r"landmark_mask: expected shape .* got \(2, 24\)"):
        fit_head(obs.normal_maps, obs.landmarks, model, landmark_mask=torch.ones(2, 24, dtype=torch.bool))
    with pytest.raises(ValueError, match="rounds"):
        fit_head(obs.normal_maps, obs.landmarks, model, rounds=0)
    with pytest.raises(ValueError, match="visibility_rounds: expected an integer >= 1, got 0"):
        fit_head(obs.normal_maps, obs.landmarks, model, visibility_rounds=0)
    with pytest.raises(ValueError, match="rounds: expected an integer, got float 1.5"):
        fit_head(obs.normal_maps, obs.landmarks, model, rounds=1.5)
    with pytest.raises(ValueError, match="normal_maps: expected a floating-point tensor, got dtype torch.int64"):
        fit_head(obs.normal_maps.long(), obs.landmarks, model)  # unit normals would truncate to an empty map
    with pytest.raises(ValueError, match=r"normal_maps: expected at least one subject, one view and one pixel, got "
                                         r"shape \(1, 0, 3, 32, 32\)"):
        fit_head(obs.normal_maps[:, :0], obs.landmarks[:, :0], model)
    nan_centre = obs.intrinsics.clone()
    nan_centre[..., 1] = float("nan")
    with pytest.raises(ValueError, match="intrinsics: expected finite values"):
        fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=nan_centre, initial_pose=(obs.angles, obs.translation))
    with pytest.raises(ValueError, match="landmark_robust_scale: expected a finite number > 0"):
        fit_head(obs.normal_maps, obs.landmarks, model, landmark_robust_scale=0.0)
    with pytest.raises(ValueError, match="robust_scale: expected a finite number > 0"):
        fit_head(obs.normal_maps, obs.landmarks, model, robust_scale=-1.0)
    with pytest.raises(ValueError, match="robust_scale: expected a real number, got str"):
        fit_head(obs.normal_maps, obs.landmarks, model, robust_scale="0.1")  # was a TypeError
    bad_focal = obs.intrinsics.clone()
    bad_focal[..., 0] = 0.0
    with pytest.raises(ValueError, match="intrinsics: expected focal lengths f > 0"):
        fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=bad_focal)
    with pytest.raises(ValueError, match=r"vertex_spacing: expected a spacing, a non-empty sequence"):
        fit_head(obs.normal_maps, obs.landmarks, model, vertex_spacing=[])
    with pytest.raises(ValueError, match="fit_expression: model 'builtin' has no expression basis"):
        fit_head(obs.normal_maps, obs.landmarks, model, fit_expression=True)
    nan_angles = obs.angles.clone()
    nan_angles[..., 0] = float("nan")
    with pytest.raises(ValueError, match="initial_pose angles: expected finite values"):
        fit_head(obs.normal_maps, obs.landmarks, model, initial_pose=(nan_angles, obs.translation))
    with pytest.raises(ValueError, match=r"FitWeights.focal_std: expected a finite number > 0, got 0"):
        fit_head(obs.normal_maps, obs.landmarks, model, weights=FitWeights(focal_std=0))


def test_intrinsics_and_initial_pose_that_are_not_floating_point_are_named(model, head):
    """A bool prior fitted a focal length of 1.3 px and a bool translation a 200 px landmark error, both
    CONVERGED; integer angles were blamed on the normal maps' x components."""
    obs = render_oracle_views(model, head, [0.0], image_size=32)
    angles, translation = obs.angles, obs.translation
    for intrinsics in (obs.intrinsics.bool(), obs.intrinsics.long()):
        with pytest.raises(ValueError, match=f"intrinsics: expected a floating-point tensor, got dtype {intrinsics.dtype}"):
            fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=intrinsics)
    cases = [((angles.bool(), translation), "initial_pose angles: expected a floating-point tensor, got dtype torch.bool"),
             ((angles.long(), translation), "initial_pose angles: expected a floating-point tensor, got dtype torch.int64"),
             ((angles, translation.bool()), "initial_pose translation: expected a floating-point tensor, got dtype torch.bool")]
    for pose, match in cases:
        with pytest.raises(ValueError, match=match):
            fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=obs.intrinsics, initial_pose=pose)
    with pytest.raises(ValueError, match=r"initial_pose translation: expected shape \(V, 3\) or \(B, V, 3\)"):
        fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=obs.intrinsics, initial_pose=(angles, translation[..., :2]))


def test_options_that_silently_dropped_the_normal_term_are_errors(model, head):
    # each of these used to fit a landmarks-only head (1 vertex or none in the normal term) and
    # report CONVERGED
    obs = render_oracle_views(model, head, [0.0], image_size=32)
    for spacing, shown in ((float("nan"), "nan"), (float("inf"), "inf"), ((3.0, float("nan")), r"\(3.0, nan\)"),
                           (0.0, "0.0"), ("3", "'3'")):
        with pytest.raises(ValueError, match=rf"vertex_spacing: expected finite spacings > 0 in pixels or None, got {shown}"):
            fit_head(obs.normal_maps, obs.landmarks, model, vertex_spacing=spacing)
    import numpy as np

    assert int(fit_head(obs.normal_maps, obs.landmarks, model, vertex_spacing=(np.float32(3.0), np.int64(1)),
                        rounds=1, iterations_per_round=1).iterations[0]) == 1  # numpy numbers are numbers
    for facing, match in ((1.0, r"min_facing: expected a value in \[-1, 1\), got 1.0"),
                          (float("nan"), "min_facing: expected a finite number")):
        with pytest.raises(ValueError, match=match):
            fit_head(obs.normal_maps, obs.landmarks, model, min_facing=facing)


@pytest.mark.parametrize("encode, match", [
    (lambda n, fg: n * 255, "holds normals of median length 255 where unit .*0-255 or encoded as colours"),
    (lambda n, fg: (n + 1) / 2 * fg, "holds normals of median length 0.85.*0-255 or encoded as colours"),
    (lambda n, fg: n * torch.tensor([1.0, -1.0, -1.0])[:, None, None], "0 % of its normals facing the camera.*OpenGL"),
])
def test_normal_maps_in_another_encoding_are_refused(model, head, encode, match):
    # each fitted without error to a head near the mean (1.9 mm, or 4.5 mm for the OpenGL frame)
    obs = render_oracle_views(model, head, [0.0, 30.0], image_size=32)
    maps = obs.normal_maps.clone()
    fg = maps[0, 1].norm(dim=0, keepdim=True) > 0.5
    maps[0, 1] = encode(maps[0, 1], fg)
    with pytest.raises(ValueError, match="normal_maps: view 1 (has only )?" + match):
        fit_head(maps, obs.landmarks, model, intrinsics=obs.intrinsics)


def test_wrong_argument_types_are_named(model, head):
    obs = render_oracle_views(model, head, [0.0], image_size=32)
    cases = [
        (dict(weights={"normals": 1.0}), "weights: expected a FitWeights, got dict"),
        (dict(model="builtin"), r"model: expected a MorphableModel \(e.g. facenormals.load_model\('builtin'\)"),
        (dict(initial_pose=obs.angles), "initial_pose: expected a pair"),
        (dict(jacobian_dtype=torch.float16), "jacobian_dtype: expected None, torch.float32 or torch.float64"),
    ]
    for kwargs, match in cases:
        args = {"normal_maps": obs.normal_maps, "landmarks": obs.landmarks, "model": model, **kwargs}
        with pytest.raises(ValueError, match=match):
            fit_head(**args)


def test_a_given_pose_still_needs_something_in_every_view(model, head):
    obs = render_oracle_views(model, head, [0.0, 40.0], image_size=32)
    maps, marks = obs.normal_maps.clone(), obs.landmarks.clone()
    maps[0, 1], marks[0, 1] = 0.0, float("nan")
    with pytest.raises(ValueError, match="view 1 has neither a face in its normal map nor a landmark"):
        fit_head(maps, marks, model, intrinsics=obs.intrinsics, initial_pose=(obs.angles, obs.translation))


def test_a_model_without_landmarks_fits_from_a_given_pose(model, head):
    # the fit from a given pose needs no landmarks: it crashed on reshaping 0 landmarks, and the
    # pixel size (for the vertex subset) was NaN, which kept a single vertex
    from facenormals.models import MorphableModel

    bare = MorphableModel(model.mean, model.shape_basis, model.faces, shape_std=model.shape_std, name="bare")
    obs = render_oracle_views(model, head, [0.0], image_size=48)
    fit = fit_head(obs.normal_maps, torch.zeros(1, 1, 0, 2), bare, intrinsics=obs.intrinsics,
                   initial_pose=(obs.angles, obs.translation))
    assert int(fit.visible.sum()) > 100 and float(fit.energies["normals"]) > 0
    assert p2p(model, fit.vertices[0], obs.vertices[0]) < 0.7 * p2p(model, model.mean, obs.vertices[0])


def test_reported_energies_are_the_weighted_terms(model, head):
    """With plain least squares over every visible vertex, the energies are λ times the paper's terms."""
    obs = render_oracle_views(model, head, [10.0], image_size=64)
    weights = FitWeights(normals=1.0, landmarks=0.8, prior=0.4)
    fit = fit_head(obs.normal_maps, obs.landmarks + 0.5, model, weights=weights, robust_scale=None,
                   landmark_robust_scale=None, vertex_spacing=None, fit_intrinsics=False, rounds=2)
    prior = 0.5 * 0.4 * (fit.shape_coeffs / model.shape_std).square().sum(1)
    torch.testing.assert_close(fit.energies["prior"], prior)
    count = obs.landmark_mask.sum()
    landmarks = 0.5 * 0.8 * fit.landmark_rms_px.square().sum(1) * count  # rms over all (visible) landmarks
    torch.testing.assert_close(fit.energies["landmarks"], landmarks, rtol=1e-4, atol=1e-6)
    assert set(fit.energies) == {"normals", "landmarks", "prior"}
    assert float(fit.energies["normals"]) > 0
    halved = fit_head(obs.normal_maps, obs.landmarks + 0.5, model, weights=FitWeights(normals=0.5, landmarks=0.8,
                      prior=0.4), robust_scale=None, landmark_robust_scale=None, vertex_spacing=None,
                      fit_intrinsics=False, initial_pose=(fit.angles, fit.translation), rounds=1, iterations_per_round=1)
    assert float(halved.energies["normals"]) < float(fit.energies["normals"])
    # intrinsics that are not fitted are the result's own, not the caller's tensor
    given = obs.intrinsics.clone()
    fixed = fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=given, fit_intrinsics=False, rounds=1,
                     iterations_per_round=1)
    fixed.intrinsics[..., 0] *= 2.0
    assert torch.equal(given, obs.intrinsics)


def test_vertex_spacing_options(model, head):
    obs = render_oracle_views(model, head, [15.0])
    mean_err = p2p(model, model.mean, obs.vertices[0])
    for spacing in (None, (2.0, 0.75)):
        result = fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=obs.intrinsics, vertex_spacing=spacing)
        assert p2p(model, result.vertices[0], obs.vertices[0]) < 0.5 * mean_err


def test_grid_subset_thins_dense_regions_only():
    from facenormals.fitting.subsample import grid_subset

    g = torch.Generator().manual_seed(0)
    dense = torch.rand(400, 3, generator=g) * 2.0  # ~50 per unit cube
    sparse = torch.rand(20, 3, generator=g) * 2.0 + 10.0 + 3.0 * torch.arange(20.0)[:, None]  # far apart
    keep = grid_subset(torch.cat([dense, sparse]), 1.0)
    assert int(keep[:400].sum()) <= 27 and keep[400:].all()
    assert grid_subset(dense, 0.0).all()


def test_spurious_landmarks_are_rejected(model, head):
    """Two landmarks detected 25 px off (a network's spurious peaks): the Cauchy-reweighted fit stays
    near the clean one, least squares does not, and the reported landmark RMS shows the outliers."""
    obs = render_oracle_views(model, head, [10.0])
    clean = fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=obs.intrinsics)
    bad = obs.landmarks.clone()
    visible = torch.nonzero(torch.isfinite(bad[0, 0]).all(-1)).squeeze(1)
    bad[0, 0, visible[:2]] += torch.tensor([25.0, -25.0], dtype=bad.dtype)
    robust = fit_head(obs.normal_maps, bad, model, intrinsics=obs.intrinsics)
    plain = fit_head(obs.normal_maps, bad, model, intrinsics=obs.intrinsics, landmark_robust_scale=None)
    truth = obs.vertices[0]
    err_clean, err_robust, err_plain = (p2p(model, r.vertices[0], truth) for r in (clean, robust, plain))
    assert err_robust < 1.2 * err_clean + 0.05
    assert err_plain > 1.5 * err_robust
    assert float(robust.landmark_rms_px[0, 0]) > 5.0  # the RMS is of the raw errors, outliers included
    assert float(robust.landmark_median_px[0, 0]) < 1.0  # the median is not moved by two outliers


@pytest.mark.parametrize("spacing,visibility_rounds,expected", [
    ((3.0, 0.75), 2, 2),  # the default: the third round keeps the second's visibility
    ((3.0, 0.75), 3, 3),
    ((3.0, 0.75), 1, 2),  # a new vertex subset always needs a new visibility
    ((3.0, 0.75, 1.5), 1, 3),
])
def test_visibility_is_recomputed_in_the_first_rounds_and_for_new_subsets(model, head, monkeypatch, spacing,
                                                                          visibility_rounds, expected):
    from facenormals.fitting import HeadFitProblem

    calls = []
    original = HeadFitProblem.update_visibility
    monkeypatch.setattr(HeadFitProblem, "update_visibility",
                        lambda self, *a, **k: calls.append(self.vertex_subset) or original(self, *a, **k))
    obs = render_oracle_views(model, head, [10.0])
    result = fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=obs.intrinsics, vertex_spacing=spacing,
                      visibility_rounds=visibility_rounds)
    assert len(calls) == expected
    assert result.visible.shape == (1, 1, model.num_vertices) and result.visible.any()


def test_landmark_count_errors_explain_the_order(model, head):
    """Landmarks follow model.landmark_names; a model without named landmarks says so before any shape check."""
    from facenormals.models import MorphableModel

    obs = render_oracle_views(model, head, [0.0], image_size=32)
    face_only = model.with_annotations({name: model.landmarks[name] for name in model.landmark_names[:18]})
    with pytest.raises(ValueError, match=r"got \(1, 1, 24, 2\); landmarks follow model.landmark_names \(model 'builtin' "
                                         r"names 18\); the network's channels map onto them with "
                                         r"facenormals.reconstruct.landmark_channels\(model\)"):
        fit_head(obs.normal_maps, obs.landmarks, face_only)
    bare = MorphableModel(model.mean, model.shape_basis, model.faces, shape_std=model.shape_std)
    with pytest.raises(ValueError, match="has 0 named landmarks; at least 4 are needed"):
        fit_head(obs.normal_maps, obs.landmarks, bare)


def test_grid_subset_checks_its_inputs():
    """A NaN or infinite cell, or a NaN vertex, kept a single vertex silently."""
    from facenormals.fitting import grid_subset

    vertices = torch.rand(50, 3, dtype=torch.float64) * 100
    for cell in (float("nan"), float("inf"), "1"):
        with pytest.raises(ValueError, match="cell: expected a"):
            grid_subset(vertices, cell)
    bad = vertices.clone()
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match="vertices: expected finite values"):
        grid_subset(bad, 5.0)
    assert grid_subset(vertices[:0], 5.0).shape == (0,)


@pytest.mark.parametrize("axis, name", [(0, "x"), (1, "y")])
def test_a_map_with_a_flipped_axis_is_refused_naming_the_view(model, head, axis, name):
    """A mirrored map or one with y up passed the encoding checks and fitted without error to a head
    near the mean (10.8 mm from the truth where the right map gives 4.2 on ICT)."""
    obs = render_oracle_views(model, head, [-10.0, 25.0])
    flip = torch.ones(3, 1, 1)
    flip[axis] = -1.0
    maps = obs.normal_maps.clone()
    maps[0, 1] = maps[0, 1] * flip
    from facenormals.fitting import NormalAxisError

    with pytest.raises(NormalAxisError, match=f"normal_maps: view 1's {name} components point against those of the "
                                              f"head pre-aligned to its landmarks .* is the map's {name} axis flipped") as caught:
        fit_head(maps, obs.landmarks, model, intrinsics=obs.intrinsics)
    error = caught.value  # what callers such as reconstruct_views report in their own terms
    assert isinstance(error, ValueError) and (error.subject, error.view, error.axis) == (0, 1, name)
    assert error.cosine < -0.3 and error.pixels >= 50 and f"cosine {error.cosine:.2f} over {error.pixels} pixels" in str(error)


def test_flags_must_be_booleans(model, head):
    obs = render_oracle_views(model, head, [0.0])
    for name in ("fit_intrinsics", "fit_expression"):
        with pytest.raises(ValueError, match=f"{name}: expected True or False, got 'no'"):
            fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=obs.intrinsics, **{name: "no"})


def test_an_unconverged_pre_alignment_is_warned_about_by_view(model, head, monkeypatch):
    """fit_head started from a pre-aligned pose whose solve ran out of iterations without a word (its
    own status then said converged, e.g. in a wrong minimum); it now warns, naming the view."""
    import warnings

    import facenormals.fitting.fit as fit_module
    from facenormals.optim import LMStatus

    obs = render_oracle_views(model, head, [-30.0, 30.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # converged pre-alignments: no warning
        fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=obs.intrinsics, rounds=1)
    real = fit_module.prealign_pose

    def second_view_stuck(*args, **kwargs):
        pose = real(*args, **kwargs)
        pose.status[1] = LMStatus.MAX_ITERATIONS
        return pose

    monkeypatch.setattr(fit_module, "prealign_pose", second_view_stuck)
    with pytest.warns(RuntimeWarning, match=r"the landmark pre-alignment did not converge for view 1 \(\d.* px, "
                                            r"MAX_ITERATIONS\)"):
        result = fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=obs.intrinsics, rounds=1)
    assert torch.isfinite(result.vertices).all()


def _mirror_order(names):
    from facenormals.models.landmarks import LANDMARK_PAIRS

    order = list(range(len(names)))
    for a, b in LANDMARK_PAIRS:
        if a in names and b in names:
            order[names.index(a)], order[names.index(b)] = names.index(b), names.index(a)
    return order


@pytest.mark.parametrize("mistake", ["left and right swapped", "(row, column)"])
def test_landmarks_in_another_convention_are_warned_about_not_fitted_silently(model, head, mistake):
    """Regression: landmarks with the subject's left and right swapped, or given as (row, column),
    fitted a head turned away from the camera (yaw near 180 deg), status CONVERGED, without a word."""
    from facenormals.fitting import FacingAwayWarning

    obs = render_oracle_views(model, head, [0.0, 30.0])
    landmarks = (obs.landmarks[..., _mirror_order(model.landmark_names), :] if mistake.startswith("left")
                 else obs.landmarks.flip(-1))
    with pytest.warns(FacingAwayWarning, match=r"faces away from the camera in view 0 \(yaw [+-]1\d\d deg, cosine "
                                               r"0\.\d\d\), view 1 .*subject's left and right"):
        fit = fit_head(obs.normal_maps, landmarks, model, intrinsics=obs.intrinsics)
    assert bool((fit.landmark_facing > 0.3).all())


def test_landmark_facing_is_the_mean_cosine_of_the_seen_landmarks_with_their_rays(model, head):
    """FitResult.landmark_facing against a loop over the landmarks: the mean of n · X / |X| in the
    camera frame, over the given landmarks only (NaN for a view without any)."""
    import math
    import warnings

    from facenormals.mesh import vertex_normals

    obs = render_oracle_views(model, head, [-30.0, 30.0])
    mask = torch.isfinite(obs.landmarks).all(-1)
    mask[0, 1, :5] = False
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a head facing the camera: no warning
        fit = fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=obs.intrinsics, landmark_mask=mask, rounds=1)
    normals = vertex_normals(fit.vertices, fit.faces)[0].double()
    for v in range(2):
        R, t = fit.rotation[0, v].double(), fit.translation[0, v].double()
        cosines = []
        for j, i in enumerate(model.landmark_indices.tolist()):
            if mask[0, v, j]:
                X, n = R @ (fit.vertices[0, i].double() + t), R @ normals[i]
                cosines.append(float(n @ X) / float(X.norm()))
        assert math.isclose(float(fit.landmark_facing[0, v]), sum(cosines) / len(cosines), abs_tol=1e-5)
        assert float(fit.landmark_facing[0, v]) < -0.3


def test_fitted_angles_are_wrapped_to_the_conventions_range(model, head):
    """A start a full turn off (the same rotation) fitted yaw 390 deg; the angles are now in (-pi, pi]."""
    import math

    obs = render_oracle_views(model, head, [30.0])
    turned = obs.angles + torch.tensor([2 * math.pi, -2 * math.pi, 2 * math.pi])
    fit = fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=obs.intrinsics,
                   initial_pose=(turned, obs.translation), rounds=1)
    assert bool((fit.angles > -math.pi).all() and (fit.angles <= math.pi).all())
    assert abs(math.degrees(float(fit.angles[0, 0, 2])) - 30.0) < 1.0
    from facenormals.geometry import euler_to_rotation_matrix

    torch.testing.assert_close(fit.rotation[0, 0], euler_to_rotation_matrix(fit.angles[0])[0])
    torch.testing.assert_close(fit.rotation[0, 0], euler_to_rotation_matrix(obs.angles[0])[0], atol=2e-2, rtol=0)


def test_inputs_that_require_gradients_fit_as_data_without_a_warning(model, head):
    """Regression: maps straight from a network (requires_grad) raised torch's "Converting a tensor with
    requires_grad=True to a scalar" warning from inside fit_head."""
    import warnings

    obs = render_oracle_views(model, head, [0.0], image_size=64)
    plain = fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=obs.intrinsics, rounds=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit = fit_head(obs.normal_maps.clone().requires_grad_(), obs.landmarks.clone().requires_grad_(), model,
                       intrinsics=obs.intrinsics.clone().requires_grad_(), rounds=1)
    assert not fit.vertices.requires_grad
    torch.testing.assert_close(fit.vertices, plain.vertices, rtol=0, atol=0)
