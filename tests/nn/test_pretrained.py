"""The weights shipped in the package: present, small, loadable, and a working network."""

import re

import pytest
import torch

from facenormals.nn import NormalLandmarkUNet, load_weights, pretrained_weights_path


def test_shipped_weights_are_small_and_load():
    path = pretrained_weights_path()
    assert path.is_file(), f"{path} is missing from the package"
    assert path.stat().st_size <= 20e6
    net = load_weights()
    assert isinstance(net, NormalLandmarkUNet) and not net.training
    assert net.metadata["samples_seen"] >= 60_000
    with torch.no_grad():
        out = net(torch.rand(2, 3, 128, 128, generator=torch.Generator().manual_seed(0)))
    assert out.normals.shape == (2, 3, 128, 128) and out.landmarks.shape == (2, 24, 128, 128)
    torch.testing.assert_close(out.normals.norm(dim=1), torch.ones(2, 128, 128))


def test_shipped_thresholds_are_mirror_symmetric():
    """reconstruct decodes mirror-averaged maps, which are mirror-symmetric: with separate
    thresholds for a left/right pair (ear lobes 0.675 and 0.625 before session 26), mirroring a
    photo changed its detections."""
    from facenormals.nn import mirror_permutation
    from facenormals.training import landmark_threshold

    net = load_weights()
    threshold = landmark_threshold(net)
    assert threshold.shape == (24,) and torch.equal(threshold, threshold[mirror_permutation()])
    assert net.metadata["image_size"] == 128  # the crops predict_maps expects


def test_shipped_network_finds_the_example_face():
    """On the bundled photo the network finds a head in the middle of the crop and most landmarks."""
    from pathlib import Path

    from facenormals.reconstruct import predict_maps, prepare_view

    photo = Path(__file__).resolve().parents[2] / "examples" / "data" / "astronaut.jpg"
    view = prepare_view(photo)
    maps = predict_maps(load_weights(), torch.from_numpy(view.crop).permute(2, 0, 1)[None].float() / 255.0)
    foreground = maps.normal_maps.norm(dim=1) > 0.5
    assert foreground[0, 64, 64] and 0.15 < float(foreground.float().mean()) < 0.9
    assert int(maps.found.sum()) >= 12
    names = __import__("facenormals").LANDMARK_NAMES
    nose = maps.landmarks[0, names.index("nose_tip")]
    assert 40 < float(nose[0]) < 88 and 40 < float(nose[1]) < 100  # the nose tip is near the crop centre


