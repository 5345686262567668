"""Load trained :class:`~facenormals.nn.NormalLandmarkUNet` weights, including the ones shipped in the package."""

from __future__ import annotations

import zipfile
import zlib
from importlib import resources
from pathlib import Path

import torch

from facenormals.core.check import check_device
from facenormals.core.files import atomic_write
from facenormals.nn.unet import NormalLandmarkUNet

__all__ = ["load_weights", "pretrained_weights_path", "update_weight_metadata"]

WEIGHTS_FORMAT = "facenormals-unet"
WEIGHTS_VERSION = 1
_SHIPPED = "normal_landmark_unet.pt"
#: Detection threshold of landmark map peaks when a network carries no calibrated one.
DEFAULT_LANDMARK_THRESHOLD = 0.1
#: The architecture numbers a weight file may state, (low, high) inclusive: far above any network
#: trained here (24 landmarks, 16 base channels, depth 5), low enough that a damaged number is refused
#: before a network is built (base_channels 10**6 tried to allocate 72 TB).
ARCHITECTURE_LIMITS = {"num_landmarks": (0, 10_000), "base_channels": (1, 4096), "depth": (1, 16)}


def landmark_threshold(net: torch.nn.Module) -> float | torch.Tensor:
    """The network's calibrated landmark detection threshold (``metadata["landmark_threshold"]``), else 0.1.

    A float, or one threshold per landmark channel as an ``(L,)`` tensor when the weights carry a list.

    Raises:
        ValueError: naming ``net.metadata['landmark_threshold']`` unless it is a number in (0, 1) or
            one per landmark channel (a NaN threshold would detect nothing, silently).
    """
    metadata = getattr(net, "metadata", {})
    if not isinstance(metadata, dict):
        raise ValueError(f"net.metadata: expected a dictionary, got {type(metadata).__name__}")
    value = metadata.get("landmark_threshold", DEFAULT_LANDMARK_THRESHOLD)
    channels = getattr(net, "num_landmarks", None)
    check_threshold(value, channels if isinstance(channels, int) else None, "net.metadata['landmark_threshold']")
    return torch.tensor(value, dtype=torch.float32) if isinstance(value, (list, tuple)) else float(value)


def pretrained_weights_path() -> Path:
    """Path of the weights shipped inside the package (see ``docs/model_card.md``)."""
    return Path(str(resources.files("facenormals") / "weights" / _SHIPPED))


def describe_load_error(error: BaseException) -> str:
    """A one-line reason for a failed ``torch.load(..., weights_only=True)``, without torch's advice
    to load with ``weights_only=False`` (which would run code from the file)."""
    text = str(error)
    marker = "WeightsUnpickler error:"
    if marker in text:  # torch wraps the cause in advice; keep the cause
        cause = text[text.index(marker) + len(marker):].strip().split("\n")[0].split(". Please")[0]
        if cause.startswith("Unsupported global"):
            return f"it holds Python objects other than tensors and plain data ({cause}), which facenormals never loads"
        return f"not a torch file of tensors and plain data ({cause})"
    first = text.strip().splitlines()[0] if text.strip() else ""
    return f"{type(error).__name__}: {first}" if first else type(error).__name__


def describe_zip_damage(path: Path) -> str | None:
    """Why the torch zip file ``path`` is damaged, or ``None``: every member is read and checked
    against its CRC-32 (``zipfile.ZipFile.testzip``), which ``torch.load`` never does (a flipped byte
    loaded as a changed weight or a renamed config key). Files that do not start as a zip archive
    (torch's legacy format, or no torch file at all) are left to ``torch.load``."""
    try:
        with open(path, "rb") as handle:
            if handle.read(4) != b"PK\x03\x04":  # torch.load's own test for its zip format
                return None
        with zipfile.ZipFile(path) as archive:
            damaged = archive.testzip()
    except (OSError, EOFError, ValueError, NotImplementedError, zipfile.BadZipFile, zlib.error) as error:
        return f"damaged zip archive ({type(error).__name__}: {error})"
    if damaged is not None:
        return f"damaged: its member {damaged!r} fails its CRC-32 check"
    return None


