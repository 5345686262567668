import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from facenormals.eval import ICPResult, fit_similarity, icp_point_to_plane
from facenormals.mesh import vertex_normals


@pytest.fixture(scope="module")
def surface():
    """A bumpy ellipsoid (mm) with outward vertex normals, float64."""
    sphere = trimesh.creation.icosphere(subdivisions=4)
    u = np.asarray(sphere.vertices)
    radius = 1.0 + 0.08 * np.sin(3 * u[:, 0]) * np.cos(2 * u[:, 1]) + 0.05 * np.sin(4 * u[:, 2])
    vertices = torch.from_numpy(u * radius[:, None] * np.array([60.0, 80.0, 100.0]))
    faces = torch.from_numpy(np.asarray(sphere.faces)).long()
    return vertices, vertex_normals(vertices[None], faces)[0]


def true_transform(scale, degrees=8.0):
    rot = Rotation.from_rotvec(np.deg2rad(degrees) * np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]))
    return (1.06 if scale else 1.0), torch.from_numpy(rot.as_matrix()), torch.tensor([4.0, -3.0, 2.0], dtype=torch.float64)


def inverse_map(points, s, rot, t):
    return ((points - t) @ rot) / s


def transform_error(result_s, result_r, result_t, s, rot, t):
    return max(abs(result_s - s), float((result_r - rot).abs().max()), float((result_t - t).abs().max()))


@pytest.mark.parametrize("scale", [False, True], ids=["rigid", "similarity"])
@pytest.mark.parametrize("direction", ["source_to_target", "target_to_source"])
def test_recovers_known_transform(surface, scale, direction):
    target, normals = surface
    s, rot, t = true_transform(scale)
    source = inverse_map(target, s, rot, t)
    result = icp_point_to_plane(source, target, normals, scale=scale, tolerance=1e-10, direction=direction)
    assert isinstance(result, ICPResult) and result.converged
    assert transform_error(result.s, result.R, result.t, s, rot, t) < 1e-6
    assert result.rmse < 1e-6 and result.num_pairs == len(target)
    assert result.R.dtype == torch.float64 and abs(float(torch.det(result.R)) - 1) < 1e-12


def test_init_is_used_and_partial_target(surface):
    """A 'face region' target (front half) against a whole source, started from a landmark-like fit."""
    target, normals = surface
    s, rot, t = true_transform(True, degrees=25.0)
    source = inverse_map(target, s, rot, t)
    front = target[:, 2] < 0
    pick = torch.nonzero(front)[:12, 0]
    init = fit_similarity(source[pick][None] + 0.5, target[pick][None])  # rough, noisy start
    result = icp_point_to_plane(source, target[front], normals[front], init=init, scale=True,
                                direction="target_to_source", tolerance=1e-10)
    assert transform_error(result.s, result.R, result.t, s, rot, t) < 1e-6
    assert result.num_pairs == int(front.sum())


def point_to_point_icp(source, target, iterations, scale):
    tree = cKDTree(target.numpy())
    s, rot, t = 1.0, torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
    for _ in range(iterations):
        x = s * source @ rot.T + t
        _, j = tree.query(x.numpy())
        s_fit, r_fit, t_fit = fit_similarity(source[None], target[j][None], scale=scale)
        s, rot, t = float(s_fit[0]), r_fit[0], t_fit[0]
    return s, rot, t


def test_faster_than_point_to_point(surface):
    target, normals = surface
    s, rot, t = true_transform(False)
    source = inverse_map(target, s, rot, t)
    result = icp_point_to_plane(source, target, normals, tolerance=1e-10)
    plane_error = transform_error(result.s, result.R, result.t, s, rot, t)
    p2p_error = transform_error(*point_to_point_icp(source, target, result.iterations, False), s, rot, t)
    assert result.iterations <= 10
    assert plane_error < 1e-6 and p2p_error > 1e-3


