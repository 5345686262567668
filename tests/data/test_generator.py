import dataclasses

import numpy as np
import pytest
import torch

from facenormals.data import HEAD_LABELS, LABELS, SynthConfig, landmark_maps, landmarks_from_maps
from facenormals.geometry import euler_to_rotation_matrix, project_points, transform_points
from facenormals.mesh import vertex_normals
from facenormals.render import render_normal_map, visible_vertices
from facenormals.sampling import sample_bicubic

from tests.data.conftest import configured


def _ground_truth(model, batch):
    """Rebuild the posed ground-truth mesh of a batch from its stored coefficients."""
    y = torch.from_numpy(batch.shape_coeffs)
    e = torch.from_numpy(batch.expression_coeffs) if model.num_expressions else None
    vertices = model(y, e)
    R, t, K = (torch.from_numpy(x) for x in (batch.rotation, batch.translation, batch.intrinsics))
    return vertices, R, t, K


def _vertex_area(vertices, faces):
    """One third of the incident triangle areas of each vertex, ``(B, N)``."""
    a, b, c = (vertices[:, faces[:, k]] for k in range(3))
    area = torch.linalg.cross(b - a, c - a).norm(dim=-1) / 6.0
    out = torch.zeros(vertices.shape[:2], dtype=vertices.dtype)
    for k in range(3):
        out.index_add_(1, faces[:, k], area)
    return out


def test_batch_fields_and_ranges(generator, samples):
    b, s = samples, generator.config.image_size
    model = generator.model
    assert b.image.shape == (8, s, s, 3) and b.image.dtype == np.uint8
    assert b.normals.shape == (8, 3, s, s) and b.normals.dtype == np.float32
    assert b.landmarks.shape == (8, 24, 2) and b.landmark_visible.dtype == bool
    assert b.shape_coeffs.shape == (8, model.num_shape) and b.expression_coeffs.shape == (8, model.num_expressions)
    norm = np.linalg.norm(b.normals, axis=1)
    assert np.allclose(norm[b.mask], 1.0, atol=1e-5)
    assert (b.normals.transpose(0, 2, 3, 1)[~b.mask] == 0).all(), "N is exactly zero off the head surface"
    assert np.isin(b.segmentation, list(LABELS.values())).all()
    roll, pitch, yaw = np.degrees(b.angles).T
    assert (np.abs(yaw) <= 90).all() and (np.abs(pitch) <= 35).all() and (np.abs(roll) <= 25).all()
    R = euler_to_rotation_matrix(torch.from_numpy(b.angles)).numpy()
    assert np.array_equal(R, b.rotation)


def test_normals_agree_with_vertex_normals_at_visible_vertices(generator, samples):
    """The issue's check: N sampled bicubically at the projected visible vertices of the ground-truth
    mesh against its ring vertex normals rotated into the camera frame.

    Visible = ``visible_vertices`` with the rendered z-buffer in which every pixel that is not the head
    surface (hair, caps, occluders, clothing) hides what is behind it. The mean is over the visible
    surface (each vertex weighted by its area); the per-vertex mean is also bounded on the built-in
    head, whose vertices are evenly spread. On ICT-FaceKit the per-vertex mean is dominated by dense
    rings of vertices at the eyelid margins, inner lips, nostrils and ear folds, whose normals turn
    by up to 90 degrees within one pixel at 128x128 (see docs/synthetic_data.md).
    """
    model = generator.model
    vertices, R, t, K = _ground_truth(model, samples)
    pixels, depth = project_points(vertices, R, t, K)
    normals = vertex_normals(vertices, model.faces) @ R.transpose(1, 2)
    zbuffer = torch.from_numpy(samples.depth).clone()
    zbuffer[~torch.from_numpy(samples.mask)] = 1e-6  # an occluder in front of everything
    visible = visible_vertices(pixels, depth, normals, transform_points(vertices, R, t), zbuffer)
    sampled, inside = sample_bicubic(torch.from_numpy(samples.normals), pixels)
    cosine = torch.nn.functional.cosine_similarity(sampled, normals, dim=-1)
    angle = torch.rad2deg(torch.acos(cosine.clamp(-1.0, 1.0)))
    use = visible & inside
    assert use.sum() > 8 * 500
    weight = _vertex_area(vertices, model.faces)
    surface_mean = float((angle * weight)[use].sum() / weight[use].sum())
    assert surface_mean <= 3.0, surface_mean
    assert float(angle[use].median()) <= 1.5
    if model.name == "builtin":
        assert float(angle[use].mean()) <= 3.0
    # a convention error (flipped axis, transposed rotation) would give tens of degrees
    flipped = torch.nn.functional.cosine_similarity(sampled * torch.tensor([1.0, -1.0, 1.0]), normals, dim=-1)
    assert float(torch.rad2deg(torch.acos(flipped.clamp(-1, 1)))[use].median()) > 10.0