def test_load_weights_rejects_a_mismatching_architecture(tmp_path):
    from facenormals.nn.pretrained import WEIGHTS_FORMAT, WEIGHTS_VERSION

    net = NormalLandmarkUNet(base_channels=4, depth=2)
    path = tmp_path / "w.pt"
    torch.save({"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION,
                "architecture": {"base_channels": 8, "depth": 2, "num_landmarks": 24},
                "state_dict": net.state_dict(), "metadata": {}}, path)
    with pytest.raises(ValueError, match="w.pt: weights do not match"):
        load_weights(path)
    torch.save({"format": "something else"}, path)
    with pytest.raises(ValueError, match="not a facenormals network weight file"):
        load_weights(path)
    torch.save({"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION, "state_dict": net.state_dict()}, path)
    with pytest.raises(ValueError, match="w.pt: the weight file lacks its architecture"):
        load_weights(path)
    good = {"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION,
            "architecture": {"base_channels": 4, "depth": 2, "num_landmarks": 24}, "state_dict": net.state_dict(),
            "metadata": {}}
    for change, match in (({"state_dict": {**net.state_dict(), "extra": "text"}}, "state_dict holds entries that are not tensors"),
                          ({"metadata": ["a", "b"]}, "metadata is not a dictionary"),
                          ({"architecture": {"base_channels": 4, "depth": 0, "num_landmarks": 24}},
                           "architecture .* is not a valid network")):
        torch.save({**good, **change}, path)
        with pytest.raises(ValueError, match=f"w.pt: the weight file's {match}"):
            load_weights(path)
    # a NaN threshold detected nothing, silently; a string failed in the middle of a reconstruction
    for threshold, match in ((float("nan"), "got nan"), ("abc", "got 'abc'"), (1.5, "got 1.5"),
                             ([0.5] * 3, r"one threshold per landmark channel \(24\), got 3")):
        torch.save({**good, "metadata": {"landmark_threshold": threshold}}, path)
        with pytest.raises(ValueError, match=f"w.pt: metadata landmark_threshold: expected .*{match}"):
            load_weights(path)
    torch.save({**good, "metadata": {"landmark_threshold": [0.5] * 24}}, path)
    assert load_weights(path).metadata["landmark_threshold"] == [0.5] * 24
    # NaN weights made every map NaN: the error named the maps, far from the file
    state = {k: v.clone() for k, v in net.state_dict().items()}
    name = next(k for k, v in state.items() if v.is_floating_point())
    state[name].view(-1)[0] = float("inf")
    torch.save({**good, "state_dict": state}, path)
    with pytest.raises(ValueError, match=f"w.pt: the weights hold NaN or infinite values \\({re.escape(name)}: 1 of"):
        load_weights(path)
    # integer weights were copied into the float parameters: an int8 file loaded as an all-zero network
    state = {k: (v.to(torch.int8) if v.is_floating_point() else v) for k, v in net.state_dict().items()}
    torch.save({**good, "state_dict": state}, path)
    with pytest.raises(ValueError, match=f"w.pt: the weight file stores {re.escape(name)} as torch.int8; expected "
                                         "a floating dtype"):
        load_weights(path)


def test_update_weight_metadata_keeps_the_weights(tmp_path):
    import shutil

    from facenormals.nn import update_weight_metadata

    path = tmp_path / "mine.pt"
    shutil.copy(pretrained_weights_path(), path)
    before = load_weights(path)
    update_weight_metadata(path, fit_weights={"normals": 0.25, "prior": 1.5}, note="tuned")
    after = load_weights(path)
    assert after.metadata == {**before.metadata, "fit_weights": {"normals": 0.25, "prior": 1.5}, "note": "tuned"}
    for a, b in zip(before.state_dict().values(), after.state_dict().values()):
        assert torch.equal(a, b)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.pt"]  # no temporary file left
    with pytest.raises(FileNotFoundError, match="missing.pt: no such weight file"):
        update_weight_metadata(tmp_path / "missing.pt", note="x")
    (tmp_path / "junk.pt").write_bytes(b"not a weight file")
    with pytest.raises(ValueError, match="junk.pt: not a readable weight file"):
        update_weight_metadata(tmp_path / "junk.pt", note="x")


def test_metadata_that_a_weight_file_cannot_hold_is_refused(tmp_path):
    import re
    import shutil

    import numpy as np

    from facenormals.nn import update_weight_metadata

    path = tmp_path / "mine.pt"
    shutil.copy(pretrained_weights_path(), path)
    before = path.read_bytes()
    for bad, name in ((np.float64(0.3), "metadata['landmark_threshold']: expected plain data"),
                      ([0.1, np.float32(2)], "metadata['landmark_threshold'][1]: expected plain data"),
                      ({"a": tmp_path}, "metadata['landmark_threshold']['a']: expected plain data")):
        with pytest.raises(ValueError, match=re.escape(name)):
            update_weight_metadata(path, landmark_threshold=bad)
    # values load_weights refuses were written, and the file then refused
    for bad, match in ((float("nan"), "got nan"), (1.5, "got 1.5"), ([0.3] * 3, r"per landmark channel \(24\), got 3")):
        with pytest.raises(ValueError, match=f"landmark_threshold: expected .*{match}"):
            update_weight_metadata(path, landmark_threshold=bad)
    assert path.read_bytes() == before
    update_weight_metadata(path, landmark_threshold=[0.3] * 24, note={"run": "x", "steps": 3, "ok": True, "none": None})
    assert load_weights(path).metadata["note"]["steps"] == 3


def test_unreadable_weight_files_never_suggest_weights_only_false(tmp_path):
    import numpy as np

    torch.save({"x": np.float64(1.0)}, tmp_path / "objects.pt")
    (tmp_path / "garbage.pt").write_bytes(b"garbage")
    for name, reason in (("objects.pt", "holds Python objects other than tensors"), ("garbage.pt", "Unsupported operand")):
        with pytest.raises(ValueError, match=f"{name}: not a readable weight file") as caught:
            load_weights(tmp_path / name)
        assert reason in str(caught.value) and "weights_only" not in str(caught.value)


@pytest.mark.parametrize("change, match", [
    ({"base_channels": 10**6}, r"base_channels: expected an integer in \[1, 4096\], got 1000000"),
    ({"depth": 17}, r"depth: expected an integer in \[1, 16\], got 17"),
    ({"num_landmarks": 10_001}, r"num_landmarks: expected an integer in \[0, 10000\], got 10001"),
    ({"depth": 2.7}, r"depth: expected an integer in \[1, 16\], got 2.7"),
    ({"depth": True}, r"depth: expected an integer in \[1, 16\], got True"),
])
def test_an_absurd_architecture_is_refused_before_the_network_is_built(tmp_path, change, match):
    """base_channels 10**6 tried to allocate 72 TB (a RuntimeError naming no file); depth 2.7 loaded as 2."""
    from facenormals.nn.pretrained import WEIGHTS_FORMAT, WEIGHTS_VERSION

    net = NormalLandmarkUNet(base_channels=4, depth=2)
    path = tmp_path / "w.pt"
    torch.save({"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION,
                "architecture": {"base_channels": 4, "depth": 2, "num_landmarks": 24, **change},
                "state_dict": net.state_dict(), "metadata": {}}, path)
    with pytest.raises(ValueError, match=f"w.pt: the weight file's architecture .* is not a valid network \\({match}\\)"):
        load_weights(path)


def test_weights_are_checked_against_the_architecture_before_it_is_built(tmp_path, monkeypatch):
    """The stated architecture is built only once its shapes match the weights: a file stating a
    wide network beside small weights is refused without allocating the wide one."""
    from facenormals.nn import pretrained
    from facenormals.nn.pretrained import WEIGHTS_FORMAT, WEIGHTS_VERSION

    built = []

    class Recording(NormalLandmarkUNet):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            built.append(self.head.weight.device.type)

    monkeypatch.setattr(pretrained, "NormalLandmarkUNet", Recording)
    path = tmp_path / "w.pt"
    small = NormalLandmarkUNet(num_landmarks=10, base_channels=4, depth=2).state_dict()
    for arch, match in (({"base_channels": 256, "depth": 2, "num_landmarks": 10}, r"stem.0.weight: shape \(4, 3, 3, 3\), "
                                                                                  r"expected \(256, 3, 3, 3\)"),
                        ({"base_channels": 4, "depth": 2, "num_landmarks": 24}, r"head.weight: shape \(14, 4, 1, 1\), "
                                                                                 r"expected \(28, 4, 1, 1\)"),
                        ({"base_channels": 4, "depth": 3, "num_landmarks": 10}, r"missing down.2.0.0.weight")):
        torch.save({"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION, "architecture": arch, "state_dict": small,
                    "metadata": {}}, path)
        with pytest.raises(ValueError, match=f"w.pt: weights do not match the architecture .*{match}"):
            load_weights(path)
    assert "cpu" not in built  # only shapes (meta tensors) were built
    torch.save({"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION,
                "architecture": {"base_channels": 4, "depth": 2, "num_landmarks": 10}, "state_dict": small,
                "metadata": {}}, path)
    assert load_weights(path).num_landmarks == 10 and "cpu" in built


@pytest.mark.parametrize(
    "value, match",
    [
        (float("nan"), "got nan"),
        (float("inf"), "got inf"),
        (0.0, "got 0.0"),
        (1.5, "got 1.5"),
        ("0.3", "got '0.3'"),
        ([0.1] * 3, r"expected one threshold per landmark channel \(24\), got 3"),
    ],
)
def test_landmark_threshold_refuses_a_bad_metadata_entry(value, match):
    """Regression: a NaN threshold set on a network's metadata came back as nan (and detected nothing)."""
    from facenormals.nn.pretrained import landmark_threshold

    net = NormalLandmarkUNet(base_channels=4, depth=2)
    net.metadata = {"landmark_threshold": value}
    with pytest.raises(ValueError, match=re.escape("net.metadata['landmark_threshold']: ") + f".*{match}"):
        landmark_threshold(net)
    net.metadata = {"landmark_threshold": [0.3] * 24}
    assert landmark_threshold(net).shape == (24,)
    assert landmark_threshold(torch.nn.Linear(2, 2)) == 0.1  # no metadata: the default


@pytest.mark.parametrize("device", ["bogus", "", "cuda:x", None, 3.5, "mps", "meta"])
def test_load_weights_names_a_bad_device(device):
    """Regression: load_weights(None, device="bogus") ended in torch's RuntimeError."""
    with pytest.raises(ValueError, match=re.escape(f"device: expected 'cpu', 'cuda' or 'cuda:N', got {device!r}")):
        load_weights(None, device=device)


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_load_weights_names_an_unavailable_cuda_device():
    with pytest.raises(ValueError, match="device: 'cuda' requested but this torch build .* has no CUDA device"):
        load_weights(None, device="cuda")


def _flip_member_byte(path, member_end: str, offset: int, mask: int = 0xFF) -> str:
    """Flip the bits ``mask`` of byte ``offset`` of the (stored) zip member of ``path`` whose name ends in
    ``member_end``; returns the member's name."""
    import struct
    import zipfile

    with zipfile.ZipFile(path) as archive:
        info = next(i for i in archive.infolist() if i.filename.endswith(member_end))
    data = bytearray(path.read_bytes())
    name_length, extra_length = struct.unpack_from("<HH", data, info.header_offset + 26)  # the local header's
    data[info.header_offset + 30 + name_length + extra_length + offset] ^= mask
    path.write_bytes(bytes(data))
    return info.filename


def test_a_damaged_byte_in_a_weight_file_fails_its_crc_check(tmp_path):
    """Regression: torch.load never checks the CRC-32 of its zip's members: of 184 flipped bytes, 40 loaded
    silently, e.g. all four values of a weight tensor became 5580, or metadata changed. update_weight_metadata
    would then have written the damage back with fresh checksums."""
    import zipfile

    from facenormals.nn import update_weight_metadata
    from facenormals.nn.pretrained import WEIGHTS_FORMAT, WEIGHTS_VERSION

    net = NormalLandmarkUNet(base_channels=4, depth=2)
    good = tmp_path / "good.pt"
    torch.save({"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION,
                "architecture": {"base_channels": 4, "depth": 2, "num_landmarks": 24}, "state_dict": net.state_dict(),
                "metadata": {"note": "tuned"}}, good)
    assert load_weights(good).metadata == {"note": "tuned"}
    with zipfile.ZipFile(good) as archive:  # where the metadata's text lies in data.pkl
        in_pickle = archive.read(next(n for n in archive.namelist() if n.endswith("/data.pkl"))).index(b"tuned")
    path = tmp_path / "w.pt"
    for member_end, offset, mask in (("/data/0", 2, 0xFF), ("/data.pkl", in_pickle + 2, 0x01)):  # a weight; "tuoed"
        path.write_bytes(good.read_bytes())
        member = _flip_member_byte(path, member_end, offset, mask)
        damaged = path.read_bytes()
        for load in (load_weights, lambda p: update_weight_metadata(p, note="x")):
            with pytest.raises(ValueError, match=f"w.pt: not a readable weight file \\(damaged: its member "
                                                 f"{re.escape(repr(member))} fails its CRC-32 check\\)"):
                load(path)
        assert path.read_bytes() == damaged  # not rewritten
    update_weight_metadata(good, note="again")  # what update_weight_metadata writes stays a torch file
    assert torch.load(good, weights_only=True)["metadata"] == {"note": "again"}


@pytest.mark.parametrize("items, match", [
    ([1], "metadata: expected a dict of plain values (str keys; str, int, float, bool, None, lists and dicts of "
          "them), got list [1]"),
    (None, "metadata: expected a dict of plain values"),
    ("note", "metadata: expected a dict of plain values"),
    ({1: "x"}, "metadata: expected string keys, got int 1"),
])
def test_check_plain_metadata_names_metadata_that_is_not_a_dict(items, match):
    """Regression: a list was an AttributeError ('list' object has no attribute 'items')."""
    from facenormals.nn.pretrained import check_plain_metadata

    with pytest.raises(ValueError, match=re.escape(match)):
        check_plain_metadata(items)
    check_plain_metadata({"note": {"run": "x", "steps": [1, 2.5, None, True]}})
