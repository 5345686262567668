import json
import os

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from facenormals.data import HeadlessGLError, PhotoAugmentation, SynthConfig, SyntheticHeadDataset, write_dataset
from facenormals.data.shards import read_manifest

CONFIG = SynthConfig(occluder_probability=0.5)


def _write(root, count=10, **kwargs):
    try:
        return write_dataset(root, count, workers=kwargs.pop("workers", 1), seed=kwargs.pop("seed", 1),
                             model_spec="builtin", shard_size=kwargs.pop("shard_size", 4),
                             config=kwargs.pop("config", CONFIG), progress=False, **kwargs)
    except HeadlessGLError as error:
        pytest.skip(f"no headless OpenGL: {error}")


def _copy_with_manifest(dataset_root, tmp_path, **changes):
    """A copy of the dataset whose manifest has ``changes``."""
    import shutil

    root = tmp_path / "copy"
    shutil.copytree(dataset_root, root)
    manifest = json.loads((root / "manifest.json").read_text())
    (root / "manifest.json").write_text(json.dumps({**manifest, **changes}))
    return root


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth")
    summary = _write(root)
    assert summary.shards_written == 3 and summary.samples == 10
    return root


def test_layout_and_manifest(dataset_root):
    names = sorted(os.listdir(dataset_root))
    assert names == [".synth.lock", "manifest.json", "shard_00000.npz", "shard_00001.npz", "shard_00002.npz"]
    manifest = read_manifest(dataset_root)
    assert manifest["count"] == 10 and manifest["seed"] == 1 and manifest["model"]["name"] == "builtin"
    assert SynthConfig.from_dict(manifest["config"]) == CONFIG
    with np.load(dataset_root / "shard_00002.npz") as shard:  # plain numpy can read a shard
        assert shard["index"].tolist() == [8, 9]
        assert shard["image/0001"].shape == (128, 128, 3)
        assert shard["normals/0000"].dtype == np.int16


def test_dataset_items_match_the_generator(dataset_root):
    from facenormals.data import SyntheticHeadGenerator

    dataset = SyntheticHeadDataset(dataset_root)
    assert len(dataset) == 10 and "samples=10" in repr(dataset)
    item = dataset[9]
    assert item["image"].shape == (3, 128, 128) and item["image"].dtype == torch.float32
    assert item["landmark_maps"].shape == (24, 128, 128)
    assert item["foreground"].shape == (1, 128, 128) and item["foreground"].dtype == torch.bool
    assert int(item["index"]) == 9
    with SyntheticHeadGenerator("builtin", CONFIG) as generator:
        direct = generator.sample(1, 9)
    assert torch.equal(item["image"], torch.from_numpy(direct.image[0]).permute(2, 0, 1).float() / 255)
    assert float((item["normals"] - torch.from_numpy(direct.normals[0])).abs().max()) < 1e-4
    assert torch.equal(item["foreground"][0], torch.from_numpy(direct.mask[0]))
    assert torch.equal(item["landmark_visible"], torch.from_numpy(direct.landmark_visible[0]))
    visible = item["landmark_visible"]
    assert torch.equal(item["landmark_maps"].flatten(1).amax(-1) > 0, visible)
    assert dataset[-1]["index"] == 9
    with pytest.raises(IndexError):
        dataset[10]


def test_dataloader_with_two_workers(dataset_root):
    dataset = SyntheticHeadDataset(dataset_root, augment=PhotoAugmentation())
    dataset[0]  # open a shard in the parent: workers must not reuse its handle
    loader = DataLoader(dataset, batch_size=4, shuffle=True, num_workers=2,
                        generator=torch.Generator().manual_seed(0))
    seen = []
    for batch in loader:
        assert batch["image"].shape[1:] == (3, 128, 128)
        assert batch["normals"].shape[1:] == (3, 128, 128)
        assert batch["landmark_maps"].shape[1:] == (24, 128, 128)
        seen += batch["index"].tolist()
    assert sorted(seen) == list(range(10))


