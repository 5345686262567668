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


def test_sphere_normals_depth_and_labels(renderer):
    out = renderer.render([_sphere_scene([0.0, 0.0, 300.0])], [3])
    assert out.normals.shape == (1, 32, 32, 3) and out.labels.dtype == np.uint8
    mask = out.labels[0] == 3
    assert mask[15, 15] and not mask[0, 0] and out.coverage[0, 0, 0] == 0 and out.coverage[0, 15, 15] == 255
    v, u = np.nonzero(mask)
    # the analytic sphere: a ray through pixel (u, v) hits it where the normal is (X - C) / r
    rays = np.stack([(u - 15.5) / 60.0, (v - 15.5) / 60.0, np.ones_like(u, float)], 1)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    c = np.array([0.0, 0.0, 300.0])
    b = rays @ c
    t = b - np.sqrt(b * b - (c @ c - 50.0**2))
    hit = rays * t[:, None]
    expected = (hit - c) / 50.0
    cosine = np.sum(out.normals[0][v, u] * expected, axis=1)
    assert np.degrees(np.arccos(np.clip(cosine, -1, 1))).mean() < 1.0  # a 24x32 polygon, not a sphere
    assert np.abs(out.depth[0][v, u] - hit[:, 2]).max() < 1.5
    assert np.isinf(out.depth[0][~mask]).all() and (out.normals[0][~mask] == 0).all()


def test_off_centre_object_lands_on_the_right_pixels(renderer):
    # x right, y down: a sphere at +x, +y appears right of and below the centre
    out = renderer.render([_sphere_scene([60.0, 40.0, 300.0], radius=10.0)])
    v, u = np.nonzero(out.labels[0])
    assert abs(u.mean() - (15.5 + 60 * 60 / 300)) < 0.6 and abs(v.mean() - (15.5 + 60 * 40 / 300)) < 0.6


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
