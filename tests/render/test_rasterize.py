import pytest
import torch

from facenormals.geometry import euler_to_rotation_matrix, project_points, transform_points
from facenormals.render import interpolate_vertex_attributes, rasterize_depth, rasterize_triangles
from tests.conftest import assert_close


def naive_cover(uv, tri, height, width):
    """Pixel centres covered by a 2D triangle, by a loop over all pixels."""
    (x0, y0), (x1, y1), (x2, y2) = uv[tri].tolist()
    area = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
    covered = torch.zeros(height, width, dtype=torch.bool)
    for v in range(height):
        for u in range(width):
            w0 = ((x1 - u) * (y2 - v) - (y1 - v) * (x2 - u)) / area
            w1 = ((x2 - u) * (y0 - v) - (y2 - v) * (x0 - u)) / area
            covered[v, u] = w0 >= -1e-9 and w1 >= -1e-9 and 1 - w0 - w1 >= -1e-9
    return covered


def test_coverage_matches_naive_loop():
    g = torch.Generator().manual_seed(0)
    for _ in range(5):
        uv = torch.rand(1, 3, 2, generator=g, dtype=torch.float64) * torch.tensor([30.0, 20.0]) - 3
        frags = rasterize_triangles(uv, torch.ones(1, 3, dtype=torch.float64), torch.tensor([[0, 1, 2]]), (18, 25))
        assert torch.equal(frags.mask[0], naive_cover(uv[0], [0, 1, 2], 18, 25))