def test_bare_head_matches_the_software_rasteriser(generator):
    """Without hair, eyes, mouth, clothing and occluders, N and the mask equal the pure-torch
    rasteriser's exact normal map pixel for pixel: catches any sign flip of the OpenGL camera,
    swapped axes or half-pixel offsets."""
    with configured(generator, SynthConfig.head_only()) as gen:
        batch = gen.generate(5, [0, 1, 2])
    vertices, R, t, K = _ground_truth(gen.model, batch)
    reference, fragments = render_normal_map(vertices.double(), gen.model.faces, R.double(), t.double(), K.double(),
                                             (128, 128))
    mask = torch.from_numpy(batch.mask)
    iou = (mask & fragments.mask).sum() / (mask | fragments.mask).sum()
    assert iou > 0.995, iou
    both = mask & fragments.mask
    ours = torch.from_numpy(batch.normals).double().permute(0, 2, 3, 1)[both]
    theirs = reference.permute(0, 2, 3, 1)[both]
    angle = torch.rad2deg(torch.acos((ours * theirs).sum(-1).clamp(-1, 1)))
    assert float(angle.mean()) < 0.05 and float(angle.quantile(0.99)) < 0.5
    assert (theirs[:, 2] < 0.5).float().mean() > 0.99  # visible surfaces face the camera (z < 0)
    depth = torch.from_numpy(batch.depth).double()[both]
    # GL interpolates the depth attribute in float32: on Mesa (llvmpipe) within 1.1e-5 of the depth
    # (0.011 mm at 1.9 m), on NVIDIA's EGL ~0.04 mm and more at ~2 m, hence a relative bound. A
    # half-pixel offset or flipped axis shifts depths by millimetres on the slanted parts of the head.
    error = (depth - fragments.depth[both]).abs()
    assert float((error / fragments.depth[both]).max()) < 1e-4 and float(error.mean()) < 0.01


