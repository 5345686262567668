import math

import numpy as np
import pytest
import torch
from torch import nn

from facenormals.data import landmark_maps
from facenormals.nn import NormalLandmarkUNet, UNetOutput
from facenormals.training import calibrate_landmark_threshold, evaluate_network, landmark_threshold, normal_angles

from .conftest import TinyHeads


class Cheat(nn.Module):
    """Looks up the true maps of the sample whose image it is given; optional landmark shift and gain.
    It knows no mirrored images, so the tests score it with ``mirror=False``."""

    def __init__(self, data, shift=(0.0, 0.0), gain=1.0, floor=0.0):
        super().__init__()
        self.p = nn.Parameter(torch.zeros(()))
        self.data, self.shift, self.gain, self.floor = data, torch.tensor(shift), gain, floor

    def forward(self, images):
        items = [next(d for d in self.data.items if torch.equal(d["image"], im)) for im in images]
        normals = torch.stack([d["normals"] for d in items])
        fg = torch.stack([d["foreground"] for d in items])
        normals = torch.where(fg, normals, torch.tensor([0.0, 0.0, -1.0]).view(3, 1, 1))
        pts = torch.stack([d["landmarks"] for d in items]) + self.shift
        vis = torch.stack([d["landmark_visible"] for d in items])
        maps = landmark_maps(pts, vis, images.shape[-2:]) * self.gain + self.floor
        return UNetOutput(normals, maps, fg.float() * 20 - 10)


def test_normal_angles_against_numpy():
    g = torch.Generator().manual_seed(0)
    a = torch.nn.functional.normalize(torch.randn(2, 3, 4, 5, generator=g), dim=1)
    b = torch.nn.functional.normalize(torch.randn(2, 3, 4, 5, generator=g), dim=1)
    mask = torch.rand(2, 1, 4, 5, generator=g) > 0.5
    got = normal_angles(a, b, mask)
    an, bn, m = a.numpy(), b.numpy(), mask.numpy()[:, 0]
    ref = [math.degrees(math.acos(np.clip(np.dot(an[i, :, r, c], bn[i, :, r, c]), -1, 1)))
           for i in range(2) for r in range(4) for c in range(5) if m[i, r, c]]
    np.testing.assert_allclose(got.numpy(), ref, atol=1e-3)


def test_perfect_network_scores_perfectly_and_a_shift_shows():
    data = TinyHeads(6)
    m = evaluate_network(Cheat(data), data, batch_size=4, mirror=False)
    assert m.normal_mean_deg < 0.05 and m.landmark_median_px < 0.05 and m.visibility_accuracy == 1.0
    assert m.foreground_iou == 1.0
    shifted = evaluate_network(Cheat(data, shift=(3.0, 4.0)), data, batch_size=4, mirror=False)
    assert abs(shifted.landmark_median_px - 5.0) < 0.1  # points near the border are clamped: the median


def test_calibrated_threshold_is_stored_and_used():
    data = TinyHeads(6)
    hazy = Cheat(data, gain=0.6, floor=0.3)  # every map exceeds 0.3, visible peaks reach 0.9
    assert evaluate_network(hazy, data, threshold=0.1, mirror=False).visibility_accuracy < 0.9
    threshold, accuracy = calibrate_landmark_threshold(hazy, data, mirror=False, per_landmark=False)
    assert 0.3 < threshold < 0.9 and accuracy == 1.0
    hazy.metadata = {"landmark_threshold": threshold}
    assert landmark_threshold(hazy) == threshold
    assert evaluate_network(hazy, data, mirror=False).visibility_accuracy == 1.0
    with pytest.raises(ValueError, match="dataset: expected at least one sample"):
        calibrate_landmark_threshold(hazy, data, max_samples=0, mirror=False)


def test_per_landmark_thresholds_separate_what_one_cannot():
    """Half the channels have hazy maps of 0.3 with visible peaks at 0.55, the other half 0.7 and 0.95:
    no common threshold separates both, one per channel does."""
    data = TinyHeads(6)
    floor = torch.tensor([0.3] * 12 + [0.7] * 12).view(24, 1, 1)
    net = Cheat(data, gain=0.25, floor=floor)
    common, common_accuracy = calibrate_landmark_threshold(net, data, mirror=False, per_landmark=False)
    per_channel, accuracy = calibrate_landmark_threshold(net, data, mirror=False)
    assert isinstance(common, float) and common_accuracy < 1.0
    assert len(per_channel) == 24 and accuracy == 1.0
    visible = torch.stack([d["landmark_visible"] for d in data.items])
    mixed = [c for c in range(24) if 0 < int(visible[:, c].sum()) < len(data.items)]  # both outcomes seen
    assert len(mixed) >= 4
    for c in mixed:
        assert (0.3 < per_channel[c] < 0.55) if c < 12 else (0.7 < per_channel[c] < 0.95), (c, per_channel[c])
    net.metadata = {"landmark_threshold": per_channel}
    assert torch.equal(landmark_threshold(net), torch.tensor(per_channel))
    assert evaluate_network(net, data, mirror=False).visibility_accuracy == 1.0


