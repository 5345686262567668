import numpy as np
import pytest
import torch

from facenormals.data.head import HeadAssets
from facenormals.data.meshes import boundary_loops, box_mesh, cylinder_mesh, face_normals, ring_strip, sphere_mesh
from facenormals.models import builtin_head_model, load_model


@pytest.mark.parametrize("build", [lambda: sphere_mesh(np.linspace(0, np.pi, 7), 9), box_mesh, cylinder_mesh])
def test_primitives_are_closed_and_outward(build):
    vertices, faces, _ = build()
    if build not in (box_mesh, cylinder_mesh):  # those have split vertices at their sharp edges
        assert boundary_loops(faces) == []
    centroid = vertices[faces].mean(1)
    assert (np.sum(face_normals(vertices, faces) * centroid, axis=1) > 0).all()


def test_boundary_loops_follow_the_winding():
    # a square of two triangles, counter-clockwise seen from +z
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    (loop,) = boundary_loops(faces)
    assert sorted(loop.tolist()) == [0, 1, 2, 3]
    start = loop.tolist().index(0)
    assert np.roll(loop, -start).tolist() == [0, 1, 2, 3]
    strip = ring_strip(np.arange(4), np.arange(4, 8))
    assert strip.shape == (8, 3)


def test_head_assets_of_ict(ict_npz):
    assets = HeadAssets.from_model(load_model(ict_npz))
    assert len(assets.eye_loops) == 2 and assets.mouth_loop is not None and assets.neck_loop is not None
    mean = assets.model.mean.numpy()
    right, left = (mean[loop].mean(0) for loop in assets.eye_loops)
    assert right[0] < 0 < left[0], "the subject's right eye is on the image left (negative x)"
    for name, weight in assets.regions.items():
        assert weight.shape == (assets.model.num_vertices,) and 0 <= weight.min() and weight.max() <= 1, name
    lips = assets.regions["lips"]
    assert lips[assets.model.landmarks["upper_lip"]] > 0.5 and lips[assets.model.landmarks["nose_tip"]] < 0.05
    field = assets.noise(np.random.default_rng(0), "mottle")
    assert field.shape == (assets.model.num_vertices,) and 0.5 < field.std() < 1.5
    with pytest.raises(ValueError, match="name: expected one of"):
        assets.noise(np.random.default_rng(0), "plaid")


def test_head_assets_of_a_closed_head_and_rebuilt_vertices():
    model = builtin_head_model()
    assets = HeadAssets.from_model(model)
    assert assets.eye_loops == [] and assets.mouth_loop is None and assets.neck_loop is None
    y = np.random.default_rng(1).normal(size=model.num_shape).astype(np.float32)
    identity, full = assets.vertices(y, None)
    assert np.array_equal(full, model(torch.from_numpy(y)[None])[0].numpy())


def test_model_without_landmarks_is_refused():
    model = builtin_head_model()
    from facenormals.models import MorphableModel

    bare = MorphableModel(model.mean, model.shape_basis, model.faces)
    with pytest.raises(ValueError, match="needs the 24 landmarks"):
        HeadAssets.from_model(bare)
