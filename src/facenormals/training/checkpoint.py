"""Training checkpoints (resumable) and the small shipped weight files made from them."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import torch
from torch.utils.data import Dataset

from facenormals.core.check import check_file_name
from facenormals.core.files import atomic_write
from facenormals.nn.pretrained import (WEIGHTS_FORMAT, WEIGHTS_VERSION, check_plain_metadata, check_threshold,
                                      describe_load_error, describe_zip_damage)

__all__ = ["export_weights", "load_checkpoint", "save_checkpoint"]


def save_checkpoint(path: str | Path, state: dict) -> Path:
    """Write ``state`` with :func:`torch.save` atomically and durably
    (:func:`~facenormals.core.files.atomic_write`): a run killed while saving, or a machine that
    goes down, keeps its previous checkpoint.

    ``state`` is a training checkpoint (``"format": "facenormals-train"``) or the payload of a weight
    file (:func:`export_weights`). A training checkpoint must hold the entries :func:`load_checkpoint`
    reads (their values, e.g. NaN weights, are checked when it is read), so that no file is written
    that cannot be resumed.

    Raises:
        ValueError: naming ``path`` unless it is a non-empty file name (not a folder, not under a file).
        ValueError: naming ``state`` when it is not a dictionary of either kind, or a training
            checkpoint that lacks or mistypes an entry :func:`load_checkpoint` requires.
    """
    check_file_name(path, "path")
    if not isinstance(state, dict):
        raise ValueError(f"state: expected a dictionary (a training checkpoint), got {type(state).__name__}")
    kind = state.get("format")
    if kind == "facenormals-train":
        if not isinstance(state.get("config"), dict):
            raise ValueError(f"state: expected the run's settings as a dictionary ('config'), got "
                             f"{type(state.get('config')).__name__}")
        _check_entries(state, lambda what: ValueError(f"state: a training checkpoint that load_checkpoint cannot "
                                                      f"read: {what}"), values=False)
    elif kind != WEIGHTS_FORMAT:
        raise ValueError(f"state: expected a training checkpoint (format 'facenormals-train') or a weight file "
                         f"payload (format {WEIGHTS_FORMAT!r}), got format {kind!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as part:
        torch.save(state, part)
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """Read a checkpoint written by :func:`save_checkpoint`.

    The entries a resume or an export reads are checked here, so that a damaged file is an error
    naming it: ``step`` and ``samples_seen`` non-negative integers, ``world_size`` a positive one,
    ``num_landmarks`` a non-negative one, ``model`` and ``ema`` state dicts of finite tensors and
    ``optimizer`` an optimiser state dict (``state`` and ``param_groups``) of finite tensors.

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        ValueError: if it is not a facenormals training checkpoint, or one with missing, mistyped or
            non-finite entries (``"<path>: corrupt checkpoint: ..."``).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {'a folder, not a checkpoint' if path.is_dir() else 'no such checkpoint'}")
    damage = describe_zip_damage(path)  # torch.load never checks the CRC-32 of its zip members
    if damage is not None:
        raise ValueError(f"{path}: not a readable checkpoint ({damage})")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)  # plain data: no code runs on load
    except Exception as error:  # noqa: BLE001 - torch raises many types for a corrupt file
        raise ValueError(f"{path}: not a readable checkpoint ({describe_load_error(error)})") from None
    if not isinstance(state, dict) or state.get("format") != "facenormals-train":
        raise ValueError(f"{path}: not a facenormals training checkpoint")
    if not isinstance(state.get("config"), dict):  # every reader takes the run's settings from it
        raise ValueError(f"{path}: a facenormals training checkpoint without its settings ('config'); it cannot "
                         "be resumed or exported")
    _check_entries(state, lambda what: ValueError(f"{path}: corrupt checkpoint: {what}; it cannot be resumed or "
                                                  "exported"))
    return state


