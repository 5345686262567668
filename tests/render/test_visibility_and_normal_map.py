import math

import pytest
import torch

from facenormals.geometry import euler_to_rotation_matrix, project_points, transform_points
from facenormals.mesh import vertex_normals
from facenormals.models import builtin_head_model
from facenormals.render import rasterize_depth, rasterize_triangles, render_normal_map, unoccluded_points, visible_vertices
from facenormals.sampling import sample_bicubic


@pytest.fixture(scope="module")
def posed_head():
    model = builtin_head_model(dtype=torch.float64)
    vertices = model(torch.zeros(1, model.num_shape, dtype=torch.float64))
    R = euler_to_rotation_matrix(torch.tensor([[0.05, 0.1, math.radians(35)]], dtype=torch.float64))
    t = torch.tensor([[0.0, 0.0, 650.0]], dtype=torch.float64) @ R[0]
    K = torch.tensor([[500.0, 95.5, 95.5]], dtype=torch.float64)
    return model, vertices, R, t, K


def test_normal_map_is_unit_on_foreground_and_zero_elsewhere(posed_head):
    model, vertices, R, t, K = posed_head
    nmap, frags = render_normal_map(vertices, model.faces, R, t, K, (192, 192))
    norm = nmap.norm(dim=1)
    assert torch.allclose(norm[frags.mask], torch.ones_like(norm[frags.mask]), atol=1e-9)
    assert (nmap.permute(0, 2, 3, 1)[~frags.mask] == 0).all()
    # visible surfaces face the camera: the normal points against the viewing ray
    assert (nmap[:, 2][frags.mask] < 0.2).float().mean() > 0.99


def test_normal_map_agrees_with_vertex_normals_at_visible_vertices(posed_head):
    model, vertices, R, t, K = posed_head
    nmap, frags = render_normal_map(vertices, model.faces, R, t, K, (192, 192))
    pixels, depth = project_points(vertices, R, t, K)
    normals = vertex_normals(vertices, model.faces) @ R.transpose(1, 2)
    vis = visible_vertices(pixels, depth, normals, transform_points(vertices, R, t), frags.depth)
    sampled, inside = sample_bicubic(nmap, pixels)
    # away from the silhouette (all 4x4 taps on the foreground)
    cos = torch.nn.functional.cosine_similarity(sampled, normals, dim=-1)
    interior = vis & inside & (normals[..., 2] < -0.3)
    angle = torch.rad2deg(torch.acos(cos[interior].clamp(-1, 1)))
    assert interior.sum() > 1000
    assert angle.median() < 1.5, angle.median()


def test_visibility_hides_the_far_side(posed_head):
    model, vertices, R, t, K = posed_head
    pixels, depth = project_points(vertices, R, t, K)
    zbuf = rasterize_triangles(pixels, depth, model.faces, (192, 192)).depth
    normals = vertex_normals(vertices, model.faces) @ R.transpose(1, 2)
    vis = visible_vertices(pixels, depth, normals, transform_points(vertices, R, t), zbuf)
    lm = model.landmarks
    # yaw +35 deg turns the face towards image left, showing the subject's left side
    assert vis[0, lm["nose_tip"]] and vis[0, lm["left_ear_top"]]
    assert not vis[0, lm["right_ear_top"]]
    # the back of the head is hidden
    back = vertices[0, :, 2] > 60
    assert vis[0, back].float().mean() < 0.05


def test_visibility_bad_input():
    with pytest.raises(ValueError, match=r"zbuffer: expected shape \(B, H, W\) with B=1"):
        visible_vertices(torch.zeros(1, 2, 2), torch.ones(1, 2), torch.zeros(1, 2, 3), torch.zeros(1, 2, 3),
                         torch.zeros(2, 4, 4))