def test_z_buffer_keeps_nearest():
    uv = torch.tensor([[[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [0.0, 0.0], [10.0, 0.0], [0.0, 10.0]]])
    depth = torch.tensor([[5.0, 5.0, 5.0, 2.0, 2.0, 2.0]])
    frags = rasterize_triangles(uv, depth, torch.tensor([[0, 1, 2], [3, 4, 5]]), (12, 12))
    assert (frags.face_index[frags.mask] == 1).all()
    assert_close(frags.depth[frags.mask], torch.full_like(frags.depth[frags.mask], 2.0))
    assert torch.isinf(frags.depth[~frags.mask]).all()


def test_perspective_correct_barycentrics_reproject_to_pixel_centres():
    # A tilted quad in 3D: interpolated camera points must project back onto the pixel centres.
    points = torch.tensor([[[-40.0, -40.0, 0.0], [40.0, -40.0, 30.0], [40.0, 40.0, 60.0], [-40.0, 40.0, 20.0]]],
                          dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    R = euler_to_rotation_matrix(torch.tensor([[0.1, 0.2, 0.3]], dtype=torch.float64))
    t = R.transpose(1, 2) @ torch.tensor([0.0, 0.0, 300.0], dtype=torch.float64)
    K = torch.tensor([[200.0, 31.5, 30.0]], dtype=torch.float64)
    uv, z = project_points(points, R, t, K)
    frags = rasterize_triangles(uv, z, faces, (64, 64))
    cam = interpolate_vertex_attributes(frags, faces, transform_points(points, R, t))  # (1, 3, H, W)
    vv, uu = torch.nonzero(frags.mask[0], as_tuple=True)
    X = cam[0, :, vv, uu]
    assert_close(200.0 * X[0] / X[2] + 31.5, uu.double(), atol=1e-8, rtol=0)
    assert_close(200.0 * X[1] / X[2] + 30.0, vv.double(), atol=1e-8, rtol=0)
    assert_close(X[2], frags.depth[0, vv, uu])
    assert frags.mask.sum() > 500


def test_backface_culling_keeps_the_faces_towards_the_camera():
    """A triangle wound counter-clockwise seen from the camera (its outward normal, by the right-hand
    rule, points at the camera) is kept; the same triangle wound the other way is culled."""
    points = torch.tensor([[[-1.0, -1.0, 5.0], [-1.0, 1.0, 5.0], [1.0, -1.0, 5.0]]], dtype=torch.float64)
    outward = torch.linalg.cross(points[0, 1] - points[0, 0], points[0, 2] - points[0, 0])
    assert float(outward[2]) < 0  # towards the camera at the origin
    R, t = torch.eye(3, dtype=torch.float64)[None], torch.zeros(1, 3, dtype=torch.float64)
    uv, z = project_points(points, R, t, torch.tensor([[25.0, 5.5, 5.5]], dtype=torch.float64))
    facing, away = torch.tensor([[0, 1, 2]]), torch.tensor([[0, 2, 1]])
    plain = rasterize_triangles(uv, z, facing, (12, 12)).mask
    assert plain.sum() > 10
    assert torch.equal(rasterize_triangles(uv, z, facing, (12, 12), cull_backfaces=True).mask, plain)
    assert not rasterize_triangles(uv, z, away, (12, 12), cull_backfaces=True).mask.any()


def test_backface_culling_leaves_the_visible_surface_of_a_closed_head():
    """The z-buffer already shows front faces only, so culling must not change the depth map."""
    from facenormals.models import builtin_head_model

    model = builtin_head_model()
    R, t = torch.eye(3, dtype=torch.float64)[None], torch.tensor([[0.0, 0.0, 600.0]], dtype=torch.float64)
    uv, z = project_points(model.mean[None].double(), R, t, torch.tensor([[300.0, 31.5, 31.5]], dtype=torch.float64))
    plain = rasterize_depth(uv, z, model.faces, (64, 64))
    culled = rasterize_depth(uv, z, model.faces, (64, 64), cull_backfaces=True)
    fg = torch.isfinite(plain)
    assert fg.sum() > 500 and torch.equal(torch.isfinite(culled), fg)
    assert_close(culled[fg], plain[fg])


def test_behind_camera_skipped_and_batch():
    uv = torch.tensor([[[0.0, 0.0], [9.0, 0.0], [0.0, 9.0]]]).repeat(2, 1, 1)
    depth = torch.tensor([[1.0, 1.0, 1.0], [1.0, -1.0, 1.0]])
    frags = rasterize_triangles(uv, depth, torch.tensor([[0, 1, 2]]), (10, 10))
    assert frags.mask[0].sum() == 55 and frags.mask[1].sum() == 0


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(pixels=torch.zeros(1, 3, 3)), r"pixels: expected shape \(B, N, 2\)"),
        (dict(depth=torch.zeros(2, 3)), r"depth: expected shape \(B, N\) with B=1"),
        (dict(faces=torch.zeros(1, 3)), "faces: expected an integer tensor"),
        (dict(faces=torch.ones(1, 3, dtype=torch.bool)), "faces: expected an integer tensor"),
        (dict(faces=torch.tensor([[0, 1, 3]])), r"faces: expected vertex indices in \[0, 3\), got values in \[0, 3\]"),
        (dict(image_size=(0, 4)), r"image_size: expected \(H, W\), two integers >= 1, got \(0, 4\)"),
        (dict(image_size=(4.5, 4)), r"image_size: expected \(H, W\), two integers >= 1, got \(4.5, 4\)"),
        (dict(image_size=4), r"image_size: expected \(H, W\)"),
    ],
)
@pytest.mark.parametrize("fn", [rasterize_triangles, rasterize_depth])
def test_bad_input(kwargs, match, fn):
    args = dict(pixels=torch.zeros(1, 3, 2), depth=torch.ones(1, 3), faces=torch.tensor([[0, 1, 2]]), image_size=(4, 4))
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        fn(**args)


def test_interpolation_checks_the_faces():
    uv = torch.tensor([[[0.0, 0.0], [9.0, 0.0], [0.0, 9.0], [9.0, 9.0]]])
    faces = torch.tensor([[0, 1, 2], [1, 3, 2]])
    frags = rasterize_triangles(uv, torch.ones(1, 4), faces, (10, 10))
    with pytest.raises(ValueError, match=r"faces: expected vertex indices in \[0, 4\)"):
        interpolate_vertex_attributes(frags, torch.tensor([[0, 1, 2], [1, 4, 2]]), torch.ones(1, 4, 2))
    with pytest.raises(ValueError, match="faces: expected the 2 or more triangles"):
        interpolate_vertex_attributes(frags, faces[:1], torch.ones(1, 4, 2))
    with pytest.raises(ValueError, match="attributes: expected a floating-point tensor, got dtype torch.int64"):
        interpolate_vertex_attributes(frags, faces, torch.tensor([[[10], [20], [30], [40]]]))


