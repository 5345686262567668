import math

import numpy as np
import pytest
import torch

from facenormals.models import builtin_head_model
from facenormals.render import render_shaded, shade_normal_map


def test_lambert_against_a_loop_and_background_stays_black():
    g = torch.Generator().manual_seed(0)
    n = torch.nn.functional.normalize(torch.randn(2, 3, 4, 5, generator=g, dtype=torch.float64), dim=1)
    n[:, :, 0, 0] = 0.0  # background
    light, ambient = (0.2, -0.4, -1.0), 0.1
    shaded = shade_normal_map(n, light, ambient)
    assert shaded.shape == (2, 1, 4, 5) and shaded.dtype == torch.float64
    norm = math.sqrt(sum(c * c for c in light))
    for b in range(2):
        for i in range(4):
            for j in range(5):
                normal = n[b, :, i, j].tolist()
                if (i, j) == (0, 0):
                    expected = 0.0
                else:
                    lambert = max(0.0, sum(a * c / norm for a, c in zip(normal, light)))
                    expected = ambient + (1 - ambient) * lambert
                assert shaded[b, 0, i, j].item() == pytest.approx(expected, abs=1e-12)


def test_the_default_light_comes_from_the_upper_right_in_front():
    tilt = 0.5  # normals facing the camera (-z), tilted towards image right (+x), left, up (-y), down
    n = torch.tensor([[tilt, 0, -1], [-tilt, 0, -1], [0, -tilt, -1], [0, tilt, -1]])
    n = torch.nn.functional.normalize(n, dim=1).T.reshape(1, 3, 1, 4)
    right, left, up, down = shade_normal_map(n)[0, 0, 0].tolist()
    assert right > left and up > down


def test_render_shaded_lights_a_head_facing_the_camera():
    model = builtin_head_model()
    rotation = torch.eye(3)[None]  # the model frame shows the face frontally (docs/conventions.md)
    image = render_shaded(model.mean[None], model.faces, rotation, torch.tensor([[0.0, 0.0, 600.0]]),
                          torch.tensor([[100.0, 32.0, 32.0]]), (64, 64))
    assert image.shape == (1, 1, 64, 64)
    assert float(image[0, 0, 32, 32]) > 0.5 and float(image[0, 0, 0, 0]) == 0.0


def test_shading_checks_its_arguments():
    n = torch.zeros(1, 3, 2, 2)
    with pytest.raises(ValueError, match=r"normal_map: expected shape \(B, 3, H, W\) \(4 dimensions\), got \(3, 4, 4\)"):
        shade_normal_map(torch.zeros(3, 4, 4))
    with pytest.raises(ValueError, match="normal_map: expected a floating-point tensor"):
        shade_normal_map(n.long())
    with pytest.raises(ValueError, match="light: expected a non-zero finite direction"):
        shade_normal_map(n, light=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="light: expected a non-zero finite direction"):
        shade_normal_map(n, light=(0.0, 1.0))
    with pytest.raises(ValueError, match=r"ambient: expected a value in \[0, 1\]"):
        shade_normal_map(n, ambient=1.5)
    with pytest.raises(ValueError, match="normal_map: expected finite values, got 1 NaN"):  # read as background before
        shade_normal_map(torch.tensor([[[[float("nan")]], [[0.0]], [[-1.0]]]]))


def test_light_and_ambient_must_be_numbers():
    nmap = torch.zeros(1, 3, 2, 2)
    nmap[:, 2] = -1.0
    with pytest.raises(ValueError, match="light: expected a non-zero finite direction"):
        shade_normal_map(nmap, light="abc")
    with pytest.raises(ValueError, match="ambient: expected a real number, got str"):
        shade_normal_map(nmap, ambient="0.2")


def test_render_shaded_lights_a_posed_plane_by_lambert_in_the_camera_frame():
    """``light`` points from the surface to the light in the camera frame: a flat plane posed off-axis
    (so that its camera-frame normal R m differs from its model-frame normal m) renders 0.15 + 0.85
    max(0, R m · l / ‖l‖) on every pixel it covers (the default ambient), 0 elsewhere, for lights of
    any length from either side of it, the default light included."""
    from facenormals.geometry import euler_to_rotation_matrix

    xs = torch.linspace(-60.0, 60.0, 9, dtype=torch.float64)
    gy, gx = torch.meshgrid(xs, xs, indexing="ij")
    vertices = torch.stack([gx, gy, torch.zeros_like(gx)], -1).reshape(1, -1, 3)
    index = torch.arange(81).reshape(9, 9)
    a, b, c, d = index[:-1, :-1].reshape(-1), index[:-1, 1:].reshape(-1), index[1:, :-1].reshape(-1), index[1:, 1:].reshape(-1)
    faces = torch.cat([torch.stack([a, c, b], 1), torch.stack([b, c, d], 1)])
    p = vertices[0, faces[0]].numpy()
    normal = np.cross(p[1] - p[0], p[2] - p[0])  # counter-clockwise winding: the outward normal
    normal /= np.linalg.norm(normal)
    assert np.allclose(normal, [0.0, 0.0, -1.0])  # towards a camera at the identity pose
    R = euler_to_rotation_matrix(torch.tensor([[0.1, 0.35, -0.5]], dtype=torch.float64))
    t = torch.tensor([[0.0, 0.0, 500.0]], dtype=torch.float64) @ R[0]  # X_c = R p + (0, 0, 500)
    K = torch.tensor([[200.0, 31.5, 31.5]], dtype=torch.float64)
    camera_normal = R[0].numpy() @ normal
    assert camera_normal[2] < -0.5 and np.abs(camera_normal[:2]).min() > 0.05  # facing the camera, off-axis
    rng = np.random.default_rng(9)
    lights = [None, (0.0, 0.0, -1.0), (0.0, 0.0, 2.0), (1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 3.0, 0.0),
              (0.0, -0.5, 0.0), (0.3, -0.5, 1.0)] + [tuple(rng.normal(size=3) * 10.0 ** rng.uniform(-2, 2))
                                                     for _ in range(8)]
    lit, covered = 0, None
    for light in lights:
        image = render_shaded(vertices, faces, R, t, K, (64, 64), *([] if light is None else [light]))
        direction = np.array((0.3, -0.5, -1.0) if light is None else light, dtype=np.float64)
        lambert = max(0.0, float(camera_normal @ direction) / np.linalg.norm(direction))
        lit += lambert > 0.1
        foreground = image[0, 0] != 0
        covered = foreground if covered is None else covered
        assert torch.equal(foreground, covered) and 1000 < int(foreground.sum()) < 64 * 64 - 500, light
        torch.testing.assert_close(image[0, 0][foreground], torch.full((int(foreground.sum()),), 0.15 + 0.85 * lambert,
                                                                        dtype=torch.float64), rtol=0, atol=1e-9)
    assert 4 <= lit <= len(lights) - 4  # lights from in front of the plane and from behind it