def test_unoccluded_points_against_a_loop():
    """Inside the image, in front of the camera, and within the slack of the z-buffer read at the
    point: 1/z interpolated bilinearly between the four pixel centres around it, or the nearest
    pixel's depth where one of them is background or off the image."""
    g = torch.Generator().manual_seed(3)
    zbuffer = torch.rand(2, 5, 7, generator=g, dtype=torch.float64) * 10 + 5
    zbuffer[0, 2, 3] = float("inf")  # background
    pixels = torch.rand(2, 40, 2, generator=g, dtype=torch.float64) * torch.tensor([9.0, 7.0]) - 1.0
    depth = torch.rand(2, 40, generator=g, dtype=torch.float64) * 20 - 1.0
    pixels[1, :3] = float("nan")  # points that project nowhere
    got = unoccluded_points(pixels, depth, zbuffer, tolerance=2.0)
    for b in range(2):
        for i in range(40):
            if math.isnan(float(pixels[b, i, 0])):
                assert not bool(got[b, i])
                continue
            x, y = float(pixels[b, i, 0]), float(pixels[b, i, 1])
            u, v = math.floor(x + 0.5), math.floor(y + 0.5)  # the pixel whose square holds the point
            inside = 0 <= u <= 6 and 0 <= v <= 4 and float(depth[b, i]) > 0
            surface = float(zbuffer[b, min(max(v, 0), 4), min(max(u, 0), 6)])
            left, top = math.floor(x), math.floor(y)
            if 0 <= left and left + 1 <= 6 and 0 <= top and top + 1 <= 4:
                corners = [(left + du, top + dv, (1 - abs(x - left - du)) * (1 - abs(y - top - dv)))
                           for du in (0, 1) for dv in (0, 1)]
                if all(math.isfinite(float(zbuffer[b, cv, cu])) for cu, cv, _ in corners):
                    surface = 1.0 / sum(w / float(zbuffer[b, cv, cu]) for cu, cv, w in corners)
            expected = inside and float(depth[b, i]) <= surface + 2.0
            assert bool(got[b, i]) == expected, (b, i)
    assert 0 < int(got.sum()) < 80
    with pytest.raises(ValueError, match=r"zbuffer: expected shape \(B, H, W\)"):
        unoccluded_points(pixels, depth, zbuffer[0])


def test_splat_zbuffer_ignores_points_that_project_nowhere():
    from facenormals.render import splat_zbuffer

    g = torch.Generator().manual_seed(4)
    pixels = torch.rand(1, 30, 2, generator=g) * 8
    depth = torch.rand(1, 30, generator=g) * 10 + 1
    with_nan = torch.cat([pixels, torch.full((1, 2, 2), float("nan"))], 1)
    expected = splat_zbuffer(pixels, depth, (8, 8))
    assert torch.equal(splat_zbuffer(with_nan, torch.cat([depth, torch.ones(1, 2)], 1), (8, 8)), expected)
    with pytest.raises(ValueError, match="image_size"):
        splat_zbuffer(pixels, depth, (0, 8))
    with pytest.raises(ValueError, match="depth: expected a floating-point tensor"):
        splat_zbuffer(pixels, depth.long(), (8, 8))
    with pytest.raises(ValueError, match="radius: expected an integer, got float 1.5"):
        splat_zbuffer(pixels, depth, (8, 8), radius=1.5)
    with pytest.raises(ValueError, match="radius: expected an integer >= 0, got -1"):
        splat_zbuffer(pixels, depth, (8, 8), radius=-1)


def test_given_normals_must_match_the_vertices(posed_head):
    model, vertices, R, t, K = posed_head
    normals = vertex_normals(vertices, model.faces)
    nmap, _ = render_normal_map(vertices, model.faces, R, t, K, (32, 32), normals=normals)
    assert nmap.dtype == torch.float64
    with pytest.raises(ValueError, match=r"normals: expected dtype torch.float64 \(the dtype of vertices\), got torch.float32"):
        render_normal_map(vertices, model.faces, R, t, K, (32, 32), normals=normals.float())
    with pytest.raises(ValueError, match=r"rotation: expected dtype torch.float64 \(the dtype of vertices\), got torch.float32"):
        render_normal_map(vertices, model.faces, R.float(), t, K, (32, 32))
    with pytest.raises(ValueError, match=r"translation: expected shape \(B, 3\), got \(1, 2\)"):
        render_normal_map(vertices, model.faces, R, t[:, :2], K, (32, 32))


def test_unoccluded_points_checks_the_tolerance():
    with pytest.raises(ValueError, match="tolerance: expected a finite number >= 0, got nan"):
        unoccluded_points(torch.ones(1, 1, 2), torch.ones(1, 1), torch.ones(1, 3, 3), tolerance=float("nan"))