@pytest.mark.parametrize("cull", [False, True])
def test_z_buffer_matches_a_naive_loop_over_pixels_and_triangles(cull):
    """Overlapping triangles of all sizes in two batch elements, crossing the image's borders, some
    behind the camera: each pixel's nearest triangle and depth, by a loop over every pixel and triangle."""
    g = torch.Generator().manual_seed(5)
    uv = torch.rand(2, 40, 2, generator=g, dtype=torch.float64) * torch.tensor([28.0, 22.0]) - 4
    depth = torch.rand(2, 40, generator=g, dtype=torch.float64) * 10 + 1
    depth[1, :4] = -1.0
    faces = torch.randint(0, 40, (25, 3), generator=g)
    frags = rasterize_triangles(uv, depth, faces, (17, 21), cull_backfaces=cull)
    for b in range(2):
        best = torch.full((17, 21), float("inf"), dtype=torch.float64)
        face = torch.full((17, 21), -1)
        for f, tri in enumerate(faces.tolist()):
            (x0, y0), (x1, y1), (x2, y2) = uv[b, tri].tolist()
            area = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
            if min(depth[b, tri].tolist()) <= 1e-6 or abs(area) <= 1e-12 or (cull and area >= 0):
                continue
            covered = naive_cover(uv[b], tri, 17, 21)
            for v, u in covered.nonzero().tolist():
                w0 = ((x1 - u) * (y2 - v) - (y1 - v) * (x2 - u)) / area
                w1 = ((x2 - u) * (y0 - v) - (y2 - v) * (x0 - u)) / area
                z = 1.0 / sum(w / d for w, d in zip((w0, w1, 1 - w0 - w1), depth[b, tri].tolist()))
                if z < best[v, u]:
                    best[v, u], face[v, u] = z, f
        assert torch.equal(frags.face_index[b], face)
        assert_close(frags.depth[b], best, atol=1e-12, rtol=1e-12)
    assert 100 < int(frags.mask.sum()) < 2 * 17 * 21


@pytest.mark.parametrize("cull", [False, True])
def test_depth_only_equals_full_rasteriser(cull):
    # Random overlapping triangles in two batch elements, some behind the camera or off-screen.
    g = torch.Generator().manual_seed(3)
    uv = torch.rand(2, 60, 2, generator=g, dtype=torch.float64) * 50 - 5
    depth = torch.rand(2, 60, generator=g, dtype=torch.float64) * 10 + 1
    depth[1, :5] = -1.0
    faces = torch.randint(0, 60, (40, 3), generator=g)
    full = rasterize_triangles(uv, depth, faces, (40, 45), cull_backfaces=cull)
    z = rasterize_depth(uv, depth, faces, (40, 45), cull_backfaces=cull)
    assert z.dtype == uv.dtype and torch.equal(z, full.depth)
    assert full.mask.sum() > 300 and torch.isinf(z[~full.mask]).all()


def test_near_and_mixed_dtypes_are_checked():
    uv = torch.tensor([[[0.0, 0.0], [9.0, 0.0], [0.0, 9.0]]])
    faces = torch.tensor([[0, 1, 2]])
    for near in (float("nan"), -1.0, "0.1"):  # NaN used to give an empty render
        for op in (rasterize_triangles, rasterize_depth):
            with pytest.raises(ValueError, match="near: expected a"):
                op(uv, torch.ones(1, 3), faces, (10, 10), near=near)
    # float64 depths used to come back rounded to float32
    with pytest.raises(ValueError, match=r"depth: expected dtype torch.float32 \(the dtype of pixels\), got torch.float64"):
        rasterize_depth(uv, torch.ones(1, 3, dtype=torch.float64), faces, (10, 10))
    z = rasterize_depth(uv.double(), torch.full((1, 3), 1000.0001, dtype=torch.float64), faces, (10, 10))
    assert z.dtype == torch.float64 and abs(z[0, 0, 0].item() - 1000.0001) < 1e-9