def test_landmark_peaks_lie_on_the_projected_vertices(generator, samples):
    model = generator.model
    vertices, R, t, K = _ground_truth(model, samples)
    projected, _ = project_points(vertices[:, model.landmark_indices], R, t, K)
    assert torch.allclose(torch.from_numpy(samples.landmarks), projected, atol=1e-4)
    visible = torch.from_numpy(samples.landmark_visible)
    assert visible.any() and not visible.all()
    maps = landmark_maps(torch.from_numpy(samples.landmarks), visible, (128, 128))
    assert (maps.flatten(2).amax(-1) > 0)[visible].all() and (maps[~visible] == 0).all()
    peaks, found = landmarks_from_maps(maps)
    assert torch.equal(found, visible)
    error = (peaks - projected).norm(dim=-1)[visible]
    assert float(error.max()) <= 0.5
    # the brightest pixel itself is the pixel nearest to the landmark
    flat = maps.flatten(2).argmax(-1)
    pixel = torch.stack([flat % 128, flat // 128], dim=-1).to(projected.dtype)
    assert float((pixel - projected).abs().amax(-1)[visible].max()) <= 0.5 + 1e-4


def _ray_gaps(point, parts):
    """Per part label, the largest distance in front of camera-frame ``point`` ``(3,)`` at which its
    ray from the camera centre crosses a triangle of that label (0 where none crosses), by signed
    volumes rather than the library's Möller-Trumbore: the ray meets the cone of triangle (a, b, c)
    where ``p . (a x b)``, ``p . (b x c)``, ``p . (c x a)`` share a sign, at ``s = (a . n) / (p . n)``."""
    gaps = {}
    for part in parts:
        posed = (part.vertices.astype(np.float64) + part.translation) @ np.asarray(part.rotation, np.float64).T
        a, b, c = (posed[part.faces[:, k]] for k in range(3))
        volumes = [np.cross(x, y) @ point for x, y in ((a, b), (b, c), (c, a))]
        cone = np.all([v >= 0 for v in volumes], 0) | np.all([v <= 0 for v in volumes], 0)
        n = np.cross(b - a, c - a)
        s = np.einsum("ki,ki->k", a, n) / np.where(n @ point == 0, np.nan, n @ point)
        crossing = cone & (s > 0) & (s < 1)
        gap = float((1 - s[crossing]).max() * np.linalg.norm(point)) if crossing.any() else 0.0
        gaps[part.label] = max(gaps.get(part.label, 0.0), gap)
    return gaps


def _reference_visibility(generator, seed, indices, skip_labels=()):
    """The visibility rule of ``docs/synthetic_data.md``, by brute force over every triangle of each
    sample's scene: inside the image, no hair, cap, clothing or occluder in front, and the head
    surface at most max(3 mm, 2 pixels at the landmark's depth) in front. Also returns the gaps."""
    visible, gaps = [], []
    for index in indices:
        plan = generator._plan(seed, index)
        record = plan.record
        R, t = record["rotation"].astype(np.float64), record["translation"].astype(np.float64)
        vertices = generator.assets.vertices(record["shape_coeffs"], record["expression_coeffs"]
                                             if generator.model.num_expressions else None)[1]
        points = (vertices[generator.model.landmark_indices.numpy()].astype(np.float64) + t) @ R.T
        parts = [p for p in plan.scene.parts if p.label not in skip_labels]
        size = generator.config.image_size
        inside = (np.rint(record["landmarks"]) >= 0).all(-1) & (np.rint(record["landmarks"]) <= size - 1).all(-1)
        row, row_gaps = [], []
        for k, point in enumerate(points):
            gap = _ray_gaps(point, parts)
            slack = max(3.0, 2.0 * point[2] / float(record["intrinsics"][0]))
            head = max([gap.get(label, 0.0) for label in HEAD_LABELS])
            others = max([g for label, g in gap.items() if label not in HEAD_LABELS] + [0.0])
            row.append(bool(inside[k]) and head <= slack and others == 0.0)
            row_gaps.append((head, others, slack, gap.get(LABELS["hair"], 0.0)))
        visible.append(row)
        gaps.append(row_gaps)
    return np.array(visible), np.array(gaps)


def test_landmark_visibility_is_an_exact_ray_cast(generator, samples):
    """The stored visibility agrees with a brute-force ray cast of each landmark against every
    triangle of the scene; both kinds of decision occur on seed 11."""
    visible, gaps = _reference_visibility(generator, 11, range(len(samples)))
    np.testing.assert_array_equal(samples.landmark_visible, visible)
    head, others, slack = gaps[..., 0], gaps[..., 1], gaps[..., 2]
    assert ((head > slack) & (others == 0)).any() and (others > 0).any() and visible.any()


def test_visible_landmarks_lie_on_the_head_surface_or_its_outline(generator, samples):
    """Against the rendered image: a visible landmark has a head pixel next to its nearest pixel (on
    the head surface or on its outline), and landmarks outside the image are invisible."""
    b = samples
    u = np.rint(b.landmarks[..., 0]).astype(int).clip(0, 127)
    v = np.rint(b.landmarks[..., 1]).astype(int).clip(0, 127)
    rows = np.arange(len(b))[:, None]
    head = np.pad(np.isin(b.segmentation, HEAD_LABELS), ((0, 0), (1, 1), (1, 1)))
    near_head = np.zeros_like(b.landmark_visible)
    for dv in (0, 1, 2):
        for du in (0, 1, 2):
            near_head |= head[rows, v + dv, u + du]
    assert near_head[b.landmark_visible].all()
    inside = (b.landmarks >= 0).all(-1) & (b.landmarks <= 127).all(-1)
    assert not b.landmark_visible[~inside].any()


def test_hair_just_in_front_of_a_landmark_hides_it(generator):
    """Hair lies millimetres above the skin, within the head surface's depth slack: it hides the
    landmarks it covers all the same (seed 7 has such landmarks on both heads)."""
    b = generator.generate(7, range(16))
    visible, gaps = _reference_visibility(generator, 7, range(16))
    hair, slack = gaps[..., 3], gaps[..., 2]
    under_hair = (hair > 0) & (hair <= slack) & (gaps[..., 0] <= slack)
    assert under_hair.sum() >= 3
    assert not b.landmark_visible[under_hair].any()
    np.testing.assert_array_equal(b.landmark_visible, visible)


def test_lights_are_exposed_for_the_head(generator):
    """No head is overexposed by its lights: the 90th percentile of the camera-facing head's diffuse
    radiance (computed vertex by vertex in the test) is at most the top of the exposure range, and
    some heads' lights were dimmed to it (they lie inside the range)."""
    from tests.data.test_appearance import _facing_radiance

    levels = []
    for index in range(24):
        plan = generator._plan(13, index)
        head = next(p for p in plan.scene.parts if p.label == LABELS["skin"])
        levels.append(np.percentile(_facing_radiance(plan.scene.lighting, head).max(1), 90))
    levels = np.array(levels)
    low, high = generator.config.exposure
    assert (levels <= high + 1e-9).all()
    assert ((levels >= low - 1e-9) & (levels <= high + 1e-9)).sum() >= 3


def test_occluders_are_aimed_at_landmarks_the_image_shows(generator, monkeypatch):
    """Occluders cover landmarks that nothing else hides, not far-side ones that no image shows."""
    import facenormals.data.generator as module

    aimed = []
    original = module.occluder_parts

    def recording(rng, targets, *args):
        aimed.append(targets.copy())
        return original(rng, targets, *args)

    monkeypatch.setattr(module, "occluder_parts", recording)
    with configured(generator, dataclasses.replace(generator.config, occluder_probability=1.0)) as gen:
        before, _ = _reference_visibility(gen, 5, range(6), skip_labels=(LABELS["occluder"],))
        aimed.clear()
        b = gen.generate(5, range(6))
    vertices, R, t, _ = _ground_truth(gen.model, b)
    landmarks = transform_points(gen.model.landmark_vertices(vertices), R, t).numpy()
    assert len(aimed) == 6 and (~before).any()
    for targets, points, shows in zip(aimed, landmarks, before):
        np.testing.assert_allclose(targets, points[shows], atol=1e-3)


def test_landmarks_outside_the_image_are_invisible(generator):
    """Close-ups (the head up to 1.5 times the image) put landmarks outside, where the nearest edge
    pixel may well show the head at their depth."""
    with configured(generator, SynthConfig.head_only(fill=(1.3, 1.5), yaw=30.0)) as gen:
        b = gen.generate(0, range(8))
    outside = ((b.landmarks < -0.5) | (b.landmarks > 127.5)).any(-1)
    assert outside.sum() >= 10
    assert not b.landmark_visible[outside].any()
    assert b.landmark_visible[~outside].any()


def test_a_profile_shows_the_nose_tip_on_the_outline(generator):
    """In profile the nose tip lies on the outline, where its nearest pixel may be background: it is
    visible (nothing hides it) and its map has a peak."""
    with configured(generator, SynthConfig.head_only(pitch=0.0, roll=0.0, expression_probability=0.0)) as gen:
        batch = gen.generate(10, range(40))
    names = gen.model.landmark_names
    yaw = np.abs(np.degrees(batch.angles[:, 2]))
    tip = names.index("nose_tip")
    u, v = np.rint(batch.landmarks[:, tip]).astype(int).clip(0, 127).T
    outline = (yaw > 60) & (batch.segmentation[np.arange(len(batch)), v, u] == LABELS["background"])
    assert outline.sum() >= 1
    assert batch.landmark_visible[outline, tip].all()
    maps = landmark_maps(torch.from_numpy(batch.landmarks[outline]), torch.from_numpy(batch.landmark_visible[outline]),
                         (128, 128))
    assert bool((maps[:, tip].flatten(1).amax(-1) > 0.5).all())


def test_profiles_hide_the_far_ear(generator):
    """In profile views the z-buffer hides the far ear; positive yaw shows the subject's left side."""
    with configured(generator, SynthConfig.head_only(pitch=0.0, roll=0.0, expression_probability=0.0)) as gen:
        batch = gen.generate(10, range(12))  # seed 10: four profiles (|yaw| > 65), five frontal views
    names = gen.model.landmark_names
    yaw = np.degrees(batch.angles[:, 2])
    near = np.where(yaw > 0, names.index("left_ear_tragus"), names.index("right_ear_tragus"))
    far = np.where(yaw > 0, names.index("right_ear_tragus"), names.index("left_ear_tragus"))
    rows = np.arange(len(batch))
    profile = np.abs(yaw) > 65
    assert profile.sum() >= 3
    assert batch.landmark_visible[rows, near][profile].all()
    assert not batch.landmark_visible[rows, far][profile].any()
    frontal = np.abs(yaw) < 20
    assert batch.landmark_visible[:, names.index("nose_tip")][frontal].all()


def test_same_seed_and_index_give_identical_bytes(generator):
    first = generator.generate(3, [5, 6, 7, 8, 9])
    again = generator.generate(3, [9, 7])  # other batches, other order, other tiles in use
    alone = generator.sample(3, 7)
    for name in ("image", "normals", "segmentation", "landmarks", "landmark_visible", "shape_coeffs",
                 "expression_coeffs", "rotation", "translation", "intrinsics"):
        a = getattr(first, name)
        assert getattr(again, name)[1].tobytes() == a[2].tobytes(), name
        assert getattr(alone, name)[0].tobytes() == a[2].tobytes(), name
    other = generator.generate(4, [7])
    assert other.image.tobytes() != alone.image.tobytes(), "another seed gives another sample"


def test_fixed_poses_give_views_of_one_person(generator):
    plain = generator.sample(3, 7)
    same = generator.generate(3, [7], angles=[plain.angles[0]])
    for name in ("image", "normals", "landmarks", "intrinsics", "translation"):
        assert getattr(same, name).tobytes() == getattr(plain, name).tobytes(), name
    yaws = [-0.7, 0.0, 0.7]
    views = generator.generate(3, [7, 7, 7], angles=[(0.0, 0.1, y) for y in yaws])
    np.testing.assert_array_equal(views.shape_coeffs, np.repeat(plain.shape_coeffs, 3, axis=0))
    np.testing.assert_allclose(views.angles[:, 2], yaws, atol=1e-7)
    np.testing.assert_allclose(views.rotation, euler_to_rotation_matrix(torch.tensor([(0.0, 0.1, y) for y in yaws]))
                               .numpy(), atol=1e-6)
    assert len({views.image[i].tobytes() for i in range(3)}) == 3
    # the nose tip swings from one side of the eye-corner midpoint to the other
    names = list(generator.model.landmark_names)
    nose, eyes = names.index("nose_tip"), [names.index("right_eye_outer"), names.index("left_eye_outer")]
    offset = views.landmarks[:, nose, 0] - views.landmarks[:, eyes, 0].mean(1)
    assert offset[0] * offset[2] < 0 and abs(offset[1]) < min(abs(offset[0]), abs(offset[2]))
    with pytest.raises(ValueError, match=r"angles: expected 2 finite \(roll, pitch, yaw\) triples, one per index, "
                                         r"got 1 of shapes \[\(3,\)\]"):
        generator.generate(3, [7, 8], angles=[(0.0, 0.0, 0.0)])
    with pytest.raises(ValueError, match=r"angles: .* got 2 of shapes \[\(2,\), \(3,\)\]"):  # ragged
        generator.generate(3, [7, 8], angles=[(0.0, 0.0, 0.0), (0.0, 0.0)])


def test_variation(generator):
    b = generator.generate(21, range(16))
    vertices, R, t, K = _ground_truth(generator.model, b)
    pixels, _ = project_points(vertices[:, torch.from_numpy(generator.assets.framing)], R, t, K)
    fill = (pixels.amax(1) - pixels.amin(1)).amax(-1) / 128  # the head without the neck
    assert float(fill.min()) >= 0.398 and float(fill.max()) <= 0.902, fill  # the configured 40-90 %
    assert float(fill.max() - fill.min()) > 0.15
    assert float(pixels.amin()) >= -0.5 and float(pixels.amax()) <= 127.5  # the whole head is in the frame
    assert len({tuple(np.round(f, 3)) for f in b.intrinsics}) == 16
    if generator.model.num_expressions:
        assert (b.expression_coeffs > 0).any(axis=1).sum() >= 8
        assert (b.expression_coeffs >= 0).all() and (b.expression_coeffs <= 1).all()
    labels = set(np.unique(b.segmentation))
    assert {0, 1}.issubset(labels) and labels & {4, 5}, "hair or caps appear"


def test_wider_identity_range(generator):
    with configured(generator, SynthConfig.head_only(identity_scale=2.0)) as gen:
        wide = gen.generate(0, range(2)).shape_coeffs
    with configured(generator, SynthConfig.head_only()) as gen:
        base = gen.generate(0, range(2)).shape_coeffs
    assert np.allclose(wide, 2.0 * base, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"fill": (0.0, 0.5)}, "fill"),
        ({"exposure": (0.0, 1.0)}, r"exposure: expected 0 < low <= high <= 1, got \(0.0, 1.0\)"),
        ({"exposure": (0.9, 1.2)}, r"exposure: expected 0 < low <= high <= 1"),
        ({"exposure": 0.9}, r"exposure: expected a \(low, high\) pair of numbers, got 0.9"),
        ({"hair_probability": 1.5}, "hair_probability"),
        ({"hair_probability": 0.8, "cap_probability": 0.5}, "hair_probability \\+ cap_probability"),
        ({"supersample": 2}, "supersample"),
        ({"num_lights": (1, 4)}, "num_lights"),
        ({"yaw": -5.0}, "yaw"),
        ({"roll": 181.0}, r"roll: expected a range in \[0, 180\] degrees"),
        ({"pitch": 90.0}, r"pitch: expected a range in \[0, 90\) degrees, got 90.0"),
        ({"pitch": float("nan")}, "pitch"),
        ({"image_size": 8}, "image_size: expected an integer >= 16, got 8"),
        ({"image_size": 128.7}, "image_size: expected an integer, got float 128.7"),
        ({"image_size": True}, "image_size: expected an integer, got bool"),
        ({"supersample": 3.0}, "supersample: expected an integer, got float 3.0"),
        ({"max_expressions": -1}, "max_expressions: expected an integer >= 0, got -1"),
        ({"max_expressions": 2.5}, "max_expressions: expected an integer"),
        ({"principal_jitter": -1.0}, r"principal_jitter: expected pixels in \[0, 63.5\)"),
        ({"principal_jitter": 64.0}, r"principal_jitter: expected pixels in \[0, 63.5\) \(the principal point inside"),
        ({"temperature": (float("nan"), float("nan"))}, r"temperature: expected 1000 <= low <= high <= 40000 kelvin"),
        ({"temperature": (-100.0, 5.0)}, r"temperature: expected 1000 <= low"),
        ({"temperature": (9000.0, 2500.0)}, r"temperature: expected 1000 <= low <= high"),
        ({"temperature": 6500.0}, r"temperature: expected a \(low, high\) pair of numbers, got 6500.0"),
        ({"focal": (120.0, float("inf"))}, r"focal: expected 0 < low <= high < inf"),
        ({"focal": ("120", "800")}, r"focal: expected a \(low, high\) pair of numbers"),
        ({"num_lights": (1.5, 2)}, r"num_lights: expected integers, got \(1.5, 2\)"),
        ({"num_lights": (1, float("inf"))}, r"num_lights: expected integers, got \(1, inf\)"),
        ({"num_lights": (float("nan"), 2)}, r"num_lights: expected integers, got \(nan, 2\)"),
        ({"background_folders": "photos"}, r"background_folders: expected a tuple of folders, got the single str "
                                           r"'photos'"),
    ],
)
def test_bad_config(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SynthConfig(**kwargs)


def test_numpy_integers_are_accepted_as_python_ints():
    config = SynthConfig(image_size=np.int64(64), supersample=np.int32(1), max_expressions=np.uint8(2))
    assert config == SynthConfig(image_size=64, supersample=1, max_expressions=2)
    assert all(type(config.to_dict()[name]) is int for name in ("image_size", "supersample", "max_expressions"))


def test_bad_generate_arguments(generator):
    with pytest.raises(ValueError, match="seed: expected a non-negative integer"):
        generator.generate(-1, [0])
    with pytest.raises(ValueError, match="indices: expected a non-negative integer"):
        generator.generate(0, [0, 1.5])
    with pytest.raises(ValueError, match="config: expected a SynthConfig"):
        type(generator)(generator.model, config={"fill": (0.4, 0.9)})
    assert len(generator.generate(0, [])) == 0


@pytest.mark.parametrize("kwargs, match", [
    ({"yaw": "90"}, r"yaw: expected a real number, got str '90'"),  # was TypeError from a comparison
    ({"photo_probability": None}, r"photo_probability: expected a real number, got NoneType None"),
    ({"identity_scale": True}, r"identity_scale: expected a real number, got bool True"),
    ({"principal_jitter": [6.0]}, r"principal_jitter: expected a real number, got list"),
    ({"background_folders": ("a", 3)}, r"background_folders: expected a tuple of folders \(str or Path\), got"),
    ({"background_folders": None}, r"background_folders: expected a tuple of folders \(str or Path\), got None"),
])
def test_config_values_of_the_wrong_type_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SynthConfig(**kwargs)


def test_config_lists_become_tuples_so_that_it_hashes():
    """background_folders=["/tmp"] stayed a list: the frozen dataclass could not be hashed."""
    from pathlib import Path

    config = SynthConfig(background_folders=["/tmp", Path("photos")], fill=[0.5, 0.8], yaw=np.float32(30))
    assert config.background_folders == ("/tmp", "photos") and config.fill == (0.5, 0.8)
    assert hash(config) == hash(SynthConfig(background_folders=("/tmp", "photos"), fill=(0.5, 0.8), yaw=30.0))
    assert type(config.yaw) is float


def test_config_round_trip():
    config = SynthConfig(fill=(0.5, 0.8), background_folders=("a", "b"))
    assert SynthConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ValueError, match="unknown fields"):
        SynthConfig.from_dict({"colour": 1})