def test_unoccluded_points_refuse_a_nan_depth_unless_the_point_projects_nowhere():
    """Regression: a NaN depth read as hidden, silently."""
    zbuffer = torch.full((1, 3, 3), 5.0)
    with pytest.raises(ValueError, match="depth: expected finite values, got 1 NaN"):
        unoccluded_points(torch.tensor([[[1.0, 1.0]]]), torch.tensor([[float("nan")]]), zbuffer)
    nowhere = torch.tensor([[[float("nan"), float("nan")], [1.0, 1.0]]])
    assert unoccluded_points(nowhere, torch.tensor([[float("nan"), 5.0]]), zbuffer).tolist() == [[False, True]]


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_reads_the_right_pixel(dtype):
    """The flat pixel index v * W + u is integer arithmetic: in float16 (exact up to 2048) or bfloat16
    (256) it would name a neighbouring pixel of a 64-wide image."""
    from facenormals.render import splat_zbuffer

    zbuffer = torch.full((1, 64, 64), math.inf)
    zbuffer[0, 40, 1] = 1.0
    pixels, depth = torch.tensor([[[1.0, 40.0]]]), torch.tensor([[5.0]])
    assert not bool(unoccluded_points(pixels, depth, zbuffer)[0, 0])  # behind the surface at (40, 1)
    assert not bool(unoccluded_points(pixels.to(dtype), depth.to(dtype), zbuffer.to(dtype))[0, 0])
    splat = splat_zbuffer(torch.tensor([[[1.0, 40.0]]], dtype=dtype), torch.tensor([[2.0]], dtype=dtype), (64, 64), 0)
    assert splat.dtype == dtype and float(splat[0, 40, 1]) == 2.0 and torch.isinf(splat[0, 40, 0])


def test_nan_inputs_are_errors_not_background(posed_head):
    """NaN vertices, normals or poses would silently read as background, hidden or back-facing."""
    model, vertices, R, t, K = posed_head
    bad = vertices.clone()
    bad[0, 10] = math.nan
    with pytest.raises(ValueError, match="vertices: expected finite values, got 3 NaN"):
        render_normal_map(bad, model.faces, R, t, K, (32, 32))
    with pytest.raises(ValueError, match="normals: expected finite values"):
        render_normal_map(vertices, model.faces, R, t, K, (32, 32), normals=torch.full_like(vertices, math.nan))
    with pytest.raises(ValueError, match="rotation: expected finite values"):
        render_normal_map(vertices, model.faces, R * math.nan, t, K, (32, 32))
    with pytest.raises(ValueError, match="points: expected finite values, got 3 NaN"):
        project_points(bad, R, t, K)
    pixels, depth = project_points(vertices, R, t, K)
    with pytest.raises(ValueError, match="pixels: expected finite values"):
        rasterize_triangles(pixels.index_fill(1, torch.tensor([10]), math.nan), depth, model.faces, (32, 32))
    with pytest.raises(ValueError, match="depth: expected finite values"):
        rasterize_depth(pixels, depth.index_fill(1, torch.tensor([10]), math.inf), model.faces, (32, 32))
    pixels, depth = project_points(vertices, R, t, K)
    camera = transform_points(vertices, R, t)
    normals = vertex_normals(vertices, model.faces) @ R.transpose(1, 2)
    zbuffer = torch.full((1, 32, 32), math.inf, dtype=vertices.dtype)
    with pytest.raises(ValueError, match="camera_normals: expected finite values"):
        visible_vertices(pixels, depth, normals * math.nan, camera, zbuffer)
    with pytest.raises(ValueError, match="min_facing: expected a finite number, got nan"):
        visible_vertices(pixels, depth, normals, camera, zbuffer, min_facing=math.nan)
    with pytest.raises(ValueError, match="min_facing: expected a real number, got str"):
        visible_vertices(pixels, depth, normals, camera, zbuffer, min_facing="0.2")
    with pytest.raises(ValueError, match="zbuffer: expected no NaN values, got 1024 NaN entries"):
        unoccluded_points(pixels, depth, zbuffer * math.nan)


