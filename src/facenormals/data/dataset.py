"""A :class:`torch.utils.data.Dataset` over the shards written by :func:`~facenormals.data.write_dataset`."""

from __future__ import annotations

import os
import zipfile
import zlib
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch.utils.data import Dataset

from facenormals.core.check import check_integer, check_positive
from facenormals.data.landmark_maps import DEFAULT_SIGMA, landmark_maps
from facenormals.data.shards import (MANIFEST, SHARD_ARRAYS, read_manifest, read_member, shard_is_complete,
                                     shard_name, shard_range)

__all__ = ["SyntheticHeadDataset"]


class _StaleShard(ValueError):
    """A readable shard written for another sample count (another rank has not rewritten it yet)."""


class SyntheticHeadDataset(Dataset):
    r"""Training samples from a synthetic dataset folder; safe in ``DataLoader`` worker processes.

    Shard files are opened lazily, once per process (the open handles are dropped when the dataset
    is pickled into a worker), and a sample decompresses only its own image, normals and labels.
    The landmark maps Z are rasterised here from the stored points
    (:func:`~facenormals.data.landmark_maps`).

    Args:
        root: the dataset folder (with ``manifest.json``).
        sigma: standard deviation of the landmark Gaussians in pixels.
        augment: optional callable applied to the ``(3, H, W)`` image, e.g.
            :class:`~facenormals.data.PhotoAugmentation`.
        allow_missing: serve only the complete shards present instead of raising when some are
            missing (e.g. while other ranks are still writing).
        with_landmark_maps: rasterise ``landmark_maps`` per item; training loops that rasterise
            whole batches on their device (cheaper than collating ``L`` full maps) pass ``False``.

    Raises:
        FileNotFoundError: if the manifest or (unless ``allow_missing``) a shard is missing.
        ValueError: on a bad manifest, ``root`` (not a folder name), ``sigma`` or ``augment`` (neither
            ``None`` nor callable).

    Items are indexed as a sequence: ``index`` an integer (a Python or numpy integer or an integer
    0-d tensor, as samplers pass; ``ValueError`` naming ``index`` otherwise), negative ones counting
    from the end; one outside ``[-len, len)`` raises ``IndexError``.

    Each item is a dict of tensors (``L`` landmarks, ``K`` shape and ``E`` expression coefficients):

    - ``image`` ``(3, H, W)`` float32 in ``[0, 1]``;
    - ``normals`` ``(3, H, W)`` float32 camera-frame unit normals, 0 off the head;
    - ``foreground`` ``(1, H, W)`` bool, the head surface (where ``normals`` is non-zero);
    - ``landmark_maps`` ``(L, H, W)`` float32 (unless ``with_landmark_maps=False``);
    - ``landmarks`` ``(L, 2)`` float32 pixels and ``landmark_visible`` ``(L,)`` bool;
    - ``segmentation`` ``(H, W)`` uint8 labels;
    - ``shape_coeffs`` ``(K,)``, ``expression_coeffs`` ``(E,)``, ``angles`` ``(3,)``, ``rotation``
      ``(3, 3)``, ``translation`` ``(3,)``, ``intrinsics`` ``(3,)`` float32, and ``index`` (int64).
    """

    def __init__(
        self,
        root: str | Path,
        sigma: float = DEFAULT_SIGMA,
        augment: Callable[[torch.Tensor], torch.Tensor] | None = None,
        allow_missing: bool = False,
        with_landmark_maps: bool = True,
    ) -> None:
        self.sigma = check_positive(sigma, "sigma")  # finite: an infinite one failed on every item instead
        if augment is not None and not callable(augment):  # else every item failed, in DataLoader workers
            raise ValueError(f"augment: expected None or a callable taking and returning a (3, H, W) image, got "
                             f"{type(augment).__name__} {augment!r}")
        if not (isinstance(root, (str, os.PathLike)) and str(root)):
            raise ValueError(f"root: expected a dataset folder name (str or os.PathLike), got {root!r}")
        self.root = Path(root)
        self.manifest = read_manifest(self.root)
        self.augment = augment
        self.with_landmark_maps = bool(with_landmark_maps)
        self.count = int(self.manifest["count"])
        self.shard_size = int(self.manifest["shard_size"])
        self.image_size = int(self.manifest["image_size"])
        self.normal_scale = float(self.manifest["normal_scale"])
        self._sizes = _model_sizes(self.manifest, self.root / MANIFEST)
        num_shards = -(-self.count // self.shard_size)
        present = [k for k in range(num_shards) if (self.root / shard_name(k)).is_file()]
        if allow_missing:  # a shard of an extension being written, or a stale one, would fail mid-epoch
            present = [k for k in present
                       if shard_is_complete(self.root / shard_name(k), shard_range(k, self.count, self.shard_size))]
        missing = sorted(set(range(num_shards)) - set(present))
        if missing and not allow_missing:
            names = ", ".join(shard_name(k) for k in missing[:5]) + (" ..." if len(missing) > 5 else "")
            raise FileNotFoundError(f"{self.root}: {len(missing)} of {num_shards} shards are missing ({names})")
        self._items = [(k, i) for k in present for i in range(len(shard_range(k, self.count, self.shard_size)))]
        if not self._items:
            raise FileNotFoundError(f"{self.root}: no shard files")
        self._pid: int | None = None
        self._archives: dict[int, zipfile.ZipFile] = {}
        self._tables: dict[int, dict[str, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self._items)

    def __repr__(self) -> str:
        return (f"SyntheticHeadDataset(root={str(self.root)!r}, samples={len(self)}, "
                f"model={self.manifest['model']['name']!r}, sigma={self.sigma})")

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_pid"], state["_archives"], state["_tables"] = None, {}, {}
        return state

    def _shard(self, shard: int) -> tuple[zipfile.ZipFile, dict[str, np.ndarray]]:
        if self._pid != os.getpid():  # a fresh process (DataLoader worker): never reuse inherited handles
            self._pid, self._archives, self._tables = os.getpid(), {}, {}
        if shard not in self._archives:
            archive = zipfile.ZipFile(self.root / shard_name(shard))
            self._archives[shard] = archive
            tables = {name: read_member(archive, name) for name in SHARD_ARRAYS}
            index = tables["index"]
            _check_table("index", index, np.int64, ("n",))
            expected = shard_range(shard, self.count, self.shard_size)
            if not np.array_equal(index, np.arange(expected.start, expected.stop)):
                self.close()
                raise _StaleShard(f"{self.root / shard_name(shard)}: stale shard, holds samples "
                                  f"{int(index[0]) if len(index) else '-'}..{int(index[-1]) if len(index) else '-'} but "
                                  f"the manifest's count {self.count} asks for {expected.start}..{expected.stop - 1}; "
                                  "run `facenormals synth` for this folder on every rank to finish it")
            sizes = {"n": len(expected), **self._sizes}
            for name, (dtype, shape) in _TABLES.items():  # what write_shard writes (SynthBatch's dtypes)
                _check_table(name, tables[name], dtype, shape, sizes)
                if tables[name].dtype.kind == "f" and not np.isfinite(tables[name]).all():  # would train silently
                    raise ValueError(f"table {name!r} holds NaN or infinite values")
            self._tables[shard] = tables
        return self._archives[shard], self._tables[shard]

    def close(self) -> None:
        """Close the open shard files of this process."""
        for archive in self._archives.values():
            archive.close()
        self._archives, self._tables = {}, {}

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        item = check_integer(index, "index")  # numpy integers and 0-d integer tensors too; not a bool
        if not -len(self) <= item < len(self):  # an IndexError, as iteration and DataLoader expect
            raise IndexError(f"index {item} is out of range for {len(self)} samples")
        shard, i = self._items[item]
        S = self.image_size
        try:
            archive, table = self._shard(shard)
            members = {}
            for name, dtype, shape in (("image", np.uint8, (S, S, 3)), ("normals", np.int16, (3, S, S)),
                                       ("segmentation", np.uint8, (S, S))):  # as write_shard stores them
                array = members[name] = read_member(archive, f"{name}/{i:04d}")
                if array.dtype != dtype:  # int16 bounds the normals; a float member could hold NaN
                    raise ValueError(f"member {name}/{i:04d} has dtype {array.dtype}, expected {np.dtype(dtype)}")
                if array.shape != shape:
                    raise ValueError(f"member {name}/{i:04d} has shape {array.shape}, expected {shape} "
                                     f"from the manifest's image_size {S}")
            sample = {name: torch.from_numpy(np.array(table[name][i])) for name in SHARD_ARRAYS}
            if self.with_landmark_maps:
                sample["landmark_maps"] = landmark_maps(sample["landmarks"][None], sample["landmark_visible"][None],
                                                        (S, S), self.sigma)[0]
        except _StaleShard:
            raise
        except (OSError, EOFError, KeyError, ValueError, zipfile.BadZipFile, zlib.error, NotImplementedError) as error:
            archive = self._archives.pop(shard, None)
            if archive is not None:
                archive.close()
            self._tables.pop(shard, None)
            raise ValueError(f"{self.root / shard_name(shard)}: corrupt shard, cannot read sample {i} "
                             f"({type(error).__name__}: {error}); delete the file and run `facenormals synth` "
                             "with the same arguments to write it again") from None
        image = torch.from_numpy(members["image"]).permute(2, 0, 1).float() / 255.0
        normals = torch.from_numpy(members["normals"].astype(np.float32) / self.normal_scale)
        if self.augment is not None:
            image = self.augment(image)
        sample["image"] = image
        sample["normals"] = normals
        sample["foreground"] = (normals.square().sum(0, keepdim=True) > 0.25)
        sample["segmentation"] = torch.from_numpy(members["segmentation"])
        return sample


#: dtype and shape of the whole-shard tables (besides ``index``): ``n`` samples, ``L`` landmarks,
#: ``K`` shape and ``E`` expression coefficients (the sizes of the manifest's model).
_TABLES = {
    "landmarks": (np.float32, ("n", "L", 2)),
    "landmark_visible": (np.bool_, ("n", "L")),
    "shape_coeffs": (np.float32, ("n", "K")),
    "expression_coeffs": (np.float32, ("n", "E")),
    "angles": (np.float32, ("n", 3)),
    "rotation": (np.float32, ("n", 3, 3)),
    "translation": (np.float32, ("n", 3)),
    "intrinsics": (np.float32, ("n", 3)),
}


def _model_sizes(manifest: dict, path: Path) -> dict[str, int]:
    """``L``, ``K`` and ``E`` of the manifest's model (those it records) for the shard table checks."""
    model = manifest["model"]
    if not isinstance(model, dict):
        raise ValueError(f"{path}: model: expected a JSON object, got {type(model).__name__}")
    sizes = {}
    for key, dim in (("num_shape", "K"), ("num_expressions", "E")):
        if key in model:
            value = model[key]
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"{path}: model.{key}: expected an integer >= 0, got {value!r}")
            sizes[dim] = value
    if "landmark_names" in model:
        if not isinstance(model["landmark_names"], list):
            raise ValueError(f"{path}: model.landmark_names: expected a list, got "
                             f"{type(model['landmark_names']).__name__}")
        sizes["L"] = len(model["landmark_names"])
    return sizes


def _check_table(name: str, table: np.ndarray, dtype: type, shape: tuple, sizes: dict[str, int] | None = None) -> None:
    """Raise ``ValueError`` unless the shard table ``name`` has ``dtype`` and ``shape`` (a dimension
    named in ``sizes`` has that size, another named one any size)."""
    if table.dtype != dtype:
        raise ValueError(f"table {name!r} has dtype {table.dtype}, expected {np.dtype(dtype)}")
    sizes = sizes or {}
    if table.ndim != len(shape) or any(got != sizes.get(want, got) if isinstance(want, str) else got != want
                                       for got, want in zip(table.shape, shape)):
        expected = "(" + ", ".join(f"{d}={sizes[d]}" if d in sizes else str(d) for d in shape) + ")"
        raise ValueError(f"table {name!r} has shape {table.shape}, expected {expected}")
