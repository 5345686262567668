import numpy as np
import pytest
import torch
import trimesh

from facenormals.models import BUILTIN_PARAMETERS, LANDMARK_NAMES, LANDMARK_PAIRS, builtin_head_model


def test_builtin_is_a_closed_head_with_enough_detail():
    model = builtin_head_model()
    assert model.num_vertices >= 5000 and model.num_shape >= 20
    mesh = trimesh.Trimesh(model.mean.numpy(), model.faces.numpy(), process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward winding
    extent = model.mean.max(0).values - model.mean.min(0).values
    # a human head: about 15-20 cm wide (with ears), 20-26 cm tall, 19-23 cm deep (with the nose)
    assert 150 < extent[0] < 210 and 200 < extent[1] < 260 and 180 < extent[2] < 240


def test_builtin_is_deterministic():
    a, b = builtin_head_model(), builtin_head_model()
    assert torch.equal(a.mean, b.mean) and torch.equal(a.shape_basis, b.shape_basis)


def test_builtin_components_have_documented_std():
    model = builtin_head_model()
    assert [p.name for p in BUILTIN_PARAMETERS] == model.metadata["shape_components"]
    assert torch.allclose(model.shape_std, torch.tensor([p.std for p in BUILTIN_PARAMETERS]))
    # each component moves the surface, and +-2 sigma heads stay valid closed surfaces
    norms = model.shape_basis.flatten(1).norm(dim=1)
    assert (norms > 0).all()
    for sign in (-2.0, 2.0):
        v = model(sign * model.shape_std[None])[0]
        assert torch.isfinite(v).all()
        mesh = trimesh.Trimesh(v.numpy(), model.faces.numpy(), process=False)
        assert mesh.volume > 0


def test_head_length_component_changes_length():
    model = builtin_head_model(dtype=torch.float64)
    k = [p.name for p in BUILTIN_PARAMETERS].index("head_length")
    y = torch.zeros(1, model.num_shape, dtype=torch.float64)
    y[0, k] = 10.0
    z = model(y)[0, :, 2]
    base = model.mean[:, 2]
    assert abs(float((z.max() - z.min()) - (base.max() - base.min())) - 10.0) < 2.5


def test_builtin_landmarks_sit_on_the_right_anatomy():
    model = builtin_head_model(dtype=torch.float64)
    assert list(model.landmarks) == list(LANDMARK_NAMES)
    P = model.mean.numpy()
    lm = {k: P[v] for k, v in model.landmarks.items()}
    z = np.array([p[2] for p in lm.values()])
    assert lm["nose_tip"][2] == z.min()  # most forward (face along -z)
    for right, left in LANDMARK_PAIRS:
        mirrored = lm[left] * np.array([-1.0, 1.0, 1.0])
        assert np.linalg.norm(lm[right] - mirrored) < 2.0, (right, left)
        assert lm[right][0] < 0 < lm[left][0]
    x = np.abs(np.array([p[0] for p in lm.values()]))
    ear_names = [n for n in LANDMARK_NAMES if "_ear_" in n]
    assert min(abs(lm[n][0]) for n in ear_names) > max(abs(lm[n][0]) for n in LANDMARK_NAMES if n not in ear_names)
    assert x.max() in [abs(lm[n][0]) for n in ear_names]
    assert lm["right_eye_outer"][1] < lm["nose_tip"][1] < lm["upper_lip"][1] < lm["lower_lip"][1] < lm["chin"][1]


def test_icosphere_is_trimeshs_vertex_for_vertex_without_importing_it():
    # the built-in head's vertex order must not move with a trimesh release: it is built here, and
    # equals trimesh's own icosphere bit for bit (so heads saved before stay comparable)
    import subprocess
    import sys

    from facenormals.models.builtin import _icosphere

    for subdivisions in (0, 1, 3, 5):
        vertices, faces = _icosphere(subdivisions)
        sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
        assert np.array_equal(vertices, sphere.vertices) and np.array_equal(faces, sphere.faces)
    code = ("import sys; from facenormals.models import builtin_head_model; builtin_head_model(); "
            "print('trimesh' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_built_models_do_not_share_the_cached_arrays():
    """float64 models were built with torch.from_numpy(...).to(float64), which does not copy: editing
    one model's buffers in place changed every built-in model built after it."""
    first = builtin_head_model(dtype=torch.float64)
    std, mean = builtin_head_model().shape_std.clone(), builtin_head_model().mean.clone()
    first.shape_std.mul_(2.0)
    first.mean.mul_(0.001)
    first.faces[0] = 0
    again = builtin_head_model()
    assert torch.equal(again.shape_std, std) and torch.equal(again.mean, mean)
    with pytest.raises(ValueError, match="dtype: expected a floating-point torch dtype, got torch.int32"):
        builtin_head_model(dtype=torch.int32)