def test_empty_batches_and_images():
    """B = 0 gives an empty answer; a z-buffer without pixels is an error naming it."""
    empty = unoccluded_points(torch.zeros(0, 5, 2), torch.zeros(0, 5), torch.zeros(0, 4, 4))
    assert empty.shape == (0, 5) and empty.dtype == torch.bool
    with pytest.raises(ValueError, match=r"zbuffer: expected H, W >= 1, got shape \(1, 0, 4\)"):
        unoccluded_points(torch.zeros(1, 5, 2), torch.ones(1, 5), torch.zeros(1, 0, 4))


def _grid(n: int, half: float, z: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """A flat ``n`` x ``n`` grid of vertices in the plane ``z``, facing -z, and its triangles."""
    xs = torch.linspace(-half, half, n, dtype=torch.float64)
    gy, gx = torch.meshgrid(xs, xs, indexing="ij")
    vertices = torch.stack([gx, gy, torch.full_like(gx, z)], -1).reshape(-1, 3)
    idx = torch.arange(n * n).reshape(n, n)
    a, b, c, d = (idx[:-1, :-1].reshape(-1), idx[:-1, 1:].reshape(-1), idx[1:, :-1].reshape(-1),
                  idx[1:, 1:].reshape(-1))
    return vertices, torch.cat([torch.stack([a, b, c], 1), torch.stack([b, d, c], 1)])


def test_a_sloped_surface_does_not_hide_its_own_vertices_at_coarse_resolution():
    """Regression: the z-buffer was read at the nearest pixel centre, up to 0.71 px away, where a
    plane at 60 degrees is ~9 mm nearer at 5 mm per pixel: 47 % of the plane's vertices were
    'hidden' behind the plane itself with a 1 mm slack. Read with 1/z interpolated between the four
    centres around the vertex, a plane is exact; points behind it stay hidden."""
    plane, faces = _grid(41, 50.0)
    R = euler_to_rotation_matrix(torch.tensor([[0.0, 0.0, math.radians(60)]], dtype=torch.float64))
    t = torch.tensor([[0.0, 0.0, 500.0]], dtype=torch.float64) @ R[0]
    K = torch.tensor([[100.0, 15.5, 15.5]], dtype=torch.float64)
    pixels, depth = project_points(plane[None], R, t, K)
    zbuffer = rasterize_depth(pixels, depth, faces, (32, 32))
    u0, v0 = pixels[0, :, 0].floor().long(), pixels[0, :, 1].floor().long()
    fg = torch.isfinite(zbuffer[0])
    surrounded = fg[v0, u0] & fg[v0, u0 + 1] & fg[v0 + 1, u0] & fg[v0 + 1, u0 + 1]
    assert int(surrounded.sum()) > 1000
    seen = unoccluded_points(pixels, depth, zbuffer, tolerance=1e-6)[0]
    assert bool(seen[surrounded].all())
    # the same lines of sight 5 mm further: behind the plane
    behind = unoccluded_points(pixels, depth + 5.0, zbuffer, tolerance=1e-6)[0]
    assert not bool(behind[surrounded].any())


def test_a_sloped_surface_at_its_silhouette_completes_the_plane_from_three_corners():
    """Regression: where one of the four centres around a vertex was background, the nearest pixel's
    depth was read, several mm off on a steep plane: 56 of 139 such vertices of this plane hid behind
    the plane itself, and 34 points 5 mm behind it counted as seen. The plane through the three
    other centres is exact."""
    plane, faces = _grid(41, 50.0)
    R = euler_to_rotation_matrix(torch.tensor([[0.0, math.radians(20), math.radians(60)]], dtype=torch.float64))
    R = R @ euler_to_rotation_matrix(torch.tensor([[math.radians(30), 0.0, 0.0]], dtype=torch.float64))
    t = torch.tensor([[0.0, 0.0, 500.0]], dtype=torch.float64) @ R[0]
    K = torch.tensor([[100.0, 15.5, 15.5]], dtype=torch.float64)
    pixels, depth = project_points(plane[None], R, t, K)
    zbuffer = rasterize_depth(pixels, depth, faces, (32, 32))
    u0, v0 = pixels[0, :, 0].floor().long(), pixels[0, :, 1].floor().long()
    inside = (u0 >= 0) & (v0 >= 0) & (u0 <= 30) & (v0 <= 30)
    u0, v0 = u0.clamp(0, 30), v0.clamp(0, 30)
    fg = torch.isfinite(zbuffer[0])
    corners = fg[v0, u0].int() + fg[v0, u0 + 1].int() + fg[v0 + 1, u0].int() + fg[v0 + 1, u0 + 1].int()
    three = inside & (corners == 3)
    assert int(three.sum()) > 100
    assert bool(unoccluded_points(pixels, depth, zbuffer, tolerance=1e-6)[0][three].all())
    assert not bool(unoccluded_points(pixels, depth + 5.0, zbuffer, tolerance=1e-6)[0][three].any())


def test_splat_zbuffer_refuses_a_nan_depth_at_a_finite_pixel():
    """Such a point was dropped from the z-buffer silently (unoccluded_points refuses it); a NaN pixel
    projects nowhere and stays allowed."""
    from facenormals.render import splat_zbuffer

    with pytest.raises(ValueError, match="depth: expected a finite depth for every finite pixel, got 1 NaN or infinite"):
        splat_zbuffer(torch.tensor([[[1.0, 1.0]]]), torch.tensor([[float("nan")]]), (3, 3), 0)
    zbuf = splat_zbuffer(torch.tensor([[[float("nan"), 1.0], [1.0, 1.0]]]), torch.tensor([[float("nan"), 2.0]]), (3, 3), 0)
    assert zbuf[0, 1, 1] == 2.0
    with pytest.raises(ValueError, match="depth"):
        splat_zbuffer(torch.tensor([[[1.0, 1.0]]]), torch.tensor([[2.0]], dtype=torch.float64), (3, 3), 0)


def test_a_zbuffer_with_zero_or_negative_depths_is_an_error():
    """Regression: a z-buffer with 0 on background (OpenGL's and pyrender's convention) was accepted
    and hid every point over the background, silently; only NaN was refused."""
    from facenormals.render import splat_zbuffer

    zbuffer = torch.full((1, 4, 4), math.inf)
    zbuffer[0, :2, :2] = 500.0
    pixels, depth = torch.tensor([[[0.0, 0.0], [3.0, 3.0]]]), torch.tensor([[500.0, 520.0]])
    assert unoccluded_points(pixels, depth, zbuffer).tolist() == [[True, True]]
    zero = torch.where(torch.isinf(zbuffer), torch.zeros_like(zbuffer), zbuffer)
    with pytest.raises(ValueError, match=r"zbuffer: expected depths > 0 with inf on background, got 12 values <= 0 "
                                         r"\(minimum 0\)"):
        unoccluded_points(pixels, depth, zero)
    for bad in (-zbuffer.nan_to_num(posinf=1.0), zbuffer.index_fill(2, torch.tensor([3]), -math.inf)):
        with pytest.raises(ValueError, match="zbuffer: expected depths > 0 with inf on background"):
            unoccluded_points(pixels, depth, bad)
    normals, camera = torch.tensor([[[0.0, 0.0, -1.0]] * 2]), torch.tensor([[[0.0, 0.0, 500.0], [0.0, 0.0, 520.0]]])
    with pytest.raises(ValueError, match="zbuffer: expected depths > 0"):
        visible_vertices(pixels, depth, normals, camera, zero)
    # a splatted z-buffer is always accepted: it keeps only depths > 0
    splat = splat_zbuffer(torch.tensor([[[1.0, 1.0], [2.0, 2.0]]]), torch.tensor([[-3.0, 0.0]]), (4, 4), 1)
    assert bool(torch.isinf(splat).all()) and unoccluded_points(pixels, depth, splat).tolist() == [[True, True]]


def test_splat_zbuffer_refuses_an_infinite_depth_at_a_finite_pixel_as_unoccluded_points_does():
    """Regression: splat_zbuffer dropped such a point silently while unoccluded_points refused it."""
    from facenormals.render import splat_zbuffer

    for value in (math.inf, -math.inf):
        depth = torch.tensor([[2.0, value]])
        pixels = torch.tensor([[[1.0, 1.0], [2.0, 1.0]]])
        with pytest.raises(ValueError, match="depth: expected a finite depth for every finite pixel, got 1 NaN or "
                                             "infinite"):
            splat_zbuffer(pixels, depth, (3, 3), 0)
        with pytest.raises(ValueError, match="depth: expected finite values"):
            unoccluded_points(pixels, depth, torch.full((1, 3, 3), 5.0))
        nowhere = torch.tensor([[[1.0, 1.0], [math.inf, 1.0]]])  # e.g. a point on the camera's plane
        assert splat_zbuffer(nowhere, depth, (3, 3), 0)[0, 1, 1] == 2.0
        assert unoccluded_points(nowhere, depth, torch.full((1, 3, 3), 5.0)).tolist() == [[True, False]]


@pytest.mark.parametrize("width", [4, 5])
def test_the_image_is_the_union_of_half_open_pixel_squares_on_every_edge(width):
    """Regression: torch.round rounds half to even, so u = W - 0.5 was inside for odd W and outside
    for even W, while u = -0.5 was always inside. Pixel (u, v) now covers [u - 0.5, u + 0.5) x
    [v - 0.5, v + 0.5) on every edge, in unoccluded_points and splat_zbuffer alike."""
    from facenormals.render import splat_zbuffer

    height = 3
    zbuffer = torch.full((1, height, width), 5.0, dtype=torch.float64)
    cases = [((-0.5, 1.0), (0, 1)), ((-0.5 - 1e-9, 1.0), None), ((width - 0.5 - 1e-9, 1.0), (width - 1, 1)),
             ((width - 0.5, 1.0), None), ((1.0, -0.5), (1, 0)), ((1.0, -0.5 - 1e-9), None),
             ((1.0, height - 0.5 - 1e-9), (1, height - 1)), ((1.0, height - 0.5), None), ((1.5, 1.5), (2, 2)),
             ((2.5, 0.5), (3, 1))]
    for (u, v), pixel in cases:
        point, depth = torch.tensor([[[u, v]]], dtype=torch.float64), torch.tensor([[5.0]], dtype=torch.float64)
        assert bool(unoccluded_points(point, depth, zbuffer)[0, 0]) == (pixel is not None), (u, v)
        splat = splat_zbuffer(point, depth, (height, width), 0)[0]
        written = torch.isfinite(splat).nonzero().tolist()
        assert written == ([] if pixel is None else [[pixel[1], pixel[0]]]), (u, v, written)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_points_go_to_their_own_pixel_far_from_the_origin(dtype):
    """u + 0.5 in bfloat16 (float16) rounds a whole u above 128 (1024) half to even: the nearest
    pixel is found in float32."""
    from facenormals.render import splat_zbuffer

    size = 2048 if dtype == torch.float16 else 256
    column = size // 2 + 1  # odd, so that column + 0.5 rounds up to the even neighbour
    point, depth = torch.tensor([[[column, 1.0]]], dtype=dtype), torch.tensor([[2.0]], dtype=dtype)
    splat = splat_zbuffer(point, depth, (3, size), 0)
    assert torch.isfinite(splat[0]).nonzero().tolist() == [[1, column]]


@pytest.mark.parametrize("radius", [0, 1, 2])
def test_splat_zbuffer_gap_fill_against_a_loop(radius):
    """Each point inside the image and in front of the camera writes its depth to the pixel whose
    square holds it (the nearest depth wins); a pixel no point wrote takes the least written depth of
    its (2r+1)² window (clipped at the image's edges), inf where there is none; a written pixel keeps
    its own depth, even beside a nearer one."""
    from facenormals.render import splat_zbuffer

    g = torch.Generator().manual_seed(5)
    height, width = 9, 11
    pixels = torch.rand(2, 30, 2, generator=g, dtype=torch.float64) * torch.tensor([width + 1.0, height + 1.0]) - 1.0
    depth = torch.rand(2, 30, generator=g, dtype=torch.float64) * 20 + 1.0
    depth[0, :3] = -depth[0, :3]  # behind the camera
    pair = ((pixels[1] + 0.5).floor() == torch.tensor([4.0, 4.0], dtype=torch.float64)).all(-1) | \
        ((pixels[1] + 0.5).floor() == torch.tensor([5.0, 4.0], dtype=torch.float64)).all(-1)
    pixels[1, pair] = -3.0  # off the image, leaving the pixels (4, 4) and (5, 4) to...
    pixels[1, 0], depth[1, 0] = torch.tensor([4.2, 3.9], dtype=torch.float64), 50.0  # ...a far point...
    pixels[1, 1], depth[1, 1] = torch.tensor([5.1, 4.3], dtype=torch.float64), 0.5  # ...beside a near one
    got = splat_zbuffer(pixels, depth, (height, width), radius)
    assert got.shape == (2, height, width) and got.dtype == torch.float64
    for b in range(2):
        written = [[math.inf] * width for _ in range(height)]
        for i in range(30):
            u, v = math.floor(float(pixels[b, i, 0]) + 0.5), math.floor(float(pixels[b, i, 1]) + 0.5)
            if 0 <= u < width and 0 <= v < height and float(depth[b, i]) > 0:
                written[v][u] = min(written[v][u], float(depth[b, i]))
        for y in range(height):
            for x in range(width):
                expected = written[y][x]
                if math.isinf(expected):
                    expected = min(written[yy][xx] for yy in range(max(0, y - radius), min(height, y + radius + 1))
                                   for xx in range(max(0, x - radius), min(width, x + radius + 1)))
                assert float(got[b, y, x]) == expected, (b, y, x, radius)
    assert float(got[1, 4, 4]) == 50.0 and float(got[1, 4, 5]) == 0.5
    empty = torch.isinf(got).sum().item()
    assert (empty > 0) if radius == 0 else (empty < torch.isinf(splat_zbuffer(pixels, depth, (height, width), 0)).sum())


def test_visible_vertices_min_facing_against_a_loop():
    """A vertex is front-facing when n · X_c / ‖X_c‖ < -min_facing (strictly), checked with a loop for
    margins of either sign; visibility is that and the occlusion test of unoccluded_points."""
    g = torch.Generator().manual_seed(6)
    normals = torch.nn.functional.normalize(torch.randn(2, 200, 3, generator=g, dtype=torch.float64), dim=-1)
    camera = torch.randn(2, 200, 3, generator=g, dtype=torch.float64) * 40
    camera[..., 2] += 300.0  # in front of the camera, rays up to ~10° off the axis
    camera[0, :50] *= 10.0  # farther points: the same rays, the same cosines
    K = torch.tensor([[100.0, 15.5, 15.5]] * 2, dtype=torch.float64)
    pixels, depth = project_points(camera, torch.eye(3, dtype=torch.float64).expand(2, 3, 3),
                                   torch.zeros(2, 3, dtype=torch.float64), K)
    zbuffer = torch.full((2, 32, 32), math.inf, dtype=torch.float64)
    zbuffer[:, :, :12] = 290.0  # hides the points behind it on the left of the image
    occlusion = unoccluded_points(pixels, depth, zbuffer, tolerance=3.0)
    assert 0 < int(occlusion.sum()) < 400
    for min_facing in (-0.3, 0.0, 0.2, 0.6):
        got = visible_vertices(pixels, depth, normals, camera, zbuffer, tolerance=3.0, min_facing=min_facing)
        fronts = 0
        for b in range(2):
            for i in range(200):
                n, x = normals[b, i].tolist(), camera[b, i].tolist()
                cosine = sum(nk * xk for nk, xk in zip(n, x)) / math.sqrt(sum(xk * xk for xk in x))
                fronts += cosine < -min_facing
                assert bool(got[b, i]) == (cosine < -min_facing and bool(occlusion[b, i])), (min_facing, b, i)
        assert 0 < fronts < 400, min_facing
    # the margin is strict: a normal along the ray back to the camera (cosine -1) fails a margin of 1
    n, x = torch.tensor([[[0.0, 0.0, -1.0]]]), torch.tensor([[[0.0, 0.0, 5.0]]])
    uv, z, zbuf = torch.tensor([[[1.0, 1.0]]]), torch.tensor([[5.0]]), torch.full((1, 3, 3), 5.0)
    assert visible_vertices(uv, z, n, x, zbuf, min_facing=0.999).tolist() == [[True]]
    assert visible_vertices(uv, z, n, x, zbuf, min_facing=1.0).tolist() == [[False]]
