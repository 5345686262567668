import numpy as np
import pytest
import torch
import trimesh

from facenormals.eval import (
    DepthStatistics,
    closest_points_on_mesh,
    correspondence_errors,
    depth_errors,
    depth_statistics,
    point_to_plane_errors,
)
from facenormals.eval.surface import closest_points_on_triangles, intersect_lines_along_z
from facenormals.mesh import vertex_normals


def grid(n=21, size=100.0, z=None):
    """A square grid in the plane z = z(x, y) (mm), triangles facing a viewer looking along +z."""
    xs = np.linspace(-size / 2, size / 2, n)
    x, y = np.meshgrid(xs, xs, indexing="ij")
    x, y = x.ravel(), y.ravel()
    zz = np.zeros_like(x) if z is None else z(x, y)
    index = np.arange(n * n).reshape(n, n)
    a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])  # normal along -z
    return torch.from_numpy(np.stack([x, y, zz], 1)), torch.from_numpy(faces)


def sphere(radius, subdivisions=4):
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return torch.from_numpy(np.asarray(mesh.vertices)), torch.from_numpy(np.asarray(mesh.faces)).long()


def brute_force_distance(points, tri):
    out = []
    for p in points:
        q = closest_points_on_triangles(np.repeat(p[None], len(tri), 0), tri[:, 0], tri[:, 1], tri[:, 2])
        out.append(np.sqrt(((q - p) ** 2).sum(1)).min())
    return np.array(out)


def test_closest_point_on_triangle_regions():
    a, b, c = np.array([[0.0, 0, 0]]), np.array([[2.0, 0, 0]]), np.array([[0.0, 2, 0]])
    queries = {(0.5, 0.5, 3.0): (0.5, 0.5, 0), (-1, -1, 0): (0, 0, 0), (3, -1, 1): (2, 0, 0), (-1, 3, 0): (0, 2, 0),
               (1, -2, 0): (1, 0, 0), (-2, 1, 0): (0, 1, 0), (2, 2, 0): (1, 1, 0)}  # fmt: skip
    for p, expected in queries.items():
        got = closest_points_on_triangles(np.array([p], dtype=float), a, b, c)
        np.testing.assert_allclose(got[0], expected, atol=1e-12)
    degenerate = closest_points_on_triangles(np.array([[5.0, 0, 0]]), a, a, a)
    np.testing.assert_allclose(degenerate, a)


def test_collinear_and_repeated_corner_triangles_give_the_closest_point_of_their_edges():
    rng = np.random.default_rng(0)
    k = 2000
    a, b = rng.normal(size=(k, 3)), rng.normal(size=(k, 3))
    c = a + (b - a) * rng.uniform(-1, 2, size=(k, 1))  # on the line through a and b
    c[:200] = a[:200]  # a repeated corner
    p = rng.normal(size=(k, 3)) * 2
    got = closest_points_on_triangles(p, a, b, c)
    for i in range(0, k, 7):  # naive: the best of the three segments, densely sampled
        t = np.linspace(0.0, 1.0, 2001)[:, None]
        samples = np.concatenate([a[i] + t * (b[i] - a[i]), b[i] + t * (c[i] - b[i]), c[i] + t * (a[i] - c[i])])
        best = np.sqrt(((samples - p[i]) ** 2).sum(1).min())
        assert np.linalg.norm(got[i] - p[i]) <= best + 1e-9
        assert np.linalg.norm(got[i] - p[i]) >= best - 1e-2  # the sampling step's slack


def test_closest_points_on_mesh_matches_brute_force():
    rng = np.random.default_rng(0)
    vertices, faces = sphere(40.0, subdivisions=2)
    vertices = vertices.numpy() + rng.normal(scale=2.0, size=vertices.shape)
    faces = faces.numpy()
    points = np.concatenate([rng.normal(scale=30.0, size=(60, 3)), vertices * 1.05 + rng.normal(size=vertices.shape)])
    closest, distance, triangle = closest_points_on_mesh(points, vertices, faces, k=4)
    np.testing.assert_allclose(distance, brute_force_distance(points, vertices[faces]), atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(closest - points, axis=1), distance, atol=1e-9)
    again = closest_points_on_triangles(points, *np.moveaxis(vertices[faces][triangle], 1, 0))
    np.testing.assert_allclose(again, closest, atol=1e-9)