def _is_count(value: object, low: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= low


def _check_entries(state: dict, corrupt: Callable[[str], ValueError], values: bool = True) -> None:
    """Raise ``corrupt(what)`` naming the entry when one a resume or an export reads is missing, of the
    wrong type or (with ``values``) not finite (a NaN model failed at the first step with advice to
    resume from this same file; NaN averaged weights trained on and were exported)."""
    for key, low in (("step", 0), ("samples_seen", 0), ("world_size", 1), ("num_landmarks", 0)):
        if key not in state:
            raise corrupt(f"no {key!r} entry")
        if not _is_count(state[key], low):
            raise corrupt(f"{key!r} is {state[key]!r}, expected an integer >= {low}")
    for key in ("base_channels", "depth", "batch_size"):
        if not _is_count(state["config"].get(key), 1):
            raise corrupt(f"config {key!r} is {state['config'].get(key)!r}, expected a positive integer")
    for key, what in (("model", "model weights"), ("ema", "averaged (EMA) weights")):
        weights = state.get(key)
        if not isinstance(weights, dict) or not weights:
            raise corrupt(f"no {what} ({key!r})" if weights is None else f"the {what} ({key!r}) are not a state dict")
        for name, value in weights.items():
            if not isinstance(value, torch.Tensor):
                raise corrupt(f"the {what} ({key!r}) hold {name!r} of type {type(value).__name__}, not a tensor")
            if values and value.is_floating_point() and not bool(torch.isfinite(value).all()):
                raise corrupt(f"the {what} ({key!r}) hold NaN or infinite values ({name}: "
                              f"{int((~torch.isfinite(value)).sum())} of {value.numel()})")
    optimizer = state.get("optimizer")
    if optimizer is None:
        raise corrupt("no optimiser state ('optimizer')")
    if (not isinstance(optimizer, dict) or not isinstance(optimizer.get("state"), dict)
            or not isinstance(optimizer.get("param_groups"), list)):
        raise corrupt("the optimiser state ('optimizer') is not an optimiser state dict (state, param_groups)")
    for index, entries in (optimizer["state"].items() if values else ()):
        for name, value in (entries.items() if isinstance(entries, dict) else ()):
            if isinstance(value, torch.Tensor) and value.is_floating_point() and not bool(torch.isfinite(value).all()):
                raise corrupt(f"the optimiser state ('optimizer') holds NaN or infinite values (parameter {index}, "
                              f"{name})")


def export_weights(checkpoint: str | Path, out: str | Path, use_ema: bool = True,
                   dtype: torch.dtype = torch.float16, metadata: dict | None = None,
                   calibration_data: Dataset | None = None) -> Path:
    """Turn a training checkpoint into a weight file for :func:`~facenormals.nn.load_weights`.

    Args:
        checkpoint: a ``last.pt`` of a training run.
        out: the weight file to write.
        use_ema: export the moving average of the weights (what the run evaluates) rather than
            the raw weights.
        dtype: storage dtype of floating tensors: float16 (halves the file), bfloat16 or float32;
            weights are cast back to float32 when loaded.
        metadata: extra JSON-able facts to store (metrics, data, hardware). The file also records
            the step, the samples seen, the training configuration and (from checkpoints since
            session 26) ``image_size``, the side of the training images, which
            :func:`~facenormals.reconstruct.predict_maps` expects of its crops.
        calibration_data: optional dataset (e.g. training samples) on which the landmark detection
            threshold is calibrated (:func:`~facenormals.training.calibrate_landmark_threshold`)
            and stored as ``metadata["landmark_threshold"]``.

    Returns:
        ``out``.

    Raises:
        ValueError: when ``out`` is not a file name (empty, a folder, under a file) or is ``checkpoint``
            itself (the training state would be lost), ``checkpoint`` is not a file name, ``dtype`` is
            not a floating dtype or ``metadata`` is not a dict of plain data or holds an invalid
            ``landmark_threshold``.
    """
    if not isinstance(checkpoint, (str, os.PathLike)):
        raise ValueError(f"checkpoint: expected a file name (str or os.PathLike), got {type(checkpoint).__name__} "
                         f"{checkpoint!r}")
    out = check_file_name(out, "out")
    if dtype not in (torch.float16, torch.bfloat16, torch.float32):
        raise ValueError(f"dtype: expected torch.float16, torch.bfloat16 or torch.float32, got {dtype}")
    check_plain_metadata({} if metadata is None else metadata)
    if out.resolve() == Path(checkpoint).resolve():
        raise ValueError(f"out: {out} is the checkpoint being exported; writing the weights over it would lose "
                         "the training state, choose another file")
    state = load_checkpoint(checkpoint)
    if metadata and "landmark_threshold" in metadata:  # not written where load_weights would then refuse the file
        check_threshold(metadata["landmark_threshold"], state["num_landmarks"], "metadata['landmark_threshold']")
    weights = state["ema" if use_ema else "model"]
    tensors = {k: (v.to(dtype) if v.is_floating_point() else v) for k, v in weights.items()}
    config = state["config"]
    payload = {
        "format": WEIGHTS_FORMAT,
        "version": WEIGHTS_VERSION,
        "architecture": {"base_channels": config["base_channels"], "depth": config["depth"],
                         "num_landmarks": state["num_landmarks"]},
        "state_dict": tensors,
        "metadata": {"step": state["step"], "samples_seen": state["samples_seen"], "ema": use_ema,
                     "train_config": config,
                     # the training images' side, which predict_maps expects of its crops (absent in
                     # checkpoints before session 26)
                     **({"image_size": state["image_size"][0]} if "image_size" in state
                        and state["image_size"][0] == state["image_size"][1] else {}),
                     **(metadata or {})},
    }
    path = save_checkpoint(out, payload)
    if calibration_data is not None:
        from facenormals.nn import load_weights
        from facenormals.training.metrics import calibrate_landmark_threshold

        threshold, accuracy = calibrate_landmark_threshold(load_weights(path), calibration_data, max_samples=None)
        payload["metadata"].update(landmark_threshold=threshold, landmark_threshold_accuracy=accuracy,
                                   landmark_threshold_samples=len(calibration_data))
        path = save_checkpoint(out, payload)
    return path