def _read_payload(path: Path) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {'a folder, not a weight file' if path.is_dir() else 'no such weight file'}")
    damage = describe_zip_damage(path)
    if damage is not None:
        raise ValueError(f"{path}: not a readable weight file ({damage})")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 - torch raises many types for a corrupt file
        raise ValueError(f"{path}: not a readable weight file ({describe_load_error(error)})") from None
    if isinstance(payload, dict) and payload.get("format") == "facenormals-train":
        raise ValueError(f"{path}: a training checkpoint, not a weight file; export its weights with "
                         f"`facenormals train ... --export FILE` or facenormals.training.export_weights")
    if not isinstance(payload, dict) or payload.get("format") != WEIGHTS_FORMAT:
        raise ValueError(f"{path}: not a facenormals network weight file")
    if payload.get("version") != WEIGHTS_VERSION:
        raise ValueError(f"{path}: weight format version {payload.get('version')}, expected {WEIGHTS_VERSION}")
    arch, state = payload.get("architecture"), payload.get("state_dict")
    if (not isinstance(arch, dict) or not {"num_landmarks", "base_channels", "depth"} <= set(arch)
            or not isinstance(state, dict)):
        raise ValueError(f"{path}: the weight file lacks its architecture (num_landmarks, base_channels, depth) "
                         "or its state_dict")
    if not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise ValueError(f"{path}: the weight file's state_dict holds entries that are not tensors")
    if not isinstance(payload.get("metadata", {}), dict):
        raise ValueError(f"{path}: the weight file's metadata is not a dictionary")
    return payload


def check_plain_metadata(items: dict, prefix: str = "metadata") -> None:
    """Raise ``ValueError`` naming the first entry of ``items`` that is not JSON-like plain data: a
    numpy number or a path would make ``torch.load(..., weights_only=True)`` refuse the whole file,
    and tensors are refused too (metadata stays readable as plain values; store ``tensor.tolist()``).
    ``items`` itself must be a ``dict`` (``ValueError`` naming ``prefix`` otherwise)."""
    def check(value: object, name: str) -> None:
        if type(value) in (str, int, float, bool, type(None)):
            return
        if type(value) in (list, tuple):
            for i, v in enumerate(value):
                check(v, f"{name}[{i}]")
            return
        if type(value) is dict:
            for k, v in value.items():
                if type(k) is not str:
                    raise ValueError(f"{name}: expected string keys, got {type(k).__name__} {k!r}")
                check(v, f"{name}[{k!r}]")
            return
        raise ValueError(f"{name}: expected plain data (str, int, float, bool, None, lists and dicts of them), "
                         f"got {type(value).__module__}.{type(value).__name__} {value!r}; convert it, e.g. float(x)")

    if not isinstance(items, dict):
        raise ValueError(f"{prefix}: expected a dict of plain values (str keys; str, int, float, bool, None, lists "
                         f"and dicts of them), got {type(items).__name__} {items!r}")
    for key, value in items.items():
        if type(key) is not str:
            raise ValueError(f"{prefix}: expected string keys, got {type(key).__name__} {key!r}")
        check(value, f"{prefix}[{key!r}]")


def update_weight_metadata(path: str | Path, **items: object) -> Path:
    """Add or replace metadata entries of a weight file in place (e.g. the ``fit_weights`` that
    ``benchmarks/tune_network_fit.py --store`` chose for the network); the weights are untouched.

    The file is rewritten atomically (a temporary file renamed over it), so an interrupted call
    leaves the old file.

    Raises:
        FileNotFoundError, ValueError: as :func:`load_weights`; ValueError naming an entry that is not
            plain data (str, int, float, bool, None, and lists and str-keyed dicts of them): a numpy
            number or a path would make the file unreadable to :func:`load_weights`.

    Example:
        >>> import shutil, tempfile
        >>> path = Path(tempfile.mkdtemp()) / "mine.pt"
        >>> _ = shutil.copy(pretrained_weights_path(), path)
        >>> _ = update_weight_metadata(path, fit_weights={"normals": 0.25, "prior": 1.0})
        >>> load_weights(path).metadata["fit_weights"]
        {'normals': 0.25, 'prior': 1.0}
    """
    check_plain_metadata(items)
    path = Path(path)
    payload = _read_payload(path)
    if "landmark_threshold" in items:  # not written where load_weights would then refuse the file
        check_threshold(items["landmark_threshold"], _int_or_none(payload["architecture"].get("num_landmarks")),
                        "landmark_threshold")
    payload["metadata"] = {**payload.get("metadata", {}), **items}
    with atomic_write(path) as part:
        torch.save(payload, part)
    return path