def test_point_to_plane_identical_is_zero_and_inflated_sphere_is_one():
    vertices, faces = sphere(50.0)
    normals = vertex_normals(vertices[None], faces)[0]
    errors = point_to_plane_errors(vertices, normals, vertices, faces)
    assert errors.shape == (len(vertices),) and errors.dtype == torch.float64
    assert float(errors.abs().max()) < 1e-9
    inflated = vertices * (51.0 / 50.0)
    errors = point_to_plane_errors(vertices, normals, inflated, faces)
    assert float(errors.square().mean().sqrt()) == pytest.approx(1.0, abs=2e-3)
    assert float(errors.min()) > 0.99  # outside: positive
    shrunk = point_to_plane_errors(vertices, normals, vertices * (49.0 / 50.0), faces)
    assert float(shrunk.max()) < -0.99


def test_point_to_plane_uses_the_surface_not_the_vertices():
    vertices, faces = grid(n=3, size=100.0)  # vertices 50 mm apart
    points = torch.tensor([[10.0, 20.0, -2.0], [-30.0, 5.0, 4.0]], dtype=torch.float64)
    normals = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
    errors = point_to_plane_errors(points, normals, vertices, faces)
    torch.testing.assert_close(errors, torch.tensor([-2.0, 4.0], dtype=torch.float64))
    assert point_to_plane_errors(points.float(), normals.float(), vertices, faces).dtype == torch.float32
    # an oblique normal tells the surface (q = (10, 20, 0): -sqrt(2)) from the nearest vertex ((0, 0, 0): -8.49)
    oblique = torch.tensor([[1.0, 0.0, -1.0]], dtype=torch.float64) / 2**0.5
    torch.testing.assert_close(point_to_plane_errors(points[:1], oblique, vertices, faces),
                               torch.tensor([-(2**0.5)], dtype=torch.float64))


def test_point_to_plane_normalises_non_unit_normals():
    """The reference normals are normalised ("unit normals n_i (normalised here)"): against a tilted
    plane, whose closest point to p is its orthogonal projection, e_i = (q_i - p_i) · n_i / ‖n_i‖ in
    numpy for normals of lengths 1e-6 to 1e6 in random directions, in float64 and float32."""
    rng = np.random.default_rng(8)
    vertices, faces = grid(n=11, size=200.0, z=lambda x, y: 0.3 * x - 0.2 * y + 5.0)
    unit = np.array([-0.3, 0.2, 1.0]) / np.linalg.norm([-0.3, 0.2, 1.0])  # the plane's normal
    points = np.concatenate([rng.uniform(-40, 40, (60, 2)), rng.uniform(-20, 30, (60, 1))], 1)
    normals = rng.normal(size=(60, 3)) * 10.0 ** rng.uniform(-6, 6, (60, 1))
    closest = points - ((points - [0.0, 0.0, 5.0]) @ unit)[:, None] * unit  # the projection onto the plane
    expected = ((closest - points) * normals).sum(1) / np.linalg.norm(normals, axis=1)
    got = point_to_plane_errors(torch.from_numpy(points), torch.from_numpy(normals), vertices, faces)
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-9, atol=1e-9)
    assert np.abs(expected).max() > 5.0  # errors of all sizes, not just zeros
    single = point_to_plane_errors(torch.from_numpy(points).float(), torch.from_numpy(normals).float(), vertices, faces)
    assert single.dtype == torch.float32
    np.testing.assert_allclose(single.numpy(), expected, rtol=1e-4, atol=1e-4)


def test_point_to_plane_refuses_zero_normals():
    vertices, faces = grid(n=3, size=100.0)
    normals = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match=r"reference_normals: expected non-zero normals, got 1 zero rows \(first at index 1\)"):
        point_to_plane_errors(vertices[:2], normals, vertices, faces)


@pytest.mark.parametrize(
    "change,match",
    [
        ({"points": np.zeros((4, 2))}, r"points: expected shape \(N, 3\), got \(4, 2\)"),
        ({"points": np.full((4, 3), np.nan)}, r"points: expected finite values"),
        ({"vertices": np.full((4, 3), np.inf)}, r"vertices: expected finite values"),
        ({"faces": np.zeros((0, 3), np.int64)}, r"faces: expected shape \(F, 3\) with F >= 1, got \(0, 3\)"),
        ({"faces": np.array([[0, 1, 4]])}, r"faces: expected vertex indices in \[0, 4\), got values in \[0, 4\]"),
        ({"faces": np.array([[0, 1, -1]])}, r"faces: expected vertex indices in \[0, 4\), got values in \[-1, 1\]"),
        ({"faces": np.array([[0.0, 1.0, 2.0]])}, r"faces: expected integer vertex indices"),
    ],
)
def test_mesh_queries_check_their_inputs(change, match):
    args = {"points": np.zeros((4, 3)), "vertices": np.eye(4, 3), "faces": np.array([[0, 1, 2]])}
    args.update(change)
    for query in (closest_points_on_mesh, intersect_lines_along_z):
        with pytest.raises(ValueError, match=match):
            query(args["points"], args["vertices"], args["faces"])