def test_rejection_of_distant_pairs(surface):
    target, normals = surface
    s, rot, t = true_transform(False, degrees=5.0)
    outliers = target[::10] + 60.0 * normals[::10]
    source = inverse_map(torch.cat([target, outliers]), s, rot, t)
    kept = icp_point_to_plane(source, target, normals, max_distance=20.0, tolerance=1e-10)
    assert transform_error(kept.s, kept.R, kept.t, s, rot, t) < 1e-6
    assert kept.num_pairs == len(target)
    biased = icp_point_to_plane(source, target, normals, tolerance=1e-10)
    assert transform_error(biased.s, biased.R, biased.t, s, rot, t) > 1e-2


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"source_points": torch.zeros(5, 2)}, r"source_points: expected shape \(N, 3\), got \(5, 2\)"),
        ({"target_normals": torch.zeros(4, 3)}, r"target_normals: expected shape \(M, 3\) with M=6"),
        ({"target_points": torch.full((6, 3), float("nan"))}, r"target_points: expected finite values"),
        ({"init": (1.0, torch.eye(3))}, r"init: expected a tuple \(s, R, t\)"),
        ({"init": (1.0, torch.eye(2), torch.zeros(3))}, r"init: expected R of shape"),
        ({"init": (-1.0, torch.eye(3), torch.zeros(3))}, r"init: expected finite values and a positive scale"),
        ({"init": ("2", torch.eye(3), torch.zeros(3))}, r"init: expected real numbers for the scale s, got str '2'"),
        ({"init": (True, torch.eye(3), torch.zeros(3))}, r"init: expected real numbers for the scale s, got bool True"),
        ({"init": (torch.tensor(True), torch.eye(3), torch.zeros(3))}, r"init: expected real numbers for the scale s, "
                                                                       r"got Tensor of dtype torch.bool"),
        ({"init": (1 + 0j, torch.eye(3), torch.zeros(3))}, r"init: expected real numbers for the scale s, got complex"),
        ({"init": (torch.tensor(2 + 1j), torch.eye(3), torch.zeros(3))}, r"init: expected real numbers for the scale "
                                                                         r"s, got Tensor of dtype torch.complex64"),
        ({"init": (float("inf"), torch.eye(3), torch.zeros(3))}, r"init: expected finite values and a positive scale, "
                                                                 r"got s = inf"),
        ({"init": (1.0, "R", torch.zeros(3))}, r"init: expected real numbers for R, got str"),
        ({"init": (1.0, torch.eye(3).bool(), torch.zeros(3))}, r"init: expected real numbers for R, got Tensor of "
                                                                 r"dtype torch.bool"),
        ({"init": (1.0, torch.eye(3), [0, 0, "a"])}, r"init: expected real numbers for t, got list"),
        ({"init": (1.0, torch.diag(torch.tensor([1.0, 1, -1])), torch.zeros(3))}, r"init: expected R to be a rotation .* det -1"),
        ({"init": (1.0, 2 * torch.eye(3), torch.zeros(3))}, r"init: expected R to be a rotation \(orthonormal"),
        ({"direction": "both"}, r"direction: expected one of"),
        ({"max_distance": -1.0}, r"max_distance: expected a positive number"),
        ({"max_iterations": 2.5}, r"max_iterations: expected an integer, got float 2.5"),
        ({"max_iterations": -1}, r"max_iterations: expected an integer >= 0, got -1"),
        ({"tolerance": "x"}, r"tolerance: expected a real number, got str"),
        ({"max_distance": "1"}, r"max_distance: expected a positive number or None, got '1'"),
        ({"target_normals": torch.zeros(6, 3)}, r"target_normals: expected at least 6 non-zero normals to fit a rigid transform, got 0"),
    ],
)
def test_bad_inputs(kwargs, match):
    args = {"source_points": torch.randn(5, 3), "target_points": torch.randn(6, 3), "target_normals": torch.randn(6, 3)}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        icp_point_to_plane(**args)


def test_a_two_cycle_of_closest_pairs_counts_as_converged(ict_npz):
    """Between two different ICT heads the closest pairs can alternate between two sets for ever: ICP
    ran to max_iterations, reported not converged, and returned whichever of the two states the
    iteration count's parity left it in."""
    from facenormals.models import load_ict_npz

    model = load_ict_npz(ict_npz, dtype=torch.float64)
    g = torch.Generator().manual_seed(1)
    for _ in range(3):
        coeffs = torch.randn(model.num_shape, generator=g, dtype=torch.float64)
    prediction = model((coeffs * model.shape_std)[None])[0]  # the third identity of that seed cycled
    region = model.face_region
    points = model.mean[region]
    normals = vertex_normals(model.mean[None], model.faces)[0][region]
    init = fit_similarity(prediction[model.landmark_indices][None], model.mean[model.landmark_indices][None],
                          scale=False)
    results = {n: icp_point_to_plane(prediction, points, normals, init=init, scale=False, max_iterations=n,
                                     direction="target_to_source") for n in (50, 51)}
    assert all(r.converged and r.iterations < 50 for r in results.values())
    assert results[50].rmse == results[51].rmse  # the same state, whatever the parity of the limit