def load_weights(path: str | Path | None = None, device: str | torch.device = "cpu") -> NormalLandmarkUNet:
    """Build the network stored in a weight file and load its weights (float32, ``eval()`` mode).

    Args:
        path: a file written by :func:`~facenormals.training.export_weights`; ``None`` loads the
            shipped weights.
        device: where to put the network: ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or such a ``torch.device``.

    Raises:
        FileNotFoundError: if the file does not exist.
        ValueError: naming ``device`` unless it is a CPU or an available CUDA device.
        ValueError: if it is not a facenormals weight file, states an architecture outside
            ``ARCHITECTURE_LIMITS`` (checked, with the weights' shapes, before the network is built),
            does not match its architecture or holds NaN or infinite weights.

    Example:
        >>> net = load_weights()
        >>> net.num_landmarks, net.training
        (24, False)
    """
    check_device(device)  # before the file is read: torch's RuntimeError would come after all the work
    path = pretrained_weights_path() if path is None else Path(path)
    payload = _read_payload(path)
    arch = payload["architecture"]
    sizes = {}
    for name, (low, high) in ARCHITECTURE_LIMITS.items():
        value = arch[name]
        if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
            raise ValueError(f"{path}: the weight file's architecture {arch} is not a valid network ({name}: expected "
                             f"an integer in [{low}, {high}], got {value!r})")
        sizes[name] = value
    try:
        with torch.device("meta"):  # shapes only: the weights are checked against them before memory is taken
            shapes = {k: tuple(v.shape) for k, v in NormalLandmarkUNet(**sizes).state_dict().items()}
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: the weight file's architecture {arch} is not a valid network ({error})") from None
    stored = payload["state_dict"]
    problems = [f"missing {k}" for k in shapes if k not in stored]
    problems += [f"unexpected {k}" for k in stored if k not in shapes]
    problems += [f"{k}: shape {tuple(v.shape)}, expected {shapes[k]}" for k, v in stored.items()
                 if k in shapes and tuple(v.shape) != shapes[k]]
    if problems:
        more = f"; and {len(problems) - 3} more" if len(problems) > 3 else ""
        raise ValueError(f"{path}: weights do not match the architecture {arch} ({'; '.join(problems[:3])}{more})")
    net = NormalLandmarkUNet(**sizes)
    expected = net.state_dict()
    for key, value in payload["state_dict"].items():  # load_state_dict would copy 0/1 integers into the weights
        if key in expected and expected[key].is_floating_point() and not value.is_floating_point():
            raise ValueError(f"{path}: the weight file stores {key} as {value.dtype}; expected a floating dtype "
                             "(float16, bfloat16 or float32)")
    state = {k: v.float() if v.is_floating_point() else v for k, v in payload["state_dict"].items()}
    for key, value in state.items():  # else every map would be NaN, an error far from its cause
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise ValueError(f"{path}: the weights hold NaN or infinite values ({key}: "
                             f"{int((~torch.isfinite(value)).sum())} of {value.numel()})")
    net.load_state_dict(state)  # keys and shapes checked above
    net.metadata = dict(payload.get("metadata", {}))
    try:  # a NaN threshold detects nothing, silently; a string fails in the middle of a reconstruction
        check_threshold(net.metadata.get("landmark_threshold", DEFAULT_LANDMARK_THRESHOLD), net.num_landmarks)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
    return net.to(device).eval()


def check_threshold(value: object, channels: int | None, name: str = "metadata landmark_threshold") -> None:
    """Raise ``ValueError`` naming ``name`` unless ``value`` is a number in (0, 1) or a list (or 1-D
    tensor) of one per channel (any length when ``channels`` is ``None``)."""
    if isinstance(value, torch.Tensor):
        if value.dim() > 1:
            raise ValueError(f"{name}: expected one value or one per landmark channel, got shape {tuple(value.shape)}")
        value = value.tolist()
    values = list(value) if isinstance(value, (list, tuple)) else [value]
    if isinstance(value, (list, tuple)) and channels is not None and len(values) != channels:
        raise ValueError(f"{name}: expected one threshold per landmark channel ({channels}), got {len(values)}")
    for item in values:
        if isinstance(item, bool) or not isinstance(item, (int, float)) or not 0.0 < float(item) < 1.0:
            raise ValueError(f"{name}: expected numbers in (0, 1), got {item!r}")


def _int_or_none(value: object) -> int | None:
    try:
        return int(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
