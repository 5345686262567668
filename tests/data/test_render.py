import numpy as np
import pytest

from facenormals.data.render import Lighting, MeshPart, TileRenderer, TileScene
from facenormals.data.meshes import sphere_mesh
from facenormals.data import HeadlessGLError


@pytest.fixture(scope="module")
def renderer():
    try:
        r = TileRenderer((32, 32), grid=2, supersample=3)
    except HeadlessGLError as error:
        pytest.skip(f"no headless OpenGL: {error}")
    yield r
    r.close()


def _sphere_scene(center, radius=50.0, f=60.0):
    unit, faces, _ = sphere_mesh(np.linspace(0, np.pi, 24), 32)
    part = MeshPart(vertices=(unit * radius).astype(np.float32), normals=unit.astype(np.float32),
                    colors=np.full((len(unit), 3), 0.5, np.float32), faces=faces, label=3,
                    translation=np.asarray(center, float))
    light = Lighting(np.full(3, 0.5), np.array([[0.0, 0.0, -1.0]]), np.ones((1, 3)))
    return TileScene([part], np.array([f, 15.5, 15.5]), light)


def _hit_by_pixel_rays(center, radius, f=60.0):
    """``(32, 32)`` bool: the pixels whose centre ray hits the sphere of a :func:`_sphere_scene`, and
    the first hit points ``(32, 32, 3)``."""
    v, u = np.mgrid[0:32, 0:32].astype(float)
    rays = np.stack([(u - 15.5) / f, (v - 15.5) / f, np.ones_like(u)], -1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    b = rays @ center
    discriminant = b * b - (center @ center - radius**2)
    return discriminant >= 0, rays * (b - np.sqrt(np.maximum(discriminant, 0.0)))[..., None]


def test_sphere_normals_depth_and_labels(renderer):
    out = renderer.render([_sphere_scene([0.0, 0.0, 300.0])], [3])
    assert out.normals.shape == (1, 32, 32, 3) and out.labels.dtype == np.uint8
    mask = out.labels[0] == 3
    assert mask[15, 15] and not mask[0, 0] and out.coverage[0, 0, 0] == 0 and out.coverage[0, 15, 15] == 255
    v, u = np.nonzero(mask)
    # the analytic sphere: a ray through pixel (u, v) hits it where the normal is (X - C) / r
    c = np.array([0.0, 0.0, 300.0])
    hit, points = _hit_by_pixel_rays(c, 50.0)
    assert hit[mask].all()
    expected = (points[v, u] - c) / 50.0
    cosine = np.sum(out.normals[0][v, u] * expected, axis=1)
    assert np.degrees(np.arccos(np.clip(cosine, -1, 1))).mean() < 1.0  # a 24x32 polygon, not a sphere
    assert np.abs(out.depth[0][v, u] - points[v, u, 2]).max() < 1.5
    assert np.isinf(out.depth[0][~mask]).all() and (out.normals[0][~mask] == 0).all()


def test_off_centre_object_lands_on_the_right_pixels(renderer):
    """x right, y down: a sphere at +x, +y covers exactly the pixels right of and below the centre
    whose centre rays hit it (no pixel centre lies within 0.14 px of its outline; a half-pixel offset
    changes 11 of its 52 pixels)."""
    center = np.array([50.0, 35.0, 300.0])
    out = renderer.render([_sphere_scene(center, radius=20.0)])
    hit, _ = _hit_by_pixel_rays(center, 20.0)
    np.testing.assert_array_equal(out.labels[0] > 0, hit)
    v, u = np.nonzero(hit)
    assert u.mean() > 20 and v.mean() > 20  # right of and below the centre 15.5


def test_bad_tiles(renderer):
    scene = _sphere_scene([0.0, 0.0, 300.0])
    with pytest.raises(ValueError, match="distinct tiles"):
        renderer.render([scene, scene], [1, 1])
    with pytest.raises(ValueError, match="distinct tiles"):
        renderer.render([scene], [4])
    with pytest.raises(ValueError, match="expected 2 tiles"):
        renderer.render([scene, scene], [0])
    with pytest.raises(ValueError, match="supersample"):
        TileRenderer((32, 32), supersample=2)


def _part(**changes):
    unit, faces, _ = sphere_mesh(np.linspace(0, np.pi, 6), 8)
    values = dict(vertices=unit.astype(np.float32), normals=unit.astype(np.float32),
                  colors=np.full((len(unit), 3), 0.5, np.float32), faces=faces, label=1)
    values.update(changes)
    return MeshPart(**values)


def test_bad_scenes_are_named_before_drawing(renderer):
    """Out-of-range faces would make the GPU read outside the vertex buffer; a fourth light would be
    dropped by the shader's arrays of three."""
    light = Lighting(np.full(3, 0.5), np.array([[0.0, 0.0, -1.0]]), np.ones((1, 3)))
    n = len(_part().vertices)
    bad = [
        (dict(faces=np.array([[0, 1, n]])), rf"scenes\[0\]\.parts\[0\]\.faces: expected vertex indices in \[0, {n}\)"),
        (dict(faces=np.array([[0, -1, 2]])), r"parts\[0\]\.faces: expected vertex indices"),
        (dict(faces=np.array([[0.0, 1.0, 2.0]])), r"parts\[0\]\.faces: expected integers"),
        (dict(faces=np.array([0, 1, 2])), r"parts\[0\]\.faces: expected shape \(N, 3\), got \(3,\)"),
        (dict(normals=np.zeros((n - 1, 3), np.float32)), rf"parts\[0\]\.normals: expected shape \({n}, 3\)"),
        (dict(colors=np.zeros((n, 4), np.float32)), r"parts\[0\]\.colors: expected shape"),
        (dict(occlusion=np.ones(n + 1, np.float32)), r"parts\[0\]\.occlusion: expected shape"),
        (dict(vertices=np.zeros((n, 2), np.float32)), r"parts\[0\]\.vertices: expected shape \(N, 3\)"),
        (dict(rotation=np.eye(4)), r"parts\[0\]\.rotation: expected shape \(3, 3\)"),
        (dict(label=0), r"parts\[0\]\.label: expected 1..255, got 0"),
        (dict(vertices=np.full((n, 3), np.nan, np.float32)), r"parts\[0\]\.vertices: expected finite numbers"),
        (dict(normals=np.full((n, 3), np.inf, np.float32)), r"parts\[0\]\.normals: expected finite numbers"),
        (dict(translation=np.array([0.0, np.nan, 300.0])), r"parts\[0\]\.translation: expected finite numbers"),
        (dict(rotation=np.full((3, 3), np.nan)), r"parts\[0\]\.rotation: expected finite numbers"),
    ]
    for changes, match in bad:
        with pytest.raises(ValueError, match=match):
            renderer.render([TileScene([_part(**changes)], np.array([60.0, 15.5, 15.5]), light)])
    four = Lighting(np.full(3, 0.5), np.tile([[0.0, 0.0, -1.0]], (4, 1)), np.ones((4, 3)))
    with pytest.raises(ValueError, match=r"scenes\[0\]\.lighting: expected at most 3 lights, got 4"):
        renderer.render([TileScene([_part()], np.array([60.0, 15.5, 15.5]), four)])
    with pytest.raises(ValueError, match=r"scenes\[0\]\.intrinsics: expected shape \(3,\)"):
        renderer.render([TileScene([_part()], np.array([60.0, 15.5]), light)])
    with pytest.raises(ValueError, match=r"scenes\[0\]\.intrinsics: expected a focal length > 0, got -60.0"):
        renderer.render([TileScene([_part()], np.array([-60.0, 15.5, 15.5]), light)])
    with pytest.raises(ValueError, match=r"scenes\[0\]\.intrinsics: expected finite numbers"):
        renderer.render([TileScene([_part()], np.array([np.nan, 15.5, 15.5]), light)])
    dark = Lighting(np.full(3, np.nan), np.array([[0.0, 0.0, -1.0]]), np.ones((1, 3)))
    with pytest.raises(ValueError, match=r"scenes\[0\]\.lighting\.ambient: expected finite numbers"):
        renderer.render([TileScene([_part()], np.array([60.0, 15.5, 15.5]), dark)])


def test_a_closed_renderer_says_so():
    try:
        renderer = TileRenderer((16, 16), grid=1)
    except HeadlessGLError as error:
        pytest.skip(f"no headless OpenGL: {error}")
    renderer.close()
    renderer.close()  # twice is harmless
    with pytest.raises(RuntimeError, match=r"render\(\) after close\(\)"):
        renderer.render([_sphere_scene([0.0, 0.0, 300.0])])


def test_a_failed_setup_releases_the_context(monkeypatch):
    """The context is created before the shaders and framebuffers; an error there must delete it."""

    class Context:
        deleted = False

        def delete(self):
            self.deleted = True

    context = Context()
    monkeypatch.setattr("facenormals.data.gl_platform.create_gl_context", lambda: context)

    def fail(self):
        raise ValueError("image_size x supersample = 99999 exceeds the renderer's limit")

    monkeypatch.setattr(TileRenderer, "_setup", fail)
    with pytest.raises(ValueError, match="exceeds the renderer's limit"):
        TileRenderer((32, 32))
    assert context.deleted


@pytest.mark.parametrize("near,far,name", [(1000.0, 10.0, "far"), (0.0, 100.0, "near"), (-5.0, 100.0, "near"),
                                           (float("nan"), 100.0, "near"), (5.0, float("inf"), "far")])
def test_clipping_planes_are_checked_before_any_context(near, far, name):
    """Reversed or non-positive planes drew the far side of the head, or nothing, without an error."""
    with pytest.raises(ValueError, match=name):
        TileRenderer((32, 32), grid=1, near=near, far=far)