def test_posed_visibility_scores_the_decisions_after_dropping_hidden_landmarks():
    """``visibility_accuracy_posed`` equals the score of the detections that drop_hidden_landmarks keeps,
    recomputed here from the same maps."""
    from facenormals.data import landmarks_from_maps
    from facenormals.fitting import drop_hidden_landmarks
    from facenormals.models import builtin_head_model

    data = TinyHeads(6)
    net = Cheat(data, gain=0.6, floor=0.3)
    model = builtin_head_model()
    plain = evaluate_network(net, data, batch_size=4, threshold=0.5, mirror=False)
    assert plain.visibility_accuracy_posed is None
    posed = evaluate_network(net, data, batch_size=4, threshold=0.5, mirror=False, model=model, focal=40.0)
    assert posed.visibility_accuracy == plain.visibility_accuracy
    images = torch.stack([d["image"] for d in data.items])
    maps = net(images).landmarks
    points, _ = landmarks_from_maps(maps, threshold=float("-inf"))
    found = maps.flatten(2).amax(-1) > 0.5
    K = torch.tensor([40.0, 15.5, 15.5]).expand(6, 3)
    kept, _ = drop_hidden_landmarks(points, found, model, K, (32, 32))
    visible = torch.stack([d["landmark_visible"] for d in data.items])
    assert posed.visibility_accuracy_posed == pytest.approx(float((kept == visible).double().mean()), abs=1e-12)
    assert "with the pose" in str(posed)


def test_posed_visibility_needs_the_network_landmarks():
    from facenormals.models import builtin_head_model

    data = TinyHeads(2)
    model = builtin_head_model()
    model.landmark_names = ["ear_canal"] + list(model.landmark_names[1:])
    with pytest.raises(ValueError, match=r"model: landmarks \['ear_canal'\]"):
        evaluate_network(Cheat(data), data, mirror=False, model=model)


def test_evaluate_network_runs_where_asked_and_checks_thresholds():
    data = TinyHeads(4)
    net = NormalLandmarkUNet(base_channels=4, depth=2)
    moved = []
    original = net.to

    def to(*args, **kwargs):
        moved.append(args[0] if args else kwargs.get("device"))
        return original(*args, **kwargs)

    net.to = to
    evaluate_network(net, data, mirror=False, device="cpu")
    assert [torch.device(d) for d in moved] == [torch.device("cpu"), torch.device("cpu")]  # there and back
    with pytest.raises(ValueError, match=r"threshold: expected one threshold per landmark channel \(24\), got 5"):
        evaluate_network(net, data, mirror=False, threshold=[0.5] * 5)
    # NaN or 7 found no landmark and scored the visibility as the hidden fraction; a string failed inside torch
    for bad, match in ((float("nan"), "got nan"), (7.0, "got 7.0"), ("high", "got 'high'"),
                       (torch.full((2, 24), 0.5), r"got shape \(2, 24\)")):
        with pytest.raises(ValueError, match=f"threshold: expected .*{match}"):
            evaluate_network(net, data, mirror=False, threshold=bad)
    for bad, match in ((torch.tensor([0.2, float("nan")]), "got nan"), (torch.tensor([]), r"shape \(0,\)"),
                       (torch.tensor([0.5, 1.5]), "got 1.5")):
        with pytest.raises(ValueError, match=f"candidates: expected .*{match}"):
            calibrate_landmark_threshold(net, data, mirror=False, candidates=bad)


