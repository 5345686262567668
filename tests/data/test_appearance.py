import numpy as np
import pytest

from facenormals.data import HeadlessGLError
from facenormals.data.appearance import EXPOSURE_PERCENTILE, auto_exposure, sample_lighting
from facenormals.data.meshes import sphere_mesh
from facenormals.data.render import Lighting, MeshPart, TileRenderer, TileScene


def _facing_radiance(lighting, part):
    """The renderer's diffuse shading (ambient times occlusion, wrap-Lambert times the occlusion
    mixed half-way to 1), vertex by vertex, at the vertices whose normal faces the camera centre."""
    out = []
    for k in range(len(part.vertices)):
        position = np.asarray(part.rotation) @ (part.vertices[k] + part.translation)
        normal = np.asarray(part.rotation) @ part.normals[k]
        if normal @ position >= 0:
            continue
        occlusion = 1.0 if part.occlusion is None else part.occlusion[k]
        c = part.colors[k] * lighting.ambient * occlusion
        for direction, color in zip(lighting.directions, lighting.colors):
            diffuse = max((normal @ direction + part.wrap) / (1 + part.wrap), 0.0)
            c = c + part.colors[k] * diffuse * (0.5 + 0.5 * occlusion) * color
        out.append(c)
    return np.array(out)


def _sphere(rng, occlusion=True, wrap=0.3):
    unit, faces, _ = sphere_mesh(np.linspace(0, np.pi, 16), 20)
    return MeshPart(vertices=unit * 80.0, normals=unit, colors=rng.uniform(0.3, 0.9, size=(len(unit), 3)), faces=faces,
                    label=1, rotation=np.eye(3), translation=np.array([10.0, -5.0, 400.0]),
                    occlusion=rng.uniform(0.5, 1.0, size=len(unit)) if occlusion else None, wrap=wrap)


def test_auto_exposure_brings_the_percentile_to_the_target():
    rng = np.random.default_rng(0)
    part = _sphere(rng)
    bright = Lighting(np.array([0.5, 0.45, 0.4]), np.array([[0.0, -0.6, -0.8], [0.8, 0.0, -0.6]]),
                      np.array([[1.5, 1.4, 1.2], [0.8, 0.8, 0.9]]))
    before = np.percentile(_facing_radiance(bright, part).max(1), EXPOSURE_PERCENTILE)
    assert before > 1.0
    exposed = auto_exposure(bright, part, 0.85)
    after = np.percentile(_facing_radiance(exposed, part).max(1), EXPOSURE_PERCENTILE)
    np.testing.assert_allclose(after, 0.85, rtol=1e-9)
    scale = 0.85 / before
    np.testing.assert_allclose(exposed.ambient, bright.ambient * scale, rtol=1e-9)
    np.testing.assert_allclose(exposed.colors, bright.colors * scale, rtol=1e-9)
    np.testing.assert_array_equal(exposed.directions, bright.directions)


def test_auto_exposure_leaves_dim_lights_and_unseen_light():
    rng = np.random.default_rng(1)
    part = _sphere(rng, occlusion=False, wrap=0.0)
    dim = Lighting(np.full(3, 0.1), np.array([[0.0, 0.0, -1.0]]), np.full((1, 3), 0.4))
    same = auto_exposure(dim, part, 0.9)
    np.testing.assert_array_equal(same.colors, dim.colors)
    np.testing.assert_array_equal(same.ambient, dim.ambient)
    # a light from behind the head: only the far side is lit, which the camera does not see
    behind = Lighting(np.zeros(3), np.array([[0.0, 0.0, 1.0]]), np.full((1, 3), 5.0))
    np.testing.assert_array_equal(auto_exposure(behind, part, 0.9).colors, behind.colors)
    front = Lighting(np.zeros(3), np.array([[0.0, 0.0, -1.0]]), np.full((1, 3), 5.0))
    assert float(auto_exposure(front, part, 0.9).colors.max()) < 2.0  # the same light from the camera's side: dimmed


@pytest.mark.parametrize("target", [0.0, 1.5, float("nan")])
def test_auto_exposure_checks_the_target(target):
    rng = np.random.default_rng(2)
    with pytest.raises(ValueError, match="target: expected a linear value in \\(0, 1\\]"):
        auto_exposure(sample_lighting(rng), _sphere(rng), target)


def test_the_exposure_model_is_the_renderers_shading():
    """Every pixel of a rendered sphere has the colour auto_exposure assumes at the pixel's rendered
    normal n: albedo * (ambient * occlusion + max((n . l + wrap) / (1 + wrap), 0) * (1 + occlusion) / 2
    * light), sRGB-encoded; the light comes from the side, so the wrap term's soft falloff past the
    terminator is in the picture."""
    try:
        renderer = TileRenderer((32, 32), grid=1, supersample=1)
    except HeadlessGLError as error:
        pytest.skip(f"no headless OpenGL: {error}")
    albedo, occlusion, wrap = np.array([0.6, 0.5, 0.4]), 0.6, 0.25
    direction = np.array([0.8, -0.2, -0.3]) / np.linalg.norm([0.8, -0.2, -0.3])
    light = Lighting(np.array([0.2, 0.25, 0.3]), direction[None], np.array([[0.9, 0.8, 0.7]]))
    try:
        unit, faces, _ = sphere_mesh(np.linspace(0, np.pi, 48), 64)
        part = MeshPart(vertices=(unit * 50.0).astype(np.float32), normals=unit.astype(np.float32),
                        colors=np.tile(albedo, (len(unit), 1)).astype(np.float32), faces=faces, label=1,
                        translation=np.array([0.0, 0.0, 300.0]), occlusion=np.full(len(unit), occlusion, np.float32),
                        specular=0.0, wrap=wrap)
        out = renderer.render([TileScene([part], np.array([60.0, 15.5, 15.5]), light)], [0])
    finally:
        renderer.close()
    inside = out.coverage[0] == 255
    normals = out.normals[0][inside].astype(np.float64)
    diffuse = np.maximum((normals @ direction + wrap) / (1 + wrap), 0.0)
    linear = albedo * (light.ambient * occlusion + (diffuse * (0.5 + 0.5 * occlusion))[:, None] * light.colors[0])
    assert inside.sum() > 200 and (normals @ direction < -0.1).sum() > 20  # pixels past the terminator
    np.testing.assert_allclose(out.color[0][inside] / 255.0, np.clip(linear, 0, 1) ** (1 / 2.2), atol=1.5 / 255)
