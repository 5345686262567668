import math

import numpy as np
import pytest
import torch

from facenormals.fitting import drop_hidden_landmarks, hidden_landmarks
from facenormals.geometry import euler_to_rotation_matrix, project_points, transform_points
from facenormals.models import builtin_head_model

K = torch.tensor([[300.0, 63.5, 63.5]], dtype=torch.float64)


@pytest.fixture(scope="module")
def model():
    return builtin_head_model(dtype=torch.float64)


def posed(yaw_deg, pitch_deg=0.0, distance=600.0):
    R = euler_to_rotation_matrix(torch.tensor([[0.0, math.radians(pitch_deg), math.radians(yaw_deg)]],
                                              dtype=torch.float64))
    return R, R.transpose(1, 2) @ torch.tensor([0.0, 0.0, distance], dtype=torch.float64)


def ray_cast_hidden(vertices, faces, index, tolerance):
    """Naive reference: a landmark is hidden when a triangle not touching it crosses the segment from
    the camera centre to it more than ``tolerance`` mm (in depth) in front of it (Moller-Trumbore)."""
    v = vertices.numpy()
    f = faces.numpy()
    out = []
    for i in index.tolist():
        p = v[i]
        d = p / np.linalg.norm(p)
        tri = f[~(f == i).any(1)]
        a, b, c = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
        e1, e2 = b - a, c - a
        h = np.cross(d, e2)
        det = (e1 * h).sum(1)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = -a
        u = (s * h).sum(1) * inv
        q = np.cross(s, e1)
        w = (q * d).sum(1) * inv
        dist = (e2 * q).sum(1) * inv
        hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (dist > 0)
        depth = dist[hit] * d[2]
        out.append(bool((depth < p[2] - tolerance).any()))
    return torch.tensor(out)


@pytest.mark.parametrize("yaw", [-75.0, -40.0, 0.0, 25.0, 60.0, 85.0])
def test_hidden_landmarks_agree_with_ray_casting(model, yaw):
    R, t = posed(yaw, pitch_deg=10.0)
    hidden = hidden_landmarks(model, R, t, K, (128, 128))[0]
    camera = transform_points(model.mean[None], R, t)[0]
    reference = ray_cast_hidden(camera, model.faces, model.landmark_indices, tolerance=10.0)
    # the z-buffer is sampled at the nearest pixel centre: a landmark within a pixel of an occluding
    # silhouette may differ from the exact ray; every other decision must agree
    assert int((hidden != reference).sum()) <= 1, [n for n, a, b in zip(model.landmark_names, hidden, reference) if a != b]


def test_turning_left_and_right_hides_mirrored_landmarks(model):
    names = model.landmark_names
    left = hidden_landmarks(model, *posed(70.0), K, (128, 128))[0]
    right = hidden_landmarks(model, *posed(-70.0), K, (128, 128))[0]
    swap = [names.index(n.replace("left_", "@").replace("right_", "left_").replace("@", "right_")) for n in names]
    assert torch.equal(left, right[swap])
    assert int(left.sum()) >= 6 and not bool(left.all())
    frontal = hidden_landmarks(model, *posed(0.0), K, (128, 128))[0]
    eyes_nose_mouth = [names.index(n) for n in ("right_eye_inner", "left_eye_inner", "nose_tip", "upper_lip", "chin")]
    assert not bool(frontal[eyes_nose_mouth].any())


def test_landmarks_outside_the_image_are_hidden(model):
    R, t = posed(0.0)
    shifted = K.clone()
    shifted[0, 1] = 63.5 + 300.0  # the head projects to the right of the image
    assert bool(hidden_landmarks(model, R, t, shifted, (128, 128)).all())


def test_hidden_landmarks_use_the_given_shape(model):
    R, t = posed(60.0)
    y = torch.zeros(1, model.num_shape, dtype=torch.float64)
    assert torch.equal(hidden_landmarks(model, R, t, K, (128, 128), shape=y), hidden_landmarks(model, R, t, K, (128, 128)))
    # a head of another shape hides other landmarks: judged on that head, as ray casting on it says
    R, t = posed(30.0, pitch_deg=10.0)
    y = torch.zeros(1, model.num_shape, dtype=torch.float64)
    y[0, 0] = 3.0 * model.shape_std[0]
    hidden = hidden_landmarks(model, R, t, K, (128, 128), shape=y)[0]
    assert not torch.equal(hidden, hidden_landmarks(model, R, t, K, (128, 128))[0])
    camera = transform_points(model(y), R, t)[0]
    reference = ray_cast_hidden(camera, model.faces, model.landmark_indices, tolerance=10.0)
    assert int((hidden != reference).sum()) <= 1  # a landmark within a pixel of a silhouette may differ
    with pytest.raises(ValueError, match=r"shape: expected shape \(B, \d+\)"):
        hidden_landmarks(model, R, t, K, (128, 128), shape=torch.zeros(1, 3, dtype=torch.float64))