def test_resume_skips_finished_shards(dataset_root, tmp_path):
    root = tmp_path / "copy"
    root.mkdir()
    for name in os.listdir(dataset_root):
        (root / name).write_bytes((dataset_root / name).read_bytes())
    os.remove(root / "shard_00001.npz")
    (root / "shard_00002.npz").write_bytes(b"truncated")  # an unreadable shard is regenerated
    (root / ".shard_00001.npz.k9x2.part.npz").write_bytes(b"left by a killed writer")
    before = os.stat(root / "shard_00000.npz").st_mtime_ns
    summary = _write(root)
    assert (summary.shards_written, summary.shards_skipped, summary.samples) == (2, 1, 6)
    assert sorted(os.listdir(root)) == sorted(os.listdir(dataset_root))  # the leftover is gone
    assert os.stat(root / "shard_00000.npz").st_mtime_ns == before
    for name in ("shard_00001.npz", "shard_00002.npz"):
        with np.load(root / name) as new, np.load(dataset_root / name) as old:
            for key in ("image/0001", "normals/0000", "landmarks", "shape_coeffs"):
                assert np.array_equal(new[key], old[key]), (name, key)
    again = _write(root)
    assert (again.shards_written, again.shards_skipped) == (0, 3)


def test_extend_and_ranks(dataset_root, tmp_path):
    root = tmp_path / "ranked"
    first = _write(root, count=10, rank=1, world_size=2)
    assert sorted(os.listdir(root)) == [".synth.lock", "manifest.json", "shard_00001.npz"]
    assert first.shards_written == 1
    with pytest.raises(FileNotFoundError, match="1 of 3 shards are missing|2 of 3 shards are missing"):
        SyntheticHeadDataset(root)
    assert len(SyntheticHeadDataset(root, allow_missing=True)) == 4
    with np.load(root / "shard_00001.npz") as ours, np.load(dataset_root / "shard_00001.npz") as reference:
        assert np.array_equal(ours["image/0002"], reference["image/0002"])


def test_settings_mismatch_is_refused(dataset_root, tmp_path):
    root = tmp_path / "other"
    root.mkdir()
    (root / "manifest.json").write_text((dataset_root / "manifest.json").read_text())
    with pytest.raises(ValueError, match="another seed"):
        _write(root, seed=2)
    with pytest.raises(ValueError, match="another shard_size"):
        _write(root, shard_size=5)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"count": 0}, "count: expected an integer >= 1"),
        ({"workers": 0}, "workers: expected an integer >= 1"),
        ({"shard_size": 0}, "shard_size: expected an integer >= 1"),
        ({"seed": -3}, "seed: expected an integer >= 0"),
        ({"rank": 2, "world_size": 2}, "rank: expected 0 <= rank < world_size = 2"),
        ({"config": {"fill": (0.4, 0.9)}}, "config: expected a SynthConfig"),
    ],
)
def test_bad_arguments(tmp_path, kwargs, match):
    args = {"count": 4, "workers": 1, "seed": 0, "shard_size": 4}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        write_dataset(tmp_path / "x", args.pop("count"), model_spec="builtin", progress=False, **args)


def test_dataset_errors(tmp_path, dataset_root):
    with pytest.raises(FileNotFoundError, match="no dataset manifest"):
        SyntheticHeadDataset(tmp_path)
    (tmp_path / "manifest.json").write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(ValueError, match="format is 'something-else'"):
        SyntheticHeadDataset(tmp_path)
    with pytest.raises(ValueError, match="sigma"):
        SyntheticHeadDataset(dataset_root, sigma=0)
    (tmp_path / "manifest.json").write_text(json.dumps(["a", "list"]))
    with pytest.raises(ValueError, match="manifest.json: expected a JSON object, got list"):
        SyntheticHeadDataset(tmp_path)
    manifest = json.loads((dataset_root / "manifest.json").read_text())
    del manifest["count"]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match=r"manifest.json: the manifest lacks \['count'\]"):
        SyntheticHeadDataset(tmp_path)