def test_exact_depth_ties_go_to_the_first_triangle_with_its_own_barycentrics():
    """Regression: tied triangles were written with two separate index_put_ calls over duplicate pixels,
    whose order torch leaves undefined (parallel on CUDA), so a pixel could get one triangle's index and
    another's barycentrics. Now the triangle listed first wins, and its barycentrics come with it."""
    uv = torch.tensor([[[1.0, 1.0], [20.0, 2.0], [3.0, 17.0]]], dtype=torch.float64).repeat(1, 2, 1)
    depth = torch.tensor([[4.0, 6.0, 5.0]], dtype=torch.float64).repeat(1, 2)  # a copy of the triangle
    first, second = [0, 1, 2], [3, 4, 5]  # the same triangle twice: bit-identical depths
    values = torch.cat([torch.zeros(1, 3, 1), torch.ones(1, 3, 1)], 1).double()  # 0 on the first, 1 on the copy
    for faces, expected in (([first, second], 0.0), ([second, first], 1.0)):
        frags = rasterize_triangles(uv, depth, torch.tensor(faces), (20, 24))
        assert int(frags.mask.sum()) > 100 and bool((frags.face_index[frags.mask] == 0).all())
        shaded = interpolate_vertex_attributes(frags, torch.tensor(faces), values)[0, 0]
        assert_close(shaded[frags.mask[0]], torch.full_like(shaded[frags.mask[0]], expected), atol=1e-12, rtol=0)
    # on a regular grid (ties along every shared edge) the barycentrics rebuild each pixel centre
    # from the winning triangle's corners
    n = 12
    gv, gu = torch.meshgrid(torch.arange(n, dtype=torch.float64), torch.arange(n, dtype=torch.float64), indexing="ij")
    uv = torch.stack([gu, gv], -1).reshape(1, -1, 2) * 3.0
    idx = torch.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].reshape(-1), idx[:-1, 1:].reshape(-1), idx[1:, :-1].reshape(-1), idx[1:, 1:].reshape(-1)
    faces = torch.cat([torch.stack([a, c, b], 1), torch.stack([b, c, d], 1)])
    frags = rasterize_triangles(uv, torch.full((1, n * n), 5.0, dtype=torch.float64), faces, (34, 34))
    assert bool(frags.mask.all())
    rebuilt = (frags.barycentric[0][..., None] * uv[0][faces[frags.face_index[0]]]).sum(-2)
    gv, gu = torch.meshgrid(torch.arange(34.0, dtype=torch.float64), torch.arange(34.0, dtype=torch.float64),
                            indexing="ij")
    assert_close(rebuilt, torch.stack([gu, gv], -1), atol=1e-9, rtol=0)


def test_long_thin_triangles_are_tested_on_their_own_bounding_box(monkeypatch):
    """Regression: each triangle was tested on a square grid of its longest side, so 64 slivers of
    2000 x 1 px took 17 GB; grids now follow each axis and go in bounded chunks, with the same result."""
    from facenormals.render import rasterize as module

    uv = torch.tensor([[[0.0, 0.0], [1990.0, 0.5], [0.0, 1.0]]], dtype=torch.float64)
    extent = torch.tensor([[[1991.0, 2.0]]], dtype=torch.float64)
    assert [(w, h) for _, w, h in module._buckets(extent)] == [(2048, 2)]
    g = torch.Generator().manual_seed(1)
    uv = torch.rand(2, 60, 2, generator=g, dtype=torch.float64) * torch.tensor([70.0, 40.0]) - 5
    depth = torch.rand(2, 60, generator=g, dtype=torch.float64) + 1
    faces = torch.randint(0, 60, (80, 3), generator=g)
    whole = rasterize_triangles(uv, depth, faces, (30, 60))
    monkeypatch.setattr(module, "_CELLS_PER_CHUNK", 64)  # many chunks per bucket, some of one triangle
    chunked = rasterize_triangles(uv, depth, faces, (30, 60))
    assert torch.equal(whole.face_index, chunked.face_index) and torch.equal(whole.depth, chunked.depth)
    assert torch.equal(whole.barycentric, chunked.barycentric)
    assert torch.equal(rasterize_depth(uv, depth, faces, (30, 60)), whole.depth)


def test_a_mesh_without_triangles_interpolates_to_background():
    uv, depth, faces = torch.zeros(1, 3, 2), torch.ones(1, 3), torch.zeros(0, 3, dtype=torch.long)
    frags = rasterize_triangles(uv, depth, faces, (4, 5))
    assert not bool(frags.mask.any())
    assert torch.equal(interpolate_vertex_attributes(frags, faces, torch.ones(1, 3, 2)), torch.zeros(1, 2, 4, 5))


def test_non_finite_attributes_are_named():
    uv = torch.tensor([[[0.0, 0.0], [9.0, 0.0], [0.0, 9.0]]])
    faces = torch.tensor([[0, 1, 2]])
    frags = rasterize_triangles(uv, torch.ones(1, 3), faces, (10, 10))
    with pytest.raises(ValueError, match="attributes: expected finite values, got 1 NaN"):
        interpolate_vertex_attributes(frags, faces, torch.tensor([[[1.0], [float("nan")], [0.0]]]))