def test_correspondence_errors():
    a = torch.zeros(3, 3)
    b = torch.tensor([[3.0, 4, 0], [0, 0, 0], [1, 0, 0]])
    torch.testing.assert_close(correspondence_errors(a, b), torch.tensor([5.0, 0, 1]))


def test_depth_of_shifted_plane():
    reference, _ = grid()
    shifted, faces = grid(z=lambda x, y: np.full_like(x, 2.0))
    errors = depth_errors(reference, shifted, faces)
    torch.testing.assert_close(errors, torch.full((len(reference),), 2.0, dtype=torch.float64))
    stats = depth_statistics(errors)
    assert stats == DepthStatistics(mean=2.0, std=0.0, median=2.0, delta90=2.0, coverage=1.0, count=len(reference))


def test_depth_of_tilted_plane_and_delta90_definition():
    reference, _ = grid()
    tilted, faces = grid(z=lambda x, y: 0.1 * x - 1.0)
    errors = depth_errors(reference, tilted, faces)
    expected = 0.1 * reference[:, 0] - 1.0  # exact: the plane is linear in x
    torch.testing.assert_close(errors, expected)
    stats = depth_statistics(errors)
    absolute = np.abs(expected.numpy())
    assert stats.mean == pytest.approx(absolute.mean())
    assert stats.std == pytest.approx(absolute.std())
    assert stats.median == pytest.approx(np.median(absolute))
    assert stats.delta90 == pytest.approx(np.percentile(absolute, 90))
    assert (absolute <= stats.delta90 + 1e-12).mean() >= 0.9