def test_no_expressions_when_none_are_allowed(generator):
    if not generator.model.num_expressions:
        pytest.skip("the model has no expressions")
    with configured(generator, SynthConfig(expression_probability=1.0, max_expressions=0)) as gen:
        batch = gen.generate(5, range(4))
    assert (batch.expression_coeffs == 0).all()


def test_the_callers_model_is_left_as_it_is():
    """The generator renders in float32 on the CPU; converting the caller's module in place would
    change the dtype (or device) of a model the caller goes on using."""
    from facenormals.data import SyntheticHeadGenerator
    from facenormals.models import builtin_head_model

    config = SynthConfig.head_only(use_skimage=False)
    model = builtin_head_model().double()
    generator = SyntheticHeadGenerator(model, config)
    assert model.mean.dtype == torch.float64 and model.shape_basis.dtype == torch.float64
    assert generator.model is not model and generator.model.mean.dtype == torch.float32
    assert torch.equal(generator.model.mean, model.mean.float())
    single = builtin_head_model()
    assert SyntheticHeadGenerator(single, config).model is single  # nothing to convert: no copy


def _framed_box(generator, seed, count):
    """``(count, 2, 2)``: lowest and highest projected pixel ``(u, v)`` of the framing vertices of the
    mean head framed by ``_frame`` at random poses, from the stored float32 camera."""
    rng = np.random.default_rng(seed)
    cfg = generator.config
    angles = np.radians(np.stack([rng.uniform(-a, a, count) for a in (cfg.roll, cfg.pitch, cfg.yaw)], 1))
    rotation = euler_to_rotation_matrix(torch.from_numpy(angles.astype(np.float32)))
    mean = generator.model.mean
    head = mean[torch.from_numpy(generator.assets.framing)]
    boxes = []
    for k in range(count):
        intrinsics, translation = generator._frame(np.random.default_rng([seed, k]), mean.numpy(),
                                                   rotation[k].double().numpy())
        pixels, _ = project_points(head[None], rotation[k:k + 1], torch.from_numpy(translation)[None],
                                   torch.from_numpy(intrinsics)[None])
        boxes.append(torch.stack([pixels[0].amin(0), pixels[0].amax(0)]).numpy())
    return np.stack(boxes)