def test_drop_hidden_landmarks_drops_exactly_what_the_true_pose_hides(model):
    """A detector that reports every landmark at its exact projection: the pre-alignment recovers the
    pose, and the drop leaves exactly the landmarks the head shows."""
    poses = [posed(yaw, pitch) for yaw, pitch in ((-70.0, 5.0), (0.0, -10.0), (50.0, 0.0))]
    R = torch.cat([p[0] for p in poses])
    t = torch.cat([p[1] for p in poses])
    Ks = K.expand(3, 3)
    points, _ = project_points(model.mean[model.landmark_indices].expand(3, -1, -1), R, t, Ks)
    found = torch.ones(3, 24, dtype=torch.bool)
    kept, pose = drop_hidden_landmarks(points, found, model, Ks, (128, 128))
    assert torch.equal(kept, ~hidden_landmarks(model, R, t, Ks, (128, 128)))
    assert not bool(kept[0].all()) and not bool(kept[2].all())
    # the pose the drop was judged at is returned, so the fit can start from it
    torch.testing.assert_close(pose.rotation, R, atol=1e-6, rtol=0)
    torch.testing.assert_close(pose.translation, t[:, 0] if t.dim() == 3 else t, atol=1e-3, rtol=0)


def test_drop_hidden_landmarks_keeps_views_it_cannot_judge(model):
    R, t = posed(80.0)
    points, _ = project_points(model.mean[model.landmark_indices][None], R, t, K)
    few = torch.zeros(1, 24, dtype=torch.bool)
    few[0, :3] = True  # too few to pre-align: unchanged
    kept, pose = drop_hidden_landmarks(points, few, model, K, (128, 128))
    assert torch.equal(kept, few) and pose is None
    two = torch.cat([points, points])
    mixed = torch.cat([few, torch.ones_like(few)])  # one view judged, one not: no pose for the fit
    kept, pose = drop_hidden_landmarks(two, mixed, model, K.expand(2, 3), (128, 128))
    assert pose is None and torch.equal(kept[0], few[0])
    alone, _ = drop_hidden_landmarks(points, mixed[1:], model, K, (128, 128))  # the judged view as if alone
    assert torch.equal(kept[1], alone[0]) and not bool(alone.all())  # and its hidden landmarks are dropped
    everything = torch.ones(1, 24, dtype=torch.bool)
    shown = int((~hidden_landmarks(model, R, t, K, (128, 128))).sum())
    kept, _ = drop_hidden_landmarks(points, everything, model, K, (128, 128), min_landmarks=shown + 1)
    assert bool(kept.all())  # dropping would leave fewer than min_landmarks: unchanged
    nan_points = points.clone()
    nan_points[0, 5] = float("nan")  # a NaN point is never kept
    assert not bool(drop_hidden_landmarks(nan_points, everything, model, K, (128, 128))[0][0, 5])


def test_drop_hidden_landmarks_checks_its_inputs(model):
    points = torch.zeros(2, 24, 2, dtype=torch.float64)
    found = torch.ones(2, 24, dtype=torch.bool)
    with pytest.raises(ValueError, match=r"found: expected shape \(B, L\)"):
        drop_hidden_landmarks(points, found[:1], model, K.expand(2, 3), (128, 128))
    with pytest.raises(ValueError, match="found: expected a bool tensor"):
        drop_hidden_landmarks(points, found.double(), model, K.expand(2, 3), (128, 128))
    with pytest.raises(ValueError, match=r"landmarks: expected L = 24"):
        drop_hidden_landmarks(points[:, :5], found[:, :5], model, K.expand(2, 3), (128, 128))
    with pytest.raises(ValueError, match=r"intrinsics: expected shape \(B, 3\)"):
        drop_hidden_landmarks(points, found, model, K, (128, 128))


def test_drop_hidden_landmarks_refuses_points_and_intrinsics_that_are_not_floating_point(model):
    """Bool points pre-aligned a wrong head that silently dropped 18 of 24 detections; a bool prior read as f = 1."""
    R, t = posed(20.0)
    points, _ = project_points(model.mean[model.landmark_indices][None], R, t, K)
    found = torch.ones(1, 24, dtype=torch.bool)
    for bad in (points.bool(), points.long()):
        with pytest.raises(ValueError, match=f"landmarks: expected a floating-point tensor, got dtype {bad.dtype}"):
            drop_hidden_landmarks(bad, found, model, K, (128, 128))
    with pytest.raises(ValueError, match="intrinsics: expected a floating-point tensor, got dtype torch.bool"):
        drop_hidden_landmarks(points, found, model, K.bool(), (128, 128))


def test_drop_hidden_landmarks_runs_where_the_model_is(device):
    """Inputs on the CPU (as ``predict_maps`` returns them), the model on ``device``: the work follows
    the model and the mask comes back next to ``found``, equal to the all-CPU result."""
    cpu_model = builtin_head_model(dtype=torch.float32)
    R, t = posed(60.0)
    points, _ = project_points(cpu_model.mean[None, cpu_model.landmark_indices], R.float(), t.float(), K.float())
    found = torch.ones(1, 24, dtype=torch.bool)
    expected, _ = drop_hidden_landmarks(points, found, cpu_model, K.float(), (128, 128))
    got, _ = drop_hidden_landmarks(points, found, builtin_head_model(dtype=torch.float32).to(device), K.float(),
                                   (128, 128))
    assert got.device == found.device and torch.equal(got, expected)
    assert hidden_landmarks(cpu_model.to(device), R, t, K, (128, 128)).device == device


def test_hidden_landmarks_checks_the_pose_and_image_size(model):
    R = euler_to_rotation_matrix(torch.zeros(1, 3))
    t, K = torch.tensor([[0.0, 0.0, 600.0]]), torch.tensor([[300.0, 63.5, 63.5]])
    with pytest.raises(ValueError, match="rotation: expected finite values"):
        hidden_landmarks(model, R * math.nan, t, K, (128, 128))  # NaN would hide every landmark
    with pytest.raises(ValueError, match=r"image_size: expected \(H, W\), two integers >= 1"):
        hidden_landmarks(model, R, t, K, (128.9, 64.5))