def test_normal_angles_refuses_nan_and_integer_maps():
    from facenormals.training import normal_angles

    n = torch.zeros(1, 3, 1, 2)
    n[:, 2] = -1.0
    mask = torch.ones(1, 1, 1, 2, dtype=torch.bool)
    bad = n.clone()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="predicted: expected finite values"):
        normal_angles(bad, n, mask)
    with pytest.raises(ValueError, match="target: expected a floating-point tensor"):
        normal_angles(n, n.long(), mask)
    # a zero normal (background of a masked normal map) scored 0 degrees against anything
    missed = n.clone()
    missed[0, :, 0, 1] = 0.0
    with pytest.raises(ValueError, match="predicted: 1 pixels of mask hold no normal"):
        normal_angles(missed, n, mask)
    with pytest.raises(ValueError, match="target: 1 pixels of mask hold no normal"):
        normal_angles(n, missed, mask)
    assert normal_angles(missed, n, torch.tensor([[[[True, False]]]])).tolist() == [0.0]  # outside the mask: fine


def test_normal_angles_are_exact_near_zero():
    """acos of a float32 cosine reads up to 0.02 degrees for identical normals; atan2 reads 0."""
    n = torch.nn.functional.normalize(torch.randn(2, 3, 16, 16, generator=torch.Generator().manual_seed(0)), dim=1)
    mask = torch.ones(2, 1, 16, 16, dtype=torch.bool)
    assert float(normal_angles(n, n, mask).max()) < 1e-4
    flipped = normal_angles(n, -n, mask)
    assert float((flipped - 180.0).abs().max()) < 1e-4
    r = torch.tensor([0.0, 0.0, -1.0]).view(1, 3, 1, 1).expand(2, 3, 16, 16)
    tilted = torch.stack([torch.full((2, 16, 16), math.sin(0.01)), torch.zeros(2, 16, 16),
                          torch.full((2, 16, 16), -math.cos(0.01))], 1)
    assert_close = torch.testing.assert_close
    assert_close(normal_angles(tilted, r, mask), torch.full((512,), math.degrees(0.01)), rtol=1e-4, atol=1e-5)


def test_normal_angles_need_one_dtype_and_device():
    """A float64 map against a float32 one failed inside torch.linalg.cross."""
    n = torch.zeros(1, 3, 1, 2)
    n[:, 2] = -1.0
    mask = torch.ones(1, 1, 1, 2, dtype=torch.bool)
    with pytest.raises(ValueError, match="target"):
        normal_angles(n.double(), n, mask)
    assert normal_angles(n, n, mask).tolist() == [0.0, 0.0]  # exactly: a × a is 0


class _Spoiled(TinyHeads):
    """TinyHeads with item ``bad`` spoiled: a NaN pixel, 0-255 values, a NaN visible landmark, no normals."""

    def __init__(self, spoil, bad=5, count=6):
        super().__init__(count, size=16)
        item = dict(self.items[bad])
        if spoil == "nan image":
            item["image"] = item["image"].clone()
            item["image"][0, 3, 3] = float("nan")
        elif spoil == "image 255":
            item["image"] = item["image"] * 255
        elif spoil == "nan landmark":
            item["landmarks"] = item["landmarks"].clone()
            item["landmark_visible"] = item["landmark_visible"].clone()
            item["landmarks"][2] = float("nan")
            item["landmark_visible"][2] = True
        elif spoil == "hidden nan landmark":
            item["landmarks"] = item["landmarks"].clone()
            item["landmark_visible"] = item["landmark_visible"].clone()
            item["landmarks"][2] = float("nan")
            item["landmark_visible"][2] = False
        elif spoil == "nan normals":
            item["normals"] = item["normals"].clone()
            item["normals"][0, 8, 8] = float("nan")
        elif spoil == "no normals":
            for other in range(len(self.items)):
                self.items[other] = {k: v for k, v in self.items[other].items() if k != "normals"}
            item = self.items[bad]
        self.items[bad] = item


@pytest.mark.parametrize(
    "spoil, match",
    [
        ("nan image", "dataset: expected finite image, got NaN or infinite values in sample 5"),
        ("image 255", r"dataset: expected images of RGB values in \[0, 1\] \(an 8-bit image / 255\), got values in "
                      r"\[.*\] in sample 5"),
        ("nan landmark", "dataset: expected finite landmarks where visible, got NaN or infinite values in sample 5"),
        ("nan normals", "dataset: expected finite normals, got NaN or infinite values in sample 5"),
        ("no normals", "dataset: expected items with the keys image, normals, foreground, landmarks, landmark_visible; "
                       "the items from sample 0 lack 'normals'"),
    ],
)
@pytest.mark.parametrize("mirror", [False, True])
def test_evaluate_network_checks_the_dataset(spoil, match, mirror):
    """Regression: 0-255 images were scored (predict_maps refuses them), a NaN landmark gave
    landmark_mean_px=nan, a NaN image an error naming the internal `predicted`, no normals a KeyError."""
    net = NormalLandmarkUNet(base_channels=4, depth=2)
    with pytest.raises(ValueError, match=match):
        evaluate_network(net, _Spoiled(spoil), batch_size=4, mirror=mirror)