def test_interpolate_vertex_attributes_names_fragments_of_the_wrong_type():
    from facenormals.render import interpolate_vertex_attributes

    with pytest.raises(ValueError, match="fragments: expected the Fragments of rasterize_triangles, got NoneType"):
        interpolate_vertex_attributes(None, torch.tensor([[0, 1, 2]]), torch.ones(1, 3, 2))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_triangle_listed_twice_in_another_corner_order_is_drawn_by_its_first_copy(dtype):
    """Regression: each copy's depth is rounded differently with the order of its corners (~1 ulp),
    so the exact-tie rule almost never applied and the copies speckled (float64: the first copy on
    147 of 432 pixels). Depths within a relative 2^-40 are ties now: the first copy wins everywhere,
    with its own barycentrics; the z-buffer is the nearest depth as before."""
    uv = torch.tensor([[[0.3, 0.2], [30.7, 2.1], [4.2, 28.9]]], dtype=dtype)
    z = torch.tensor([[1.3, 2.7, 4.1]], dtype=dtype)
    for copy in ([1, 2, 0], [2, 0, 1], [0, 2, 1], [2, 1, 0]):  # cyclic shifts and reversed orders
        for faces in (torch.tensor([[0, 1, 2], copy]), torch.tensor([copy, [0, 1, 2]])):
            frags = rasterize_triangles(uv, z, faces, (32, 32))
            mask = frags.mask[0]
            assert int(mask.sum()) == 432 and bool((frags.face_index[frags.mask] == 0).all()), (copy, faces)
            # the barycentrics are the first copy's: with its corners they interpolate the depth
            rebuilt = interpolate_vertex_attributes(frags, faces, z[..., None])[0, 0]
            assert_close(rebuilt[mask], frags.depth[0][mask], atol=1e-5, rtol=0)
            assert torch.equal(frags.depth, rasterize_depth(uv, z, faces, (32, 32)))


def _one_triangle_fragments(batch=2):
    uv = torch.tensor([[[0.0, 0.0], [9.0, 0.0], [0.0, 9.0]]]).repeat(batch, 1, 1)
    faces = torch.tensor([[0, 1, 2]])
    return rasterize_triangles(uv, torch.ones(batch, 3), faces, (10, 10)), faces


@pytest.mark.parametrize(
    "field, make, match",
    [
        ("barycentric", lambda f: f.barycentric[0],
         r"fragments.barycentric: expected shape \(B, H, W, 3\) \(4 dimensions\), got \(10, 10, 3\)"),
        ("barycentric", lambda f: f.barycentric[..., :2], r"fragments.barycentric: expected shape \(B, H, W, 3\), got \(2, 10, 10, 2\)"),
        ("barycentric", lambda f: f.barycentric[:0], r"fragments.barycentric: expected shape \(B, H, W, 3\) with B=2"),
        ("barycentric", lambda f: f.barycentric.long(), "fragments.barycentric: expected a floating-point tensor, got dtype torch.int64"),
        ("barycentric", lambda f: f.barycentric.double(),
         r"fragments.barycentric: expected dtype torch.float32 \(the dtype of attributes\), got torch.float64"),
        ("barycentric", lambda f: f.barycentric.clone().index_fill_(1, torch.tensor([1]), float("nan")),
         "fragments.barycentric: expected finite values, got 60 NaN or infinite entries"),
        ("face_index", lambda f: f.face_index.float(), "fragments.face_index: expected an integer tensor, got dtype torch.float32"),
        ("face_index", lambda f: f.face_index.bool(), "fragments.face_index: expected an integer tensor, got dtype torch.bool"),
    ],
)
def test_interpolate_vertex_attributes_checks_the_fragments(field, make, match):
    """Regression: a (H, W, 3) barycentric broadcast silently, an integer one gave wrong values, a NaN
    one NaN pixels, and a float face_index or a barycentric of last dimension 2 failed deep inside."""
    import dataclasses

    frags, faces = _one_triangle_fragments()
    bad = dataclasses.replace(frags, **{field: make(frags)})
    with pytest.raises(ValueError, match=match):
        interpolate_vertex_attributes(bad, faces, torch.rand(2, 3, 2))