@pytest.mark.parametrize("fill", [0.9, 1.0])
def test_framing_hits_the_fill_and_keeps_the_head_inside(generator, fill):
    """Up close (120 px focal length at 128 px) the extent of the head shrinks faster than 1/distance:
    the former fixed six updates of the distance oscillated, missed the fill by pixels and left some
    heads partly outside the image."""
    with configured(generator, SynthConfig.head_only(fill=(fill, fill), focal=(120.0, 120.0))) as gen:
        boxes = _framed_box(gen, 1, 40)
    side = (boxes[:, 1] - boxes[:, 0]).max(-1)
    np.testing.assert_allclose(side, fill * 128, atol=0.01)
    assert boxes.min() >= -0.5 and boxes.max() <= 127.5


@pytest.mark.parametrize("focal,fill", [(20000.0, 0.4), (5.0, 1.0)])
def test_a_head_beyond_the_clipping_planes_is_refused(generator, focal, fill):
    """Past the far plane (50 m) the image was empty and all 24 landmarks marked visible; inside the
    near plane (5 mm) the head was clipped and missed its fill."""
    with configured(generator, SynthConfig.head_only(fill=(fill, fill), focal=(focal, focal))) as gen:
        with pytest.raises(ValueError, match=rf"focal: {focal:.0f} px \(at 128 px\) with fill {fill:.2f} puts the "
                                             r"head .* outside the renderer's clipping range \[5, 50000\] mm"):
            gen.generate(0, range(4))


