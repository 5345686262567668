import numpy as np
import pytest

from facenormals.data.raycast import blocked_rays


def _naive_blocked(points, vertices, faces, tolerance):
    """A loop over every (point, triangle) pair, by another formula than the op's Möller-Trumbore:
    the ray from the origin through ``p`` meets the triangle's cone where the three signed volumes
    ``det(p, a, b)``, ``det(p, b, c)``, ``det(p, c, a)`` share a sign, at ``s = (a . n) / (p . n)``."""
    tolerance = np.broadcast_to(np.asarray(tolerance, dtype=np.float64), (len(points),))
    out = np.zeros(len(points), dtype=bool)
    for i, p in enumerate(points):
        for face in faces:
            a, b, c = vertices[face]
            volumes = [np.linalg.det(np.stack([p, x, y])) for x, y in ((a, b), (b, c), (c, a))]
            if not (all(v >= 0 for v in volumes) or all(v <= 0 for v in volumes)):
                continue
            n = np.cross(b - a, c - a)
            if p @ n == 0:
                continue
            s = (a @ n) / (p @ n)
            if 0 < s < 1 - tolerance[i] / np.linalg.norm(p):
                out[i] = True
    return out


def _soup(rng, count, spread, size):
    centres = rng.uniform(-spread, spread, size=(count, 1, 3)) + np.array([0.0, 0.0, 10.0])
    return (centres + rng.normal(scale=size, size=(count, 3, 3))).reshape(-1, 3), np.arange(3 * count).reshape(-1, 3)


@pytest.mark.parametrize("seed", range(4))
def test_blocked_rays_matches_a_naive_loop(seed):
    """Random small and large triangles, some straddling the camera plane z = 0, and points in front
    of, among and behind them, with per-point tolerances."""
    rng = np.random.default_rng(seed)
    small_v, small_f = _soup(rng, 150, 4.0, 0.3)
    large_v, large_f = _soup(rng, 3, 4.0, 2.0)
    straddle_v = np.array([[-2.0, -2, -1], [3, -1, 2], [0, 3, 1]]) + rng.normal(scale=0.3, size=(3, 3))
    vertices = np.concatenate([small_v, large_v, straddle_v])
    faces = np.concatenate([small_f, large_f + len(small_v), np.array([[0, 1, 2]]) + len(small_v) + len(large_v)])
    points = np.column_stack([rng.uniform(-4, 4, size=(150, 2)), rng.uniform(0.5, 16, size=150)])
    tolerance = rng.choice([0.0, 0.3, 2.0], size=150)
    got = blocked_rays(points, vertices, faces, tolerance)
    expected = _naive_blocked(points, vertices, faces, tolerance)
    assert got.any() and not got.all()
    np.testing.assert_array_equal(got, expected)


def test_a_large_triangle_among_small_ones_blocks_everywhere():
    """Binning keys a triangle to the cell of its box's low corner: a large one must be found by points
    far from that corner."""
    rng = np.random.default_rng(0)
    small_v, small_f = _soup(rng, 400, 4.0, 0.05)
    large = np.array([[-4.0, -4, 8], [4, -4, 8], [-4, 4, 8]])
    vertices, faces = np.concatenate([small_v, large]), np.concatenate([small_f, [[1200, 1201, 1202]]])
    points = np.column_stack([rng.uniform(-0.4, -0.1, size=(50, 2)), np.full(50, 20.0)])
    assert blocked_rays(points, vertices, faces).all()


def test_a_point_on_a_surface_is_not_blocked_by_its_own_triangles():
    """A vertex of a fan of triangles: crossings at the point itself (s = 1) never count, even with no
    tolerance; a fold 1 unit in front of it counts only beyond the tolerance."""
    fan = np.array([[0.0, 0, 10], [1, 0, 10], [0, 1, 10], [-1, 0, 10], [0, -1, 10]])
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 1]])
    assert not blocked_rays(fan[:1], fan, faces, 0.0).any()
    fold = np.concatenate([fan, fan[1:] + [0, 0, -1]])
    faces = np.concatenate([faces, np.array([[5, 6, 7], [5, 7, 8]])])
    np.testing.assert_array_equal(blocked_rays(np.repeat(fan[:1], 3, 0), fold, faces, np.array([0.5, 0.99, 1.5])),
                                  [True, True, False])


def test_a_point_on_a_random_triangle_is_not_blocked_by_it_at_zero_tolerance():
    """Float rounding puts a point's own triangle a hair in front of it (s = 1 - 1e-16): that
    crossing is the point itself, not an occluder."""
    rng = np.random.default_rng(3)
    triangles = rng.normal(size=(500, 3, 3)) * 20.0 + np.array([0.0, 0.0, 400.0])
    weights = rng.dirichlet(np.ones(3), size=500)
    weights[:100] = np.eye(3)[rng.integers(0, 3, size=100)]  # at a corner
    for k, (triangle, w) in enumerate(zip(triangles, weights)):
        point = (w @ triangle)[None]
        assert not blocked_rays(point, triangle, np.array([[0, 1, 2]]), 0.0)[0]
        if k >= 100:  # just behind an interior point (a corner's ray grazes the edges)
            assert blocked_rays(point * 1.01, triangle, np.array([[0, 1, 2]]), 0.0)[0]