def test_evaluate_network_takes_a_nan_landmark_that_is_hidden():
    net = NormalLandmarkUNet(base_channels=4, depth=2)
    metrics = evaluate_network(net, _Spoiled("hidden nan landmark"), batch_size=4, mirror=False)
    assert math.isfinite(metrics.landmark_mean_px)


@pytest.mark.parametrize(
    "spoil, match",
    [
        ("nan image", "dataset: expected finite image, got NaN or infinite values in sample 5"),
        ("image 255", r"dataset: expected images of RGB values in \[0, 1\]"),
    ],
)
def test_calibrate_landmark_threshold_checks_the_dataset(spoil, match):
    """Regression: one NaN pixel made every peak NaN, and the calibration returned ([0.5] * 24, 0.0)."""
    net = NormalLandmarkUNet(base_channels=4, depth=2)
    with pytest.raises(ValueError, match=match):
        calibrate_landmark_threshold(net, _Spoiled(spoil), batch_size=4, mirror=False)
    assert calibrate_landmark_threshold(net, _Spoiled("no normals"), batch_size=4, mirror=False)[1] >= 0


class _RolledForeground(Cheat):
    """The true maps, with the foreground logits rolled 2 px to the right."""

    def forward(self, images):
        out = super().forward(images)
        return UNetOutput(out.normals, out.landmarks, out.foreground_logits.roll(2, dims=-1))


def test_foreground_iou_against_numpy():
    """Only IoU = 1 of a perfect network was checked: a hard-coded 1.0 passed."""
    data = TinyHeads(6)
    m = evaluate_network(_RolledForeground(data), data, batch_size=4, mirror=False)
    truth = np.stack([d["foreground"].numpy()[0] for d in data.items])
    predicted = np.roll(truth, 2, axis=-1)
    expected = (truth & predicted).sum() / (truth | predicted).sum()
    assert 0.3 < expected < 0.99
    assert m.foreground_iou == pytest.approx(float(expected), abs=1e-9)


def test_mirror_calibration_gives_each_left_right_pair_one_threshold(monkeypatch):
    """Regression: mirror-averaged maps are mirror-symmetric, but each channel got its own threshold
    (the shipped right_ear_lobe 0.675, left_ear_lobe 0.625), so 36 of 2,304 detections changed when
    a photo was mirrored. Here a pair's channels separate at different heights: alone, they get
    different thresholds; calibrated as mirror-averaged maps, one per pair."""
    import facenormals.training.metrics as metrics
    from facenormals.models.landmarks import LANDMARK_NAMES
    from facenormals.nn import mirror_permutation

    data = TinyHeads(8)
    left = torch.tensor([name.startswith("left") for name in LANDMARK_NAMES])
    hidden_peak, visible_peak = torch.where(left, 0.6, 0.2), torch.where(left, 0.8, 0.5)

    class Peaks(nn.Module):
        """Each channel's peak at the centre: its visible or its hidden height, by the sample's labels."""

        def __init__(self):
            super().__init__()
            self.p = nn.Parameter(torch.zeros(()))

        def forward(self, images):
            visible = torch.stack([next(d["landmark_visible"] for d in data.items if torch.equal(d["image"], im))
                                   for im in images])
            z = torch.zeros(len(images), 24, 32, 32)
            z[..., 16, 16] = torch.where(visible, visible_peak, hidden_peak)
            return UNetOutput(torch.zeros(len(images), 3, 32, 32), z, torch.zeros(len(images), 1, 32, 32))

    net = Peaks()
    alone, _ = calibrate_landmark_threshold(net, data, mirror=False)
    monkeypatch.setattr(metrics, "mirror_averaged", lambda net, images: net(images))  # maps as they are
    pooled, _ = calibrate_landmark_threshold(net, data, mirror=True)
    partner = mirror_permutation()
    pairs = [(c, partner[c]) for c in range(24) if partner[c] > c]
    assert len(pairs) == 9
    assert any(alone[a] != alone[b] for a, b in pairs)
    assert all(pooled[a] == pooled[b] for a, b in pairs)
    unpaired = [c for c in range(24) if partner[c] == c]
    assert [pooled[c] for c in unpaired] == [alone[c] for c in unpaired]