def test_no_directional_light_renders(generator):
    """num_lights = (0, k) is allowed; a draw of no light made a (0,) direction array the renderer refused."""
    with configured(generator, SynthConfig.head_only(num_lights=(0, 0), use_skimage=False)) as gen:
        batch = gen.generate(0, range(2))
    skin = batch.image[batch.segmentation == 1]
    assert skin.size and 0 < skin.mean() < 255  # the ambient light alone shows the head


def test_a_framing_that_did_not_converge_is_still_inside(generator, monkeypatch):
    """Whatever the solve leaves, the head is moved back until it lies inside the image."""
    from facenormals.data import generator as module

    monkeypatch.setattr(module, "_FRAME_ITERATIONS", 0)  # only the first guess, which ignores perspective
    with configured(generator, SynthConfig.head_only(fill=(0.9, 1.0), focal=(120.0, 200.0))) as gen:
        boxes = _framed_box(gen, 2, 40)
    assert boxes.min() >= -0.5 and boxes.max() <= 127.5


def test_the_head_of_seed_0_index_208_is_inside(generator):
    """On ICT-FaceKit six fixed distance updates left this head reaching u = 128.13 (the image ends at 127.5)."""
    record = generator._plan(0, 208).record  # the camera, without rendering
    _, vertices = generator.assets.vertices(record["shape_coeffs"], record["expression_coeffs"])
    head = torch.from_numpy(vertices[generator.assets.framing])[None]
    pixels, _ = project_points(head, *(torch.from_numpy(record[k])[None] for k in ("rotation", "translation", "intrinsics")))
    assert float(pixels.amin()) >= -0.5 and float(pixels.amax()) <= 127.5