def test_many_points_in_chunks_and_an_overflowing_triangle():
    """More points than one query chunk, spread wide; a triangle whose projection overflows (far to
    the side, just in front of the camera) has no usable box and is tested against every point."""
    rng = np.random.default_rng(4)
    vertices, faces = _soup(rng, 120, 30.0, 2.0)
    flat = np.array([[1e10, 1e10, 1e-300], [2e10, 1e10, 1e-300], [1e10, 2e10, 1e-300]])
    vertices, faces = np.concatenate([vertices, flat]), np.concatenate([faces, [[360, 361, 362]]])
    points = np.column_stack([rng.uniform(-30, 30, size=(300, 2)), rng.uniform(1, 16, size=300)])
    got = blocked_rays(points, vertices, faces, 0.5)
    np.testing.assert_array_equal(got, _naive_blocked(points, vertices, faces, 0.5))
    assert got.any() and not got.all()
    # a huge one just in front of the camera, across every ray: it hides everything
    cover = np.array([[-1e10, -1e10, 1e-300], [1e10, -1e10, 1e-300], [0.0, 1e10, 1e-300]])
    assert blocked_rays(points, cover, np.array([[0, 1, 2]])).all()


def test_a_ray_through_a_shared_edge_or_behind_the_camera():
    square = np.array([[-1.0, -1, 5], [1, -1, 5], [1, 1, 5], [-1, 1, 5]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    # the diagonal edge shared by both triangles, and the corners (the ends of the projected boxes)
    points = np.array([[0.5, 0.5, 10], [2.0, 2, 10], [-2, -2, 10], [2, -2, 10], [-2, 2, 10]])
    assert blocked_rays(points, square, faces).all()
    assert not blocked_rays(points * [1.001, 1.001, 1], square, faces)[1:].any()
    # triangles entirely behind the camera never block; nor do those behind the point
    behind = square * [1, 1, -1]
    assert not blocked_rays(np.array([[0.0, 0, 10]]), behind, faces).any()
    assert not blocked_rays(np.array([[0.0, 0, 4]]), square, faces).any()


def test_blocked_rays_scales_and_translates_with_its_unit():
    rng = np.random.default_rng(5)
    vertices, faces = _soup(rng, 200, 4.0, 0.5)
    points = np.column_stack([rng.uniform(-4, 4, size=(40, 2)), rng.uniform(1, 16, size=40)])
    got = blocked_rays(points, vertices, faces, 0.5)
    np.testing.assert_array_equal(blocked_rays(points * 1000, vertices * 1000, faces, 500.0), got)


def test_blocked_rays_empty_inputs():
    square = np.array([[-1.0, -1, 5], [1, -1, 5], [1, 1, 5]])
    assert blocked_rays(np.zeros((0, 3)), square, np.array([[0, 1, 2]])).shape == (0,)
    assert not blocked_rays(np.array([[0.0, 0, 10]]), square, np.zeros((0, 3), int)).any()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"points": np.zeros((2, 2))}, r"points: expected shape \(N, 3\), got \(2, 2\)"),
        ({"points": np.array([[0j, 0, 10]])}, r"points: expected finite numbers, got dtype complex128"),
        ({"points": np.array([[True, False, True]])}, r"points: expected finite numbers, got dtype bool"),
        ({"points": np.array([[1.0, 0, 1e-320]])}, r"points: expected projections x / z, y / z within float64's range"),
        ({"points": np.array([[0.0, 0, np.nan]])}, "points: expected finite numbers, got NaN or infinite values"),
        ({"points": np.array([[0.0, 0, -1]])}, r"points: expected points in front of the camera \(z > 0\)"),
        ({"vertices": np.zeros((3, 4))}, r"vertices: expected shape \(N, 3\), got \(3, 4\)"),
        ({"faces": np.array([[0, 1, 3]])}, r"faces: expected indices in \[0, 3\), got 0..3"),
        ({"faces": np.array([[0.0, 1, 2]])}, r"faces: expected an integer array of shape \(F, 3\)"),
        ({"tolerance": -1.0}, "tolerance: expected finite lengths >= 0, got -1.0"),
        ({"tolerance": True}, r"tolerance: expected finite numbers, got dtype bool"),
        ({"tolerance": np.zeros(3)}, r"tolerance: expected a number or shape \(1,\), got shape \(3,\)"),
    ],
)
def test_blocked_rays_checks_its_inputs(kwargs, match):
    args = {"points": np.array([[0.0, 0, 10]]), "vertices": np.array([[-1.0, -1, 5], [1, -1, 5], [0, 1, 5]]),
            "faces": np.array([[0, 1, 2]]), "tolerance": 0.0}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        blocked_rays(**args)