def test_a_corrupt_shard_is_named(tmp_path, dataset_root):
    import shutil

    root = tmp_path / "copy"
    shutil.copytree(dataset_root, root)
    data = (root / "shard_00001.npz").read_bytes()
    (root / "shard_00001.npz").write_bytes(data[: len(data) // 2])  # cut off, like an interrupted copy
    dataset = SyntheticHeadDataset(root)
    assert dataset[0]["image"].shape == (3, 128, 128)  # the other shards still read
    with pytest.raises(ValueError, match=r"shard_00001.npz: corrupt shard, cannot read sample 0"):
        dataset[4]
    (root / "shard_00001.npz").write_bytes(b"not a zip archive")
    with pytest.raises(ValueError, match=r"shard_00001.npz: corrupt shard"):
        SyntheticHeadDataset(root)[5]


def test_bad_output_or_background_folder_writes_nothing(tmp_path):
    """Checked before anything is written: a rerun with the typo fixed must not find a stale manifest."""
    with pytest.raises(ValueError, match="config.background_folders: /nonexistent/photos is not a folder"):
        write_dataset(tmp_path / "s", 1, model_spec="builtin", progress=False,
                      config=SynthConfig(background_folders=("/nonexistent/photos",)))
    assert not (tmp_path / "s").exists()
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="out_dir: .*file exists and is not a folder"):
        write_dataset(tmp_path / "file", 1, model_spec="builtin", progress=False)


def test_worker_processes_write_the_same_bytes(dataset_root, tmp_path):
    """Two spawned worker processes produce the shards that one in-process generator produced."""
    summary = _write(tmp_path / "pool", count=10, workers=2, chunk_size=3)
    assert summary.shards_written == 3
    for name in ("shard_00000.npz", "shard_00002.npz"):
        with np.load(tmp_path / "pool" / name) as new, np.load(dataset_root / name) as old:
            assert sorted(new.files) == sorted(old.files)
            for key in new.files:
                assert np.array_equal(new[key], old[key]), (name, key)


def test_worker_start_errors_reach_the_caller(tmp_path, monkeypatch):
    from facenormals.data import shards
    from facenormals.models import ModelFileError

    shards._init_worker(os.getppid(), str(tmp_path / "missing.npz"), CONFIG, 0, None)  # the error waits for the task
    with pytest.raises(ModelFileError, match="missing.npz"):
        shards._work((0, 1))
    shards._WORKER.clear()

    def no_gl():
        raise HeadlessGLError("no headless OpenGL found: install libegl1")

    monkeypatch.setattr("facenormals.data.gl_platform.select_gl_platform", no_gl)
    with pytest.raises(HeadlessGLError, match="libegl1"):
        write_dataset(tmp_path / "x", 2, workers=2, model_spec="builtin", progress=False)


def test_a_shard_missing_its_tables_is_regenerated(dataset_root, tmp_path):
    import shutil
    import zipfile

    from facenormals.data.shards import shard_is_complete, shard_range

    root = tmp_path / "copy"
    shutil.copytree(dataset_root, root)
    with zipfile.ZipFile(dataset_root / "shard_00000.npz") as old, \
            zipfile.ZipFile(root / "shard_00000.npz", "w") as new:  # everything but the landmarks table
        for item in old.infolist():
            if item.filename != "landmarks.npy":
                new.writestr(item, old.read(item.filename))
    assert not shard_is_complete(root / "shard_00000.npz", shard_range(0, 10, 4))
    assert _write(root).shards_written == 1


def test_another_model_with_the_same_sizes_is_refused(dataset_root, tmp_path):
    """The manifest records the model's content, not only its sizes and names."""
    import shutil

    from facenormals.models import builtin_head_model

    root = tmp_path / "copy"
    shutil.copytree(dataset_root, root)
    model = builtin_head_model()
    other = type(model)(model.mean, 3.0 * model.shape_basis, model.faces, shape_std=model.shape_std,
                        landmarks=model.landmarks, face_region=model.face_region, name="builtin")
    other_path = tmp_path / "other.npz"
    other.save(other_path)
    with pytest.raises(ValueError, match="another model"):
        write_dataset(root, 10, seed=1, model_spec=str(other_path), shard_size=4, config=CONFIG, progress=False)


def test_shards_without_a_manifest_are_refused(dataset_root, tmp_path):
    import shutil

    root = tmp_path / "copy"
    shutil.copytree(dataset_root, root)
    os.remove(root / "manifest.json")
    with pytest.raises(ValueError, match="holds shards but no manifest.json"):
        _write(root, seed=2)


def test_a_stale_shard_is_named_as_such(dataset_root, tmp_path):
    """After a count change on one rank, another rank's shard still holds the old samples."""
    import shutil

    root = tmp_path / "copy"
    shutil.copytree(dataset_root, root)
    manifest = json.loads((root / "manifest.json").read_text())
    manifest["count"] = 11  # shard 2 should now hold samples 8..10
    (root / "manifest.json").write_text(json.dumps(manifest))
    dataset = SyntheticHeadDataset(root)
    assert len(dataset) == 11 and int(dataset[0]["index"]) == 0
    with pytest.raises(ValueError, match=r"shard_00002.npz: stale shard, holds samples 8..9 but the manifest's "
                                         r"count 11 asks for 8..10"):
        dataset[8]


def test_a_bad_model_or_rank_writes_nothing(tmp_path):
    from facenormals.models import ModelFileError

    with pytest.raises(ModelFileError, match="missing.npz"):
        write_dataset(tmp_path / "s", 1, model_spec=str(tmp_path / "missing.npz"), progress=False)
    assert not (tmp_path / "s").exists()
    with pytest.raises(ValueError, match="rank: expected 0 <= rank < world_size"):
        write_dataset(tmp_path / "s", 1, model_spec="builtin", rank=0.5, world_size=2, progress=False)


def test_a_shard_with_non_finite_ground_truth_is_named(dataset_root, tmp_path):
    import zipfile

    root = tmp_path / "nan"
    root.mkdir()
    for name in os.listdir(dataset_root):
        (root / name).write_bytes((dataset_root / name).read_bytes())
    source = dataset_root / "shard_00001.npz"
    with zipfile.ZipFile(source) as old, zipfile.ZipFile(root / "shard_00001.npz", "w") as new:
        for member in old.namelist():
            if member == "landmarks.npy":
                landmarks = np.load(old.open(member))
                landmarks[1, 3] = np.nan
                with new.open(member, "w") as handle:
                    np.lib.format.write_array(handle, landmarks)
            else:
                new.writestr(member, old.read(member))
    dataset = SyntheticHeadDataset(root)
    assert int(dataset[0]["index"]) == 0  # other shards still read
    with pytest.raises(ValueError, match=r"shard_00001.npz: corrupt shard.*table 'landmarks' holds NaN"):
        dataset[5]


def test_bad_environment_rank_and_infinite_identity_scale_are_named(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match=r"identity_scale: expected a finite number >= 0, got inf"):
        SynthConfig(identity_scale=float("inf"))
    monkeypatch.setenv("RANK", "abc")
    with pytest.raises(ValueError, match=r"\$RANK: expected an integer, got 'abc'"):
        write_dataset(tmp_path / "out", 2, workers=1, model_spec="builtin", progress=False)
    assert not (tmp_path / "out").exists()


def test_a_count_can_grow_but_not_shrink(dataset_root, tmp_path):
    root = tmp_path / "shrink"
    root.mkdir()
    for name in os.listdir(dataset_root):
        (root / name).write_bytes((dataset_root / name).read_bytes())
    before = {name: (root / name).read_bytes() for name in os.listdir(root)}
    with pytest.raises(ValueError, match=r"holds a dataset of 10 samples; --count 6 would shrink it"):
        _write(root, count=6)
    assert {name: (root / name).read_bytes() for name in os.listdir(root)} == before


def test_resuming_with_other_background_photos_is_refused(tmp_path):
    """Which photo a sample crops depends on the whole photo set: the manifest records its content."""
    import cv2

    photos = tmp_path / "photos"
    photos.mkdir()
    cv2.imwrite(str(photos / "a.png"), np.zeros((64, 64, 3), np.uint8))
    config = SynthConfig.head_only(background_folders=(str(photos),), use_skimage=False)
    _write(tmp_path / "out", count=1, shard_size=1, config=config)
    assert read_manifest(tmp_path / "out")["photos"]["count"] == 1
    cv2.imwrite(str(photos / "b.png"), np.zeros((64, 64, 3), np.uint8))
    with pytest.raises(ValueError, match="holds a dataset with another photos"):
        _write(tmp_path / "out", count=1, shard_size=1, config=config)
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    del manifest["photos"]  # as written before the photos were recorded: nothing to compare
    (tmp_path / "out" / "manifest.json").write_text(json.dumps(manifest))
    assert _write(tmp_path / "out", count=1, shard_size=1, config=config).shards_skipped == 1


def test_resuming_a_dataset_of_another_generator_version_is_refused(tmp_path):
    """The same (seed, index) draws other bytes after a generator change: a resume would mix them."""
    from facenormals.data.generator import GENERATOR_VERSION

    config = SynthConfig.head_only(use_skimage=False)
    _write(tmp_path / "out", count=1, shard_size=1, config=config)
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert manifest["generator"] == GENERATOR_VERSION
    del manifest["generator"]  # as written before the version was recorded: version 1
    (tmp_path / "out" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match=f"holds samples of generator version 1; .* version {GENERATOR_VERSION}"):
        _write(tmp_path / "out", count=2, shard_size=1, config=config)
    assert len(SyntheticHeadDataset(tmp_path / "out")) == 1  # the dataset as it is still reads


def test_a_shard_whose_index_does_not_decompress_is_regenerated(dataset_root, tmp_path):
    """zipfile raises zlib.error (not BadZipFile) on a damaged deflate stream."""
    import shutil
    import zipfile
    import zlib

    from tests.conftest import damage_deflate_stream

    root = tmp_path / "copy"
    shutil.copytree(dataset_root, root)
    path = root / "shard_00000.npz"
    damage_deflate_stream(path, "index.npy")
    with pytest.raises(zlib.error, match="invalid block type"), zipfile.ZipFile(path) as archive:
        archive.read("index.npy")
    summary = _write(root)
    assert summary.shards_written == 1 and summary.shards_skipped == 2
    assert path.read_bytes() == (dataset_root / "shard_00000.npz").read_bytes()


def test_other_landmark_vertices_are_another_model(dataset_root, tmp_path):
    """The landmark vertices place the stored landmarks, their visibility and the hair."""
    import shutil

    from facenormals.models import builtin_head_model

    root = tmp_path / "copy"
    shutil.copytree(dataset_root, root)
    model = builtin_head_model()
    landmarks = dict(model.landmarks)
    landmarks["chin"] = (landmarks["chin"] + 5) % model.num_vertices
    other = type(model)(model.mean, model.shape_basis, model.faces, shape_std=model.shape_std,
                        landmarks=landmarks, face_region=model.face_region, name="builtin")
    other.save(tmp_path / "other.npz")
    with pytest.raises(ValueError, match=r"another model \(landmark_indices: \[") as refused:
        write_dataset(root, 12, seed=1, model_spec=str(tmp_path / "other.npz"), shard_size=4, config=CONFIG,
                      progress=False)
    assert "landmark_names" not in str(refused.value)  # only what differs, not the whole fingerprint


def test_a_manifest_without_landmark_vertices_still_resumes(dataset_root, tmp_path):
    import json
    import shutil

    root = tmp_path / "copy"
    shutil.copytree(dataset_root, root)
    manifest = json.loads((root / "manifest.json").read_text())
    del manifest["model"]["landmark_indices"]  # written before session 14
    (root / "manifest.json").write_text(json.dumps(manifest))
    assert _write(root).shards_skipped == 3


def test_an_interrupted_extension_can_be_taken_back(dataset_root, tmp_path):
    """Raising --count publishes the larger count before its shards exist; as long as none was
    written, the old count is accepted again (and the dataset reads as before)."""
    import json
    import shutil

    root = tmp_path / "copy"
    shutil.copytree(dataset_root, root)
    manifest = json.loads((root / "manifest.json").read_text())
    manifest["count"] = 4000  # what an interrupted `--count 4000` leaves
    (root / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(FileNotFoundError, match="of 1000 shards are missing"):
        SyntheticHeadDataset(root)
    before = {name: (root / name).read_bytes() for name in os.listdir(root) if name.startswith("shard_")}
    summary = _write(root, count=10)
    assert summary.shards_written == 0 and summary.shards_skipped == 3
    assert {name: (root / name).read_bytes() for name in os.listdir(root) if name.startswith("shard_")} == before
    assert len(SyntheticHeadDataset(root)) == 10
    manifest["count"] = 4000
    (root / "manifest.json").write_text(json.dumps(manifest))
    shutil.copy(root / "shard_00002.npz", root / "shard_00003.npz")  # a shard past sample 10 exists
    with pytest.raises(ValueError, match="would shrink it, rewriting or orphaning its shards of samples from 10 on"):
        _write(root, count=10)


@pytest.mark.parametrize("key, value, match", [
    ("shard_size", 0, r"shard_size: expected an integer >= 1, got 0"),
    ("count", 2.5, r"count: expected an integer >= 1, got 2.5"),
    ("image_size", "128", r"image_size: expected an integer >= 1, got '128'"),
    ("normal_scale", float("nan"), r"normal_scale: expected a finite number > 0, got nan"),
    ("normal_scale", 0, r"normal_scale: expected a finite number > 0, got 0"),
])
def test_a_manifest_with_bad_values_is_named(dataset_root, tmp_path, key, value, match):
    root = _copy_with_manifest(dataset_root, tmp_path, **{key: value})
    with pytest.raises(ValueError, match="manifest.json: " + match):
        SyntheticHeadDataset(root)


def test_a_manifest_whose_image_size_disagrees_with_the_samples_is_named(dataset_root, tmp_path):
    root = _copy_with_manifest(dataset_root, tmp_path, image_size=64)
    with pytest.raises(ValueError, match=r"shard_00000.npz: corrupt shard, cannot read sample 0 .*member image/0000 "
                                         r"has shape \(128, 128, 3\), expected \(64, 64, 3\)"):
        SyntheticHeadDataset(root)[0]


def test_a_shard_with_a_damaged_compression_method_is_regenerated_and_named(dataset_root, tmp_path):
    """zipfile raises NotImplementedError for an unknown compression method: resume crashed, the
    dataset's error named no file."""
    import shutil
    import struct

    root = tmp_path / "copy"
    shutil.copytree(dataset_root, root)
    path = root / "shard_00000.npz"
    data = bytearray(path.read_bytes())
    entry = data.index(b"PK\x01\x02")  # the first central-directory entry: index.npy
    assert data[entry + 46 : entry + 46 + 9] == b"index.npy"
    data[entry + 10 : entry + 12] = struct.pack("<H", 99)
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="shard_00000.npz: corrupt shard, cannot read sample 0 "
                                         r"\(NotImplementedError"):
        SyntheticHeadDataset(root)[0]
    summary = _write(root)
    assert summary.shards_written == 1 and summary.shards_skipped == 2
    assert path.read_bytes() == (dataset_root / "shard_00000.npz").read_bytes()


@pytest.mark.parametrize("text,match", [
    (b"\xff\xfe{", "cannot read the manifest"),
    (json.dumps({"version": None}).encode(), "version: expected an integer >= 1, got None"),
    (json.dumps({"version": "abc"}).encode(), "version: expected an integer >= 1, got 'abc'"),
    (json.dumps({"generator": [1]}).encode(), r"generator: expected an integer >= 1, got \[1\]"),
])
def test_an_undecodable_manifest_or_version_is_named(dataset_root, tmp_path, text, match):
    """A non-UTF-8 manifest gave a bare UnicodeDecodeError, a null version a TypeError traceback."""
    root = _copy_with_manifest(dataset_root, tmp_path, **(json.loads(text) if text.startswith(b"{") else {}))
    if not text.startswith(b"{"):
        (root / "manifest.json").write_bytes(text)
    with pytest.raises(ValueError, match="manifest.json: " + match):
        SyntheticHeadDataset(root)
    with pytest.raises(ValueError, match="manifest.json: " + match):
        _write(root)


def test_allow_missing_serves_only_complete_shards(dataset_root, tmp_path):
    """A shard of the old count while the manifest already announces an extension failed mid-epoch."""
    # what an extending rank publishes first: shard 2 (samples 8, 9) now needs 8..11
    root = _copy_with_manifest(dataset_root, tmp_path, count=16)
    dataset = SyntheticHeadDataset(root, allow_missing=True)
    assert len(dataset) == 8 and sorted(int(dataset[i]["index"]) for i in range(8)) == list(range(8))


def test_the_same_photo_folder_spelled_differently_resumes(tmp_path, monkeypatch):
    """background_folders were compared as strings: ./photos/ after photos refused to resume."""
    import cv2

    monkeypatch.chdir(tmp_path)
    (tmp_path / "photos").mkdir()
    cv2.imwrite(str(tmp_path / "photos" / "a.png"), np.zeros((64, 64, 3), np.uint8))
    first = SynthConfig.head_only(background_folders=("photos",), use_skimage=False)
    _write(tmp_path / "out", count=2, shard_size=1, config=first)
    again = SynthConfig.head_only(background_folders=("./photos/",), use_skimage=False)
    assert _write(tmp_path / "out", count=2, shard_size=1, config=again).shards_skipped == 2
    with pytest.raises(ValueError, match="holds a dataset with another config .*fill"):
        _write(tmp_path / "out", count=2, shard_size=1, config=SynthConfig.head_only(
            background_folders=("photos",), use_skimage=False, fill=(0.5, 0.6)))


@pytest.mark.parametrize("sigma", [float("inf"), float("nan"), 0.0, True, "1.5"])
def test_a_bad_sigma_is_refused_by_the_constructor(tmp_path, sigma):
    """An infinite sigma was accepted and failed on every item, inside DataLoader workers."""
    with pytest.raises(ValueError, match="sigma"):
        SyntheticHeadDataset(tmp_path, sigma=sigma)


def _with_members(dataset_root, tmp_path, changes):
    """A copy of the dataset whose shard_00001.npz has its members ``changes`` (name: function of the stored array)."""
    import shutil
    import zipfile

    root = tmp_path / "members"
    shutil.copytree(dataset_root, root)
    with zipfile.ZipFile(dataset_root / "shard_00001.npz") as old, \
            zipfile.ZipFile(root / "shard_00001.npz", "w") as new:
        for member in old.namelist():
            name = member[:-len(".npy")]
            if name in changes:
                with new.open(member, "w") as handle:
                    np.lib.format.write_array(handle, changes[name](np.load(old.open(member))))
            else:
                new.writestr(member, old.read(member))
    return root


@pytest.mark.parametrize("name, change, match", [
    ("normals/0001", lambda a: np.full(a.shape, np.nan, np.float32), r"member normals/0001 has dtype float32, expected int16"),
    ("normals/0001", lambda a: a.astype(np.int32) * 3, r"member normals/0001 has dtype int32, expected int16"),
    ("image/0001", lambda a: a.astype(np.float64) * 1000, r"member image/0001 has dtype float64, expected uint8"),
    ("segmentation/0001", lambda a: a.astype(np.int64), r"member segmentation/0001 has dtype int64, expected uint8"),
    ("segmentation/0001", lambda a: a[:64], r"member segmentation/0001 has shape \(64, 128\), expected \(128, 128\)"),
    ("landmark_visible", lambda a: a.astype(np.float32), r"table 'landmark_visible' has dtype float32, expected bool"),
    ("landmarks", lambda a: a[:, :20], r"table 'landmarks' has shape \(4, 20, 2\), expected \(n=4, L=\d+, 2\)"),
    ("landmarks", lambda a: a[:3], r"table 'landmarks' has shape \(3, \d+, 2\), expected \(n=4, L=\d+, 2\)"),
    ("shape_coeffs", lambda a: a[:, :1], r"table 'shape_coeffs' has shape \(4, 1\), expected \(n=4, K=\d+\)"),
    ("rotation", lambda a: a.astype(np.float64), r"table 'rotation' has dtype float64, expected float32"),
    ("index", lambda a: a.astype(np.float64), r"table 'index' has dtype float64, expected int64"),
])
def test_a_shard_with_members_of_the_wrong_type_or_shape_is_named(dataset_root, tmp_path, name, change, match):
    """NaN float normals, int32 normals 3x too long and a float image of 1000 were served silently;
    a float landmark_visible or a short landmarks table failed without naming the file (or with an IndexError)."""
    root = _with_members(dataset_root, tmp_path, {name: change})
    dataset = SyntheticHeadDataset(root)
    assert int(dataset[0]["index"]) == 0  # other shards still read
    with pytest.raises(ValueError, match=r"shard_00001.npz: corrupt shard, cannot read sample 1 .*" + match):
        dataset[5]
    dataset.close()
    without_maps = SyntheticHeadDataset(root, with_landmark_maps=False)  # the same without rasterising
    with pytest.raises(ValueError, match=r"shard_00001.npz: corrupt shard, cannot read sample 1 .*" + match):
        without_maps[5]


@pytest.mark.parametrize("key, value, match", [
    ("num_shape", "100", r"model.num_shape: expected an integer >= 0, got '100'"),
    ("num_expressions", -1, r"model.num_expressions: expected an integer >= 0, got -1"),
    ("landmark_names", "nose", r"model.landmark_names: expected a list, got str"),
])
def test_a_manifest_with_bad_model_sizes_is_named(dataset_root, tmp_path, key, value, match):
    manifest = json.loads((dataset_root / "manifest.json").read_text())
    root = _copy_with_manifest(dataset_root, tmp_path, model={**manifest["model"], key: value})
    with pytest.raises(ValueError, match="manifest.json: " + match):
        SyntheticHeadDataset(root)


def test_a_manifest_whose_model_is_not_an_object_is_named(dataset_root, tmp_path):
    root = _copy_with_manifest(dataset_root, tmp_path, model="builtin")
    with pytest.raises(ValueError, match="manifest.json: model: expected a JSON object, got str"):
        SyntheticHeadDataset(root)


@pytest.mark.parametrize("augment", [3, "flip", [PhotoAugmentation()]])
def test_an_augment_that_is_not_callable_is_refused_by_the_constructor(tmp_path, dataset_root, augment):
    """Regression: augment=3 was accepted and every item then failed with 'int' object is not callable."""
    for root in (dataset_root, tmp_path):  # a valid dataset, and before the folder is read
        with pytest.raises(ValueError, match=r"^augment: expected None or a callable .*, got "):
            SyntheticHeadDataset(root, augment=augment)


@pytest.mark.parametrize("root", ["", 3, None])
def test_a_root_that_is_no_folder_name_is_refused(root):
    with pytest.raises(ValueError, match=r"^root: expected a dataset folder name \(str or os.PathLike\), got "):
        SyntheticHeadDataset(root)


def test_an_index_must_be_an_integer_and_an_out_of_range_one_stays_an_index_error(dataset_root):
    """Regression: dataset[1.5] and dataset['3'] were raw TypeErrors (from the range comparison)."""
    dataset = SyntheticHeadDataset(dataset_root, with_landmark_maps=False)
    for index in (1.5, "3", None, True, np.bool_(False), torch.tensor(1.0), torch.tensor([1]), np.float64(2.0)):
        with pytest.raises(ValueError, match=r"^index: expected an integer, got "):
            dataset[index]
    for index in (3, np.int64(3), np.int32(3), torch.tensor(3), -7):  # what samplers pass; -7 is 3 from the end
        assert int(dataset[index]["index"]) == 3
    assert int(dataset[-1]["index"]) == 9 and int(dataset[np.int64(-10)]["index"]) == 0
    for index in (10, -11, np.int64(10), torch.tensor(-11)):
        with pytest.raises(IndexError, match="out of range for 10 samples"):
            dataset[index]
    assert [int(item["index"]) for item in dataset] == list(range(10))  # the old iteration protocol ends on IndexError


_LOCK_HOLDER = """
import sys, time
from facenormals.core.files import hold_locks
with hold_locks(sys.argv[1], [int(sys.argv[2])], "held"):
    print("held", flush=True)
    time.sleep(60)
"""


@pytest.mark.skipif(os.name != "posix", reason="advisory locks are POSIX")
def test_a_second_synth_into_a_folder_being_written_is_refused(dataset_root, tmp_path):
    """Regression: a second `synth` into the same folder deleted the first one's half-written shard (as
    a killed run's leftover); the first then failed with "No such file or directory". While another
    process holds a shard's lock, write_dataset refuses before touching anything; the ranks of one
    launch lock disjoint shards."""
    import shutil
    import signal
    import subprocess
    import sys

    from facenormals.core.files import FolderInUseError

    root = tmp_path / "busy"
    shutil.copytree(dataset_root, root)
    os.remove(root / "shard_00002.npz")
    live = root / ".shard_00002.npz.a1b2.part.npz"
    live.write_bytes(b"being written by the first synth")
    holder = subprocess.Popen([sys.executable, "-c", _LOCK_HOLDER, str(root / ".synth.lock"), "2"],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(FolderInUseError, match=f"out_dir {root}: another process is writing it"):
            _write(root)
        assert live.read_bytes() == b"being written by the first synth"
        other_rank = _write(root, rank=1, world_size=2)  # shards 1 (and 3): not locked by the holder
        assert other_rank.shards_written == 0 and other_rank.shards_skipped == 1
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert _write(root).shards_written == 1 and not live.exists()  # the holder died: its leftover goes


_SYNTH_WITH_WORKERS = """
import sys
from facenormals.data import write_dataset
if __name__ == "__main__":
    write_dataset(sys.argv[1], 400, workers=2, model_spec="builtin", shard_size=400, progress=False)
"""


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="reads the process table from /proc")
def test_render_workers_end_with_a_killed_synth(tmp_path):
    """Regression: kill -9 (or SIGTERM) of a `synth --workers 2` left its two render workers alive,
    re-parented and blocked forever on the result pipe, each holding the model and an OpenGL context."""
    import signal
    import subprocess
    import sys
    import time

    from facenormals.data.gl_platform import select_gl_platform

    try:
        select_gl_platform()
    except HeadlessGLError as error:
        pytest.skip(f"no headless OpenGL: {error}")
    script = tmp_path / "synth_script.py"
    script.write_text(_SYNTH_WITH_WORKERS)

    def children(pid):
        found = []
        for entry in os.listdir("/proc"):
            try:
                with open(f"/proc/{entry}/stat") as handle:
                    fields = handle.read().rsplit(")", 1)[1].split()
            except (OSError, IndexError):
                continue
            if entry.isdigit() and int(fields[1]) == pid:
                found.append(int(entry))
        return found

    def alive(pid):
        try:
            with open(f"/proc/{pid}/stat") as handle:
                return handle.read().rsplit(")", 1)[1].split()[0] != "Z"
        except OSError:
            return False

    main = subprocess.Popen([sys.executable, str(script), str(tmp_path / "data")])
    try:
        deadline = time.time() + 60
        while len(workers := [p for p in children(main.pid) if "spawn_main" in
                              open(f"/proc/{p}/cmdline").read().replace("\0", " ")]) < 2 and time.time() < deadline:
            time.sleep(0.2)
        assert len(workers) == 2, "the render workers did not start"
        time.sleep(1.0)  # rendering
    finally:
        main.send_signal(signal.SIGKILL)
        main.wait()
    deadline = time.time() + 10
    while any(alive(p) for p in workers) and time.time() < deadline:
        time.sleep(0.2)
    left = [p for p in workers if alive(p)]
    for p in left:
        os.kill(p, signal.SIGKILL)
    assert not left, f"workers {left} outlived their killed parent"