def test_depth_misses_view_direction_and_facing():
    reference, faces = grid()
    outside = torch.tensor([[500.0, 0.0, 0.0]], dtype=torch.float64)
    assert torch.isnan(depth_errors(outside, reference, faces)).all()
    back = faces[:, [0, 2, 1]]  # the same plane facing away from the viewer
    assert torch.isnan(depth_errors(reference, reference, back)).all()
    assert float(depth_errors(reference, reference, back, front_facing=False).abs().max()) == 0.0
    # a plane x = 3 seen along -x: rotate the grid about y by -90 degrees, so its front faces +x
    rot = torch.tensor([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]], dtype=torch.float64)
    wall = reference @ rot.T + torch.tensor([3.0, 0, 0], dtype=torch.float64)
    view = torch.tensor([-1.0, 0.0, 0.0], dtype=torch.float64)
    points = torch.tensor([[10.0, 5.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(depth_errors(points, wall, faces, view), torch.tensor([7.0], dtype=torch.float64))


def test_depth_nearest_of_several_hits():
    v, f = grid(n=3)
    layers = torch.cat([v, v + torch.tensor([0.0, 0.0, 10.0], dtype=torch.float64)])
    faces = torch.cat([f, f + len(v)])
    z = intersect_lines_along_z(np.array([[1.0, 1.0, 8.0], [1.0, 1.0, 3.0]]), layers.numpy(), faces.numpy())
    np.testing.assert_allclose(z, [10.0, 0.0])


def test_depth_of_an_edge_on_triangle_is_no_hit_and_no_warning():
    """A triangle seen edge-on (det = 0) is skipped without numpy's 'invalid value' warning."""
    import warnings

    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 1.0], [2.0, 0.0, 2.0], [0.0, 0.0, 5.0], [2.0, 0.0, 5.0],
                         [0.0, 2.0, 5.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        z = intersect_lines_along_z(np.array([[0.5, 0.0, 0.0], [0.5, 0.5, 0.0]]), vertices, np.array([[0, 1, 2],
                                                                                                      [3, 4, 5]]))
    np.testing.assert_allclose(z, [5.0, 5.0])


def test_depth_statistics_nan_and_empty():
    stats = depth_statistics(torch.tensor([1.0, -3.0, float("nan"), float("nan")]))
    assert stats.mean == 2.0 and stats.coverage == 0.5 and stats.count == 2
    empty = depth_statistics(torch.full((3,), float("nan")))
    assert np.isnan(empty.mean) and empty.coverage == 0.0 and empty.count == 0
    assert set(stats.as_dict()) == {"mean", "std", "median", "delta90", "coverage", "count"}


def test_large_mesh_against_the_sphere():
    """~10k points against ~20k triangles (the chunked path): points 1 % outside a sphere of
    radius 100 lie ~1 mm off its faceted surface along the normal (no timing asserted here; the
    eval speed is in benchmarks)."""
    vertices, faces = sphere(100.0, subdivisions=5)
    points = vertices * 1.01
    normals = vertex_normals(vertices[None], faces)[0]
    errors = point_to_plane_errors(points, normals, vertices, faces)
    assert errors.shape == (len(points),) and torch.isfinite(errors).all()
    # a vertex of the icosphere lies on the sphere; its nearest surface point is itself
    torch.testing.assert_close(errors.abs(), torch.full_like(errors, 1.0), rtol=0, atol=1e-5)


@pytest.mark.parametrize(
    "call,match",
    [
        (lambda v, f, n: point_to_plane_errors(v[:, :2], n, v, f), r"reference_vertices: expected shape \(N, 3\)"),
        (lambda v, f, n: point_to_plane_errors(v, n[:5], v, f), r"reference_normals: expected shape \(N, 3\) with N="),
        (lambda v, f, n: point_to_plane_errors(v, n, v * float("nan"), f), r"reconstruction_vertices: expected finite"),
        (lambda v, f, n: point_to_plane_errors(v * float("nan"), n, v, f), r"reference_vertices: expected finite"),
        (lambda v, f, n: point_to_plane_errors(v, n, v, f.double()), r"reconstruction_faces: expected an integer"),
        (lambda v, f, n: point_to_plane_errors(v, n, v, f + len(v)), r"reconstruction_faces: expected vertex indices"),
        (lambda v, f, n: point_to_plane_errors(v, n, v, f[:0]), r"reconstruction_faces: expected at least one"),
        (lambda v, f, n: depth_errors(v, v, f, torch.zeros(3, dtype=v.dtype)), r"view_direction: expected a non-zero"),
        (lambda v, f, n: depth_errors(v, v, f, torch.ones(2, dtype=v.dtype)), r"view_direction: expected shape \(3,\)"),
        (lambda v, f, n: correspondence_errors(v, v[:3]), r"reconstruction_vertices: expected shape \(N, 3\) with N="),
        (lambda v, f, n: depth_statistics(v), r"errors: expected shape \(N,\)"),
    ],
)
def test_bad_inputs(call, match):
    vertices, faces = sphere(10.0, subdivisions=1)
    normals = vertex_normals(vertices[None], faces)[0]
    with pytest.raises(ValueError, match=match):
        call(vertices, faces, normals)


def brute_force_lines_along_z(points, tri, front_facing=False):
    """For each query, the z of the hit nearest its own z among all triangles: a loop."""
    out = np.full(len(points), np.nan)
    for i, p in enumerate(points):
        best = np.inf
        for a, b, c in tri:
            e1, e2, d = (b - a)[:2], (c - a)[:2], (p - a)[:2]
            det = e1[0] * e2[1] - e1[1] * e2[0]
            if abs(det) <= 1e-12 * np.abs(e1).sum() * np.abs(e2).sum() or (front_facing and det >= 0):
                continue
            u, v = (d[0] * e2[1] - d[1] * e2[0]) / det, (e1[0] * d[1] - e1[1] * d[0]) / det
            if u >= -1e-9 and v >= -1e-9 and u + v <= 1 + 1e-9:
                z = a[2] + u * (b[2] - a[2]) + v * (c[2] - a[2])
                if abs(z - p[2]) < best:
                    best, out[i] = abs(z - p[2]), z
    return out


def test_lines_along_z_on_triangles_of_very_different_sizes():
    """Regression: every triangle was entered into all the cells of a grid sized by the median triangle
    that its box covers, so one large triangle among many tiny ones took (large / median)² entries
    (a 1000 mm triangle beside 0.001 mm ones: 10^12, out of memory). Size classes keep it to 4 cells."""
    rng = np.random.default_rng(5)
    tiny = rng.uniform(0, 2, (300, 1, 3)) + rng.normal(0, 0.001, (300, 3, 3))
    medium = rng.uniform(-20, 20, (40, 1, 3)) + rng.normal(0, 3.0, (40, 3, 3))
    huge = np.array([[[-500.0, -500.0, 7.0], [500.0, -500.0, 9.0], [0.0, 600.0, 8.0]]])
    tri = np.concatenate([tiny, medium, huge])
    vertices, faces = tri.reshape(-1, 3), np.arange(3 * len(tri)).reshape(-1, 3)
    points = np.concatenate([rng.uniform(-25, 25, (150, 3)), rng.uniform(0, 2, (50, 3))])
    for front in (False, True):
        np.testing.assert_allclose(intersect_lines_along_z(points, vertices, faces, front_facing=front),
                                   brute_force_lines_along_z(points, tri, front), atol=1e-9)


def test_a_view_direction_close_to_minus_z_is_exact():
    """Regression: the rotation to +z divided by 1 + cos, which loses every digit near -z: a view
    direction 1e-7 rad off -z read a 10 mm offset as 10.47 mm, and 1e-8 rad off gave NaN."""
    from facenormals.eval.metrics import _rotation_to_z

    for tilt in (0.0, 1e-12, 1e-8, 1e-7, 1e-6, 1e-3, 0.5):
        for sign in (1.0, -1.0):
            d = np.array([tilt, 0.3 * tilt, sign])
            d /= np.linalg.norm(d)
            rotation = _rotation_to_z(d)
            np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-14)
            assert abs(np.linalg.det(rotation) - 1.0) < 1e-14
            np.testing.assert_allclose(rotation @ d, [0.0, 0.0, 1.0], atol=1e-14)
    reference, _ = grid(size=90.0)  # inside the reconstruction's outline
    shifted, faces = grid(z=lambda x, y: np.full_like(x, -10.0))
    faces = faces[:, [0, 2, 1]]  # facing +z, towards a viewer looking along -z
    for tilt in (0.0, 1e-8, 1e-7):
        view = torch.tensor([tilt, 0.0, -1.0], dtype=torch.float64)
        torch.testing.assert_close(depth_errors(reference, shifted, faces, view),
                                   torch.full((len(reference),), 10.0, dtype=torch.float64))


def test_closest_points_on_slivers():
    """Regression: Ericson's regions were trusted down to sin² = 1e-24 of a triangle's angle; just above
    it they lose every digit: a sliver with sin² = 4.9e-24 gave 7.1 mm where its edge is 0.0022 mm away.
    Never farther than a dense sampling of the triangle."""
    a = np.array([-14.535506168655637, 4.274795335334727, -18.38114494250367])
    b = np.array([-87.65563316873431, -10.768101314025696, -27.809010881457873])
    c = np.array([-17.85156690872012, 3.592587015375391, -18.80870678333843])
    p = np.array([[-33.80211747156245, 0.3132106358063594, -20.866097586477157]])
    t = np.clip((p[0] - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
    closest = closest_points_on_triangles(p, a[None], b[None], c[None])
    assert np.linalg.norm(closest[0] - p[0]) == pytest.approx(np.linalg.norm(p[0] - (a + t * (b - a))), rel=1e-9)
    rng = np.random.default_rng(2)
    for flatness in (1e-13, 1e-11, 1e-9, 1e-6):
        a, b = rng.normal(0, 20, (200, 3)), rng.normal(0, 20, (200, 3))
        c = a + rng.uniform(0.1, 0.9, (200, 1)) * (b - a) + flatness * rng.normal(0, 20, (200, 3))
        points = rng.normal(0, 20, (200, 3))
        got = np.linalg.norm(closest_points_on_triangles(points, a, b, c) - points, axis=1)
        w = rng.dirichlet(np.ones(3), 4000)  # samples of each triangle: an upper bound of the distance
        sampled = np.stack([a, b, c], 1)[:, None] * w[None, :, :, None]
        bound = np.linalg.norm(sampled.sum(2) - points[:, None], axis=2).min(1)
        assert (got <= bound + 1e-6).all(), flatness


def test_depth_statistics_refuse_infinite_errors():
    """NaN means "no hit"; an infinite error was counted as a miss, lowering the coverage silently."""
    with pytest.raises(ValueError, match="errors: expected finite values or NaN .* got 1 infinite"):
        depth_statistics(torch.tensor([1.0, float("inf"), float("nan")]))


def test_closest_points_on_mesh_checks_k():
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    for k in (0, 1.5, True):
        with pytest.raises(ValueError, match="k: expected an integer"):
            closest_points_on_mesh(np.zeros((1, 3)), v, np.array([[0, 1, 2]]), k=k)