def test_visibility_rules():
    """Each clause of the landmark visibility on hand-made scenes: a square patch on each landmark's
    ray (focal length 500 px, landmarks 400 mm away: the depth slack is max(3 mm, 2 px = 1.6 mm) = 3 mm)."""
    from facenormals.data import SyntheticHeadGenerator
    from facenormals.data.render import MeshPart

    generator = SyntheticHeadGenerator("builtin", SynthConfig.head_only(use_skimage=False))
    skin, hair = LABELS["skin"], LABELS["hair"]
    cases = [  # (u, v), label and depth of a patch across the landmark's ray (None: none), expected visibility
        ((10.2, 10.0), skin, 400.0, True),  # on the head surface
        ((20.0, 20.4), skin, 398.0, True),  # 2 mm in front: within the slack (a crease)
        ((30.0, 30.0), skin, 396.0, False),  # 4 mm in front: hidden by the head
        ((40.0, 40.0), hair, 399.9, False),  # hair in front, however thin, hides it
        ((50.0, 50.0), hair, 401.0, True),  # hair behind it (a landmark on the outline)
        ((60.0, 60.0), None, None, True),  # nothing on the ray
        ((127.4, 70.0), None, None, True),  # the last pixel column
        ((127.6, 80.0), None, None, False),  # outside the image, though nothing hides it
        ((90.0, -0.6), None, None, False),
    ]
    pixels = np.array([c[0] for c in cases], np.float32)
    focal, centre = 500.0, 63.5
    landmarks = np.column_stack([(pixels - centre) * 400.0 / focal, np.full(len(cases), 400.0)])
    square = np.array([[-2.0, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]])
    parts = [MeshPart(vertices=(square + landmarks[k] * depth / 400.0).astype(np.float32), normals=np.tile([0, 0, -1.0], (4, 1)),
                      colors=np.ones((4, 3)), faces=np.array([[0, 1, 2], [0, 2, 3]]), label=label)
             for k, (_, label, depth, _) in enumerate(cases) if label is not None]
    visible = generator._visible(pixels, landmarks, focal, parts)
    assert visible.tolist() == [c[3] for c in cases]


@pytest.mark.parametrize("model", [None, 3, torch.zeros(3)])
def test_a_model_of_the_wrong_type_is_named_model(model):
    """Regression: SyntheticHeadGenerator(None) raised load_model's error, naming its `spec`."""
    from facenormals.data import SyntheticHeadGenerator

    with pytest.raises(ValueError, match=r"^model: expected a MorphableModel or a spec for load_model .*, got "
                                         f"{type(model).__name__} "):
        SyntheticHeadGenerator(model)
