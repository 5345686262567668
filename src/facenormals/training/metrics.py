"""Held-out metrics of the network: normal angles, landmark errors and visibility decisions."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset, Subset

from facenormals.core.check import check_finite, check_floating, check_same_dtype_device, check_shape
from facenormals.data.landmark_maps import landmarks_from_maps
from facenormals.fitting.landmark_visibility import DEFAULT_FOCAL, drop_hidden_landmarks
from facenormals.mesh.normals import _cross
from facenormals.models import MorphableModel
from facenormals.models.landmarks import LANDMARK_NAMES
from facenormals.nn.mirror import mirror_averaged, mirror_permutation
from facenormals.nn.pretrained import check_threshold, landmark_threshold
from facenormals.nn.unet import NormalLandmarkUNet
from facenormals.reconstruct.pipeline import landmark_channels

__all__ = ["NetworkMetrics", "calibrate_landmark_threshold", "evaluate_network", "landmark_threshold", "normal_angles"]


@dataclass
class NetworkMetrics:
    """Scores of a network on a held-out set (the targets are the network issue's).

    Attributes:
        samples: images scored.
        normal_mean_deg, normal_median_deg: angle between predicted and true unit normals over
            the true foreground pixels of all images (target ≤ 12° and ≤ 8°).
        landmark_mean_px, landmark_median_px: distance from each truly visible landmark to the
            sub-pixel peak of its predicted map, whether or not the peak passes the detection
            threshold (target ≤ 2.5 px and ≤ 1.5 px).
        visibility_accuracy: fraction of all (image, landmark) pairs where "peak above threshold"
            equals the true visibility (target ≥ 0.95).
        foreground_iou: intersection over union of the predicted and true foreground.
        visibility_accuracy_posed: the same after dropping the detections that the mean head,
            pre-aligned to them, hides (:func:`~facenormals.fitting.drop_hidden_landmarks`, the
            decisions ``facenormals reconstruct`` fits with); ``None`` unless scored with a model.
    """

    samples: int
    normal_mean_deg: float
    normal_median_deg: float
    landmark_mean_px: float
    landmark_median_px: float
    visibility_accuracy: float
    foreground_iou: float
    visibility_accuracy_posed: float | None = None

    def as_dict(self) -> dict:
        return asdict(self)

    def __str__(self) -> str:
        return (f"{self.samples} images: normals mean {self.normal_mean_deg:.2f} deg, median "
                f"{self.normal_median_deg:.2f} deg; landmarks mean {self.landmark_mean_px:.2f} px, median "
                f"{self.landmark_median_px:.2f} px; visibility {100 * self.visibility_accuracy:.1f} %"
                + ("" if self.visibility_accuracy_posed is None else
                   f" ({100 * self.visibility_accuracy_posed:.1f} % with the pose)")
                + f"; foreground IoU {self.foreground_iou:.3f}")


def normal_angles(predicted: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """Angles in degrees between two normal maps at the pixels of ``mask``.

    Shape:
        - predicted, target: :math:`(B, 3, H, W)`; mask: :math:`(B, 1, H, W)` bool
        - output: :math:`(M,)` for the ``M`` pixels in ``mask``

    Example:
        >>> n = torch.zeros(1, 3, 1, 2); n[:, 2] = -1.0
        >>> m = n.clone(); m[0, :, 0, 1] = torch.tensor([1.0, 0.0, 0.0])
        >>> normal_angles(m, n, torch.ones(1, 1, 1, 2, dtype=torch.bool))
        tensor([ 0., 90.])
    """
    dims = check_shape(predicted, ["B", 3, "H", "W"], "predicted")
    check_shape(target, ["B", 3, "H", "W"], "target", dims)
    check_shape(mask, ["B", 1, "H", "W"], "mask", dims)
    if mask.dtype != torch.bool:
        raise ValueError(f"mask: expected a bool tensor, got dtype {mask.dtype}")
    for name, x in (("predicted", predicted), ("target", target)):
        check_floating(x, name)
        check_finite(x, name)
    check_same_dtype_device(predicted, "predicted", target=target)
    if mask.device != predicted.device:
        raise ValueError(f"mask: expected device {predicted.device} (that of predicted), got {mask.device}")
    for name, x in (("predicted", predicted), ("target", target)):
        short = int((x.norm(dim=1, keepdim=True)[mask] <= 0.5).sum())
        if short:  # a zero normal (background) would score 0 degrees against anything
            raise ValueError(f"{name}: {short} pixels of mask hold no normal (norm <= 0.5, e.g. background zeros); "
                             "score unit normals (the network's `normals`, not its masked `normal_map()`) or leave "
                             "those pixels out of mask")
    a, b = torch.nn.functional.normalize(predicted, dim=1), torch.nn.functional.normalize(target, dim=1)
    # atan2(|a × b|, a · b): exact near 0 and 180 degrees, where acos of a float32 cosine reads up to 0.02 degrees
    angle = torch.atan2(_cross(a, b, dim=1).norm(dim=1), (a * b).sum(1))
    return torch.rad2deg(angle)[mask[:, 0]]


#: The keys of the dataset items each function reads.
_EVALUATE_KEYS = ("image", "normals", "foreground", "landmarks", "landmark_visible")
_CALIBRATE_KEYS = ("image", "landmark_visible")


def _bad_samples(bad: Tensor, start: int) -> str:
    """``"sample 7"`` or ``"samples 7, 9"``: the dataset indices of the ``True`` entries of ``bad`` ``(B,)``."""
    index = [start + int(i) for i in torch.nonzero(bad).flatten()[:5]]
    more = ", ..." if int(bad.sum()) > len(index) else ""
    return ("sample " if len(index) == 1 else "samples ") + ", ".join(map(str, index)) + more


def _check_batch(batch: object, start: int, keys: tuple[str, ...]) -> None:
    """Raise ``ValueError`` naming ``dataset`` (and the sample index) unless a collated batch of items
    ``start, start + 1, ...`` has ``keys``, a finite image in [0, 1] (as ``predict_maps`` takes) and,
    where read, finite normals and landmarks (where visible). The net would otherwise score NaN or
    0-255 images silently, or fail on an internal argument."""
    if not isinstance(batch, dict):
        raise ValueError(f"dataset: expected items that are dictionaries with the keys {', '.join(keys)}, got "
                         f"{type(batch).__name__}")
    missing = [key for key in keys if key not in batch]
    if missing:
        raise ValueError(f"dataset: expected items with the keys {', '.join(keys)}; the items from sample {start} "
                         f"lack {', '.join(map(repr, missing))}")
    image = batch["image"]
    dims = check_shape(image, ["B", 3, "H", "W"], "dataset: the items' image")
    check_floating(image, "dataset: the items' image")
    visible = batch["landmark_visible"]
    check_shape(visible, ["B", "L"], "dataset: the items' landmark_visible", dims)
    if visible.dtype != torch.bool:
        raise ValueError(f"dataset: the items' landmark_visible: expected a bool tensor, got dtype {visible.dtype}")
    fields = {"image": image}
    if "normals" in keys:
        check_shape(batch["normals"], ["B", 3, "H", "W"], "dataset: the items' normals", dims)
        check_floating(batch["normals"], "dataset: the items' normals")
        check_shape(batch["foreground"], ["B", 1, "H", "W"], "dataset: the items' foreground", dims)
        if batch["foreground"].dtype != torch.bool:
            raise ValueError(f"dataset: the items' foreground: expected a bool tensor, got dtype "
                             f"{batch['foreground'].dtype}")
        landmarks = batch["landmarks"]
        check_shape(landmarks, ["B", "L", 2], "dataset: the items' landmarks", dims)
        fields["normals"] = batch["normals"]
        fields["landmarks"] = torch.where(visible[..., None], landmarks, 0.0)  # a hidden one may be NaN
    for name, x in fields.items():  # one synchronisation per field; these are evaluation paths
        bad = ~torch.isfinite(x).flatten(1).all(1)
        if bool(bad.any()):
            where = " where visible" if name == "landmarks" else ""
            raise ValueError(f"dataset: expected finite {name}{where}, got NaN or infinite values in "
                             f"{_bad_samples(bad, start)}")
    flat = image.flatten(1)
    if flat.shape[1]:
        bad = (flat.amin(1) < -1e-3) | (flat.amax(1) > 1.0 + 1e-3)  # 0-255 values find no landmark
        if bool(bad.any()):
            raise ValueError(f"dataset: expected images of RGB values in [0, 1] (an 8-bit image / 255), got values "
                             f"in [{float(flat.min()):g}, {float(flat.max()):g}] in {_bad_samples(bad, start)}")


@torch.no_grad()
def evaluate_network(net: NormalLandmarkUNet, dataset: Dataset, batch_size: int = 32,
                     max_samples: int | None = None, threshold: float | Tensor | None = None, workers: int = 0,
                     device: str | torch.device | None = None, mirror: bool = True,
                     model: MorphableModel | None = None, focal: float = DEFAULT_FOCAL) -> NetworkMetrics:
    """Score ``net`` on a dataset of :class:`~facenormals.data.SyntheticHeadDataset` items.

    Args:
        net: the network (put in ``eval()`` mode for the call).
        dataset: items with ``image``, ``normals``, ``foreground``, ``landmarks`` and
            ``landmark_visible``.
        batch_size: images per forward pass.
        max_samples: score only the first ``max_samples`` items.
        threshold: landmark detection threshold of :func:`~facenormals.data.landmarks_from_maps`,
            one or one per channel (default: the network's calibrated one, :func:`landmark_threshold`).
        workers: DataLoader workers.
        device: where to run (default: the network's device).
        mirror: score :func:`~facenormals.nn.mirror_averaged` predictions (what
            ``facenormals reconstruct`` uses); ``False`` scores the plain network.
        model: also score the visibility decisions after
            :func:`~facenormals.fitting.drop_hidden_landmarks` with this model's mean head
            (``visibility_accuracy_posed``; the network's channels it lacks keep their plain decisions).
        focal: the focal length prior of that pre-alignment, pixels.

    Raises:
        ValueError: when ``model`` has landmarks the network does not predict, or naming ``dataset`` when it
            is empty or an item lacks a key above, holds an image that is not finite or not in [0, 1], or
            non-finite normals or (visible) landmarks.
    """
    channels = None if model is None else landmark_channels(model)
    if threshold is None:
        threshold = landmark_threshold(net)
    else:  # NaN or 7 would find no landmark, and score the visibility as the hidden fraction
        check_threshold(threshold, getattr(net, "num_landmarks", None), "threshold")
    if max_samples is not None:
        dataset = Subset(dataset, range(min(int(max_samples), len(dataset))))
    if len(dataset) == 0:
        raise ValueError("dataset: expected at least one sample, got none")
    home = next(net.parameters()).device
    device = home if device is None else torch.device(device)
    threshold = torch.as_tensor(threshold, dtype=torch.float32, device=device)
    was_training = net.training
    net.to(device).eval()
    try:
        angles, errors = [], []
        agree = agree_posed = total = 0
        inter = union = 0
        for number, batch in enumerate(DataLoader(dataset, batch_size=batch_size, num_workers=workers)):
            _check_batch(batch, number * batch_size, _EVALUATE_KEYS)
            image = batch["image"].to(device)
            out = mirror_averaged(net, image) if mirror else net(image)
            fg = batch["foreground"].to(device)
            angles.append(normal_angles(out.normals, batch["normals"].to(device), fg).cpu())
            maps = out.landmarks.float()
            peaks, _ = landmarks_from_maps(maps, threshold=float("-inf"))  # every peak, detected or not
            found = maps.flatten(2).amax(-1) > threshold
            visible = batch["landmark_visible"].to(device)
            err = (peaks - batch["landmarks"].to(device)).norm(dim=-1)
            errors.append(err[visible].cpu())
            agree += int((found == visible).sum())
            total += visible.numel()
            if channels is not None:
                size = maps.shape[-2:]
                K = torch.tensor([focal, (size[1] - 1) / 2, (size[0] - 1) / 2]).expand(len(image), 3)
                posed = found.clone().cpu()
                posed[:, channels], _ = drop_hidden_landmarks(peaks[:, channels].cpu(), posed[:, channels], model, K,
                                                              tuple(size))
                agree_posed += int((posed == visible.cpu()).sum())
            pred_fg = out.foreground()
            inter += int((pred_fg & fg).sum())
            union += int((pred_fg | fg).sum())
    finally:
        net.train(was_training).to(home)
    angles_t, errors_t = torch.cat(angles), torch.cat(errors)

    def stat(x: Tensor, fn) -> float:
        return float(fn(x)) if x.numel() else float("nan")

    return NetworkMetrics(
        samples=len(dataset),
        normal_mean_deg=stat(angles_t, torch.mean),
        normal_median_deg=stat(angles_t, torch.median),
        landmark_mean_px=stat(errors_t, torch.mean),
        landmark_median_px=stat(errors_t, torch.median),
        visibility_accuracy=agree / max(total, 1),
        foreground_iou=inter / max(union, 1),
        visibility_accuracy_posed=None if channels is None else agree_posed / max(total, 1),
    )


@torch.no_grad()
def calibrate_landmark_threshold(net: NormalLandmarkUNet, dataset: Dataset, batch_size: int = 32,
                                 max_samples: int | None = 512, candidates: Tensor | None = None,
                                 mirror: bool = True, per_landmark: bool = True) -> tuple[float | list[float], float]:
    """The peak threshold that best separates visible from hidden landmarks on ``dataset``.

    Use samples the network will not be scored on (e.g. training samples): the threshold is then
    stored with the weights (``export_weights(..., calibration_data=...)``) and used by
    :func:`evaluate_network` and :func:`~facenormals.reconstruct.predict_maps`. ``mirror``
    calibrates the peaks of :func:`~facenormals.nn.mirror_averaged` predictions, as those use it.
    ``per_landmark`` chooses one threshold per landmark channel (the peaks of eye corners, ears and
    the nose differ: on 512 held-out images of the step-5,248 network, 77.4 % of the decisions were
    right instead of 74.4 % with one common threshold), else one for all; with ``mirror`` too, the
    two channels of each left/right pair share theirs, chosen on their pooled peaks (the averaged
    maps are mirror-symmetric, so a mirrored photo then gets the mirrored detections).

    Returns:
        ``(threshold, accuracy)``: the threshold (a list of one per channel with ``per_landmark``)
        with the most correct visibility decisions, and the fraction correct on ``dataset``.

    Raises:
        ValueError: naming ``dataset`` when it is empty, or an item lacks ``image`` or
            ``landmark_visible`` or holds an image that is not finite or not in [0, 1].
    """
    if max_samples is not None:
        dataset = Subset(dataset, range(min(int(max_samples), len(dataset))))
    if len(dataset) == 0:
        raise ValueError("dataset: expected at least one sample to calibrate on, got none")
    if candidates is None:
        candidates = torch.linspace(0.05, 0.95, 37)
    candidates = torch.as_tensor(candidates, dtype=torch.float32)
    if candidates.dim() != 1 or candidates.numel() == 0:
        raise ValueError(f"candidates: expected a non-empty 1-D tensor of thresholds, got shape "
                         f"{tuple(candidates.shape)}")
    check_threshold(candidates, None, "candidates")
    was_training = net.training
    net.eval()
    device = next(net.parameters()).device
    peaks, visible = [], []
    try:
        for number, batch in enumerate(DataLoader(dataset, batch_size=batch_size)):
            _check_batch(batch, number * batch_size, _CALIBRATE_KEYS)
            image = batch["image"].to(device)
            maps = (mirror_averaged(net, image) if mirror else net(image)).landmarks.float()
            peaks.append(maps.flatten(2).amax(-1).cpu())
            visible.append(batch["landmark_visible"])
    finally:
        net.train(was_training)
    peak, vis = torch.cat(peaks), torch.cat(visible)
    correct = torch.stack([((peak > t) == vis).float().mean(0) for t in candidates])  # (T, L)

    def middle_of_best(score: Tensor) -> int:
        # ties (e.g. a channel always visible in the data) take the middle of the best candidates
        best = torch.nonzero(score == score.max()).squeeze(1)
        return int(best[len(best) // 2])

    if per_landmark:
        # mirror-averaged maps are mirror-symmetric: a left/right pair shares one threshold, chosen on
        # their pooled peaks, so that mirroring a photo mirrors its detections
        partner = mirror_permutation() if mirror and correct.shape[1] == len(LANDMARK_NAMES) else None
        chosen = [middle_of_best(correct[:, c] if partner is None else correct[:, c] + correct[:, partner[c]])
                  for c in range(correct.shape[1])]
        accuracy = sum(float(correct[i, c]) for c, i in enumerate(chosen)) / len(chosen)
        return [float(candidates[i]) for i in chosen], accuracy
    best = middle_of_best(correct.mean(1))
    return float(candidates[best]), float(correct[best].mean())
