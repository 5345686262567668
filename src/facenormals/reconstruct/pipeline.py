r"""The product recipe: photos → network maps → landmark pre-alignment → multi-view fit → files.

Every step is a public op: :func:`~facenormals.reconstruct.detect_faces` and
:func:`~facenormals.reconstruct.crop_square` frame the head, the network
(:func:`~facenormals.nn.load_weights`) predicts the normal map N and landmark maps Z,
:func:`~facenormals.data.landmarks_from_maps` decodes Z into sub-pixel landmarks with
visibility, :func:`~facenormals.fitting.drop_hidden_landmarks` drops the detections the
pre-aligned head hides, and :func:`~facenormals.fitting.fit_head` pre-aligns and fits the
morphable model, one shared shape over all views.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from facenormals.core.check import check_floating, check_nonnegative, check_shape, check_unit_range
from facenormals.core.files import StagedFiles
from facenormals.data.landmark_maps import landmarks_from_maps
from facenormals.fitting import (FACING_AWAY_COSINE, FacingAwayWarning, FitResult, FitWeights, NormalAxisError,
                                 PoseEstimate, drop_hidden_landmarks, fit_head)
from facenormals.fitting.landmark_visibility import DEFAULT_FOCAL
from facenormals.fitting.pose import require_pose_landmarks
from facenormals.geometry import euler_to_rotation_matrix, project_points
from facenormals.models import LANDMARK_NAMES, MorphableModel
from facenormals.reconstruct.detect import NoFaceError, check_crop_box
from facenormals.nn.mirror import mirror_averaged
from facenormals.nn.pretrained import landmark_threshold
from facenormals.nn.unet import NormalLandmarkUNet

__all__ = ["FitInputs", "NETWORK_FIT_WEIGHTS", "NetworkMaps", "PhotoView", "Reconstruction", "fit_inputs", "landmark_channels", "network_fit_weights",
           "predict_maps", "reconstruct_views", "write_reconstruction"]

#: Energy weights of the fit to the shipped network's maps: the paper's λZ, and λN and λP chosen for
#: the shipped network on validation renders by
#: ``benchmarks/tune_network_fit.py`` (docs/model_card.md). Its normals are ~12 deg off on average
#: (9 deg median): at the paper's λN = 1 the fit follows their errors, and landmarks alone do as
#: well; a tenth of the normal term and λP = 1 scored best (4 % lower p2p RMSE than λN = 1, λP = 2,
#: 1.303 against 1.363 mm, on 32 validation heads). Exact maps want the paper's weights (``FitWeights()``).
NETWORK_FIT_WEIGHTS = FitWeights(normals=0.1, landmarks=0.8, prior=1.0)

#: A view fitted to fewer landmarks than this (after dropping hidden ones) is reported as unreliable.
MIN_RELIABLE_LANDMARKS = 6


def network_fit_weights(net: torch.nn.Module) -> FitWeights:
    """The fit weights for ``net``'s maps: :data:`NETWORK_FIT_WEIGHTS` with the entries its weight
    file stores in ``metadata["fit_weights"]`` (e.g. ``{"normals": 0.25, "prior": 1.0}``, chosen for
    that network by ``benchmarks/tune_network_fit.py --store``), so that a network of one's own
    brings its own λN and λP.

    Raises:
        ValueError: naming the metadata entry when it is not a mapping of :class:`FitWeights` fields
            to non-negative numbers.

    Example:
        >>> net = NormalLandmarkUNet(base_channels=4, depth=2)
        >>> network_fit_weights(net) == NETWORK_FIT_WEIGHTS
        True
        >>> net.metadata = {"fit_weights": {"normals": 1.0, "prior": 0.4}}
        >>> w = network_fit_weights(net)
        >>> w.normals, w.landmarks, w.prior
        (1.0, 0.8, 0.4)
    """
    stored = getattr(net, "metadata", {}).get("fit_weights")
    if stored is None:
        return NETWORK_FIT_WEIGHTS
    fields = {f.name for f in dataclasses.fields(FitWeights)}
    if not isinstance(stored, dict) or not set(stored) <= fields or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0
            for v in stored.values()):
        raise ValueError(f"weights metadata 'fit_weights': expected a mapping of {sorted(fields)} to non-negative "
                         f"numbers, got {stored!r}")
    return dataclasses.replace(NETWORK_FIT_WEIGHTS, **{k: float(v) for k, v in stored.items()})


@dataclass
class PhotoView:
    """One input photo and the square crop fed to the network.

    Attributes:
        crop: ``(S, S, 3)`` uint8 RGB network input.
        box: ``(x0, y0, side)`` of the crop in the photo's pixels (see :func:`crop_square`); default:
            the crop is the whole photo, ``(0, 0, S)``.
        image_size: ``(H, W)`` of the photo (after EXIF rotation); default ``(S, S)``.
        path: where the photo came from, if a file.
        alternatives: crops of the detector's other faces in the photo, best first (tried when the
            network finds too few landmarks in this one).
    """

    crop: np.ndarray
    box: tuple[float, float, float] | None = None
    image_size: tuple[int, int] | None = None
    path: str | None = None
    alternatives: list["PhotoView"] = field(default_factory=list)

    def __post_init__(self) -> None:
        shape = getattr(self.crop, "shape", None)
        if shape is None or len(shape) != 3 or shape[0] != shape[1] or shape[2] != 3 or shape[0] < 1:
            raise ValueError(f"crop: expected a square (S, S, 3) RGB image, got {shape if shape is not None else type(self.crop).__name__}")
        side = int(shape[0])
        if self.box is None:  # the crop is the whole photo (a 256-pixel crop used to read as 128)
            self.box = (0.0, 0.0, float(side))
        self.box = check_crop_box(self.box)
        if self.image_size is None:
            self.image_size = (side, side)

    def to_image(self, pixels: Tensor) -> Tensor:
        """Crop pixels ``(..., 2)`` to photo pixels."""
        x0, y0, side = self.box
        s = side / self.crop.shape[0]
        offset = torch.tensor([x0 + 0.5 * s - 0.5, y0 + 0.5 * s - 0.5], dtype=pixels.dtype, device=pixels.device)
        return pixels * s + offset


@dataclass
class NetworkMaps:
    """The network's output for ``V`` views.

    Attributes:
        normal_maps: ``(V, 3, S, S)`` unit camera-frame normals, zero on predicted background.
        landmark_maps: ``(V, L, S, S)``.
        landmarks: ``(V, L, 2)`` sub-pixel landmarks, NaN where not detected.
        found: ``(V, L)`` detection mask.
        seconds: wall time of the forward pass.
    """

    normal_maps: Tensor
    landmark_maps: Tensor
    landmarks: Tensor
    found: Tensor
    seconds: float = 0.0


@torch.no_grad()
def predict_maps(net: NormalLandmarkUNet, crops: Tensor, threshold: float | None = None,
                 mirror: bool = True) -> NetworkMaps:
    """Run the network on ``(V, 3, S, S)`` crops in ``[0, 1]`` and decode its landmark maps.

    A landmark is detected where its map's peak exceeds ``threshold`` (default: the threshold
    calibrated for the network, see :func:`~facenormals.training.calibrate_landmark_threshold`).
    With ``mirror`` the prediction is averaged with that of the mirrored crops
    (:func:`~facenormals.nn.mirror_averaged`: better maps for twice the network time).
    The network runs on its own device (e.g. CUDA) and in its own dtype; the maps come back on the
    CPU, where the fit and the output files are made (the points in at least float32). Weights
    that record the side of their training images (``metadata["image_size"]``, written by
    :func:`~facenormals.training.export_weights`; 128 for the shipped ones) warn on crops of
    another size: the network is convolutional and runs, but a face at another scale gives it
    maps it has not learnt.

    Example:
        >>> net = NormalLandmarkUNet(base_channels=4, depth=2).eval()
        >>> maps = predict_maps(net, torch.rand(2, 3, 16, 16))
        >>> maps.normal_maps.shape, maps.landmarks.shape
        (torch.Size([2, 3, 16, 16]), torch.Size([2, 24, 2]))
    """
    check_shape(crops, ["V", 3, "S", "S"], "crops")
    check_floating(crops, "crops")
    # one NaN pixel would turn every map into NaN; 0-255 values find no landmark, and read as "no face"
    check_unit_range(crops, "crops")
    factor = 2 ** getattr(net, "depth", 0)
    if crops.shape[-1] % factor or crops.shape[-1] < factor:
        raise ValueError(f"crops: expected a side that is a positive multiple of {factor} (the network's "
                         f"2**depth), got shape {tuple(crops.shape)}")
    if mirror and getattr(net, "num_landmarks", len(LANDMARK_NAMES)) != len(LANDMARK_NAMES):
        raise ValueError(f"mirror: the built-in mirroring swaps the library's {len(LANDMARK_NAMES)} landmark "
                         f"channels, and this network predicts {net.num_landmarks}: pass mirror=False, or "
                         "mirror it yourself with facenormals.nn.mirror_averaged and its permutation")
    metadata = getattr(net, "metadata", None)
    trained = metadata.get("image_size") if isinstance(metadata, dict) else None
    if isinstance(trained, int) and crops.shape[-1] != trained:
        warnings.warn(f"crops: {crops.shape[-1]}x{crops.shape[-1]} pixels, but the network was trained on "
                      f"{trained}x{trained} crops, and its maps at another scale are unreliable (crop to that size, "
                      f"e.g. facenormals.reconstruct.crop_square(image, box, size={trained}))", UserWarning, stacklevel=2)
    if threshold is None:
        threshold = landmark_threshold(net)
    start = time.perf_counter()
    device = next(net.parameters()).device
    crops = crops.to(device=device, dtype=next(net.parameters()).dtype)
    out = mirror_averaged(net, crops) if mirror else net(crops)
    points, found = landmarks_from_maps(out.landmarks, threshold=threshold)
    return NetworkMaps(out.normal_map().cpu(), out.landmarks.cpu(), points.cpu(), found.cpu(),
                       seconds=time.perf_counter() - start)


def _check_model(model: object) -> None:
    """Raise ``ValueError`` naming ``model`` unless it is a :class:`~facenormals.models.MorphableModel`."""
    if not isinstance(model, MorphableModel):
        raise ValueError(f"model: expected a MorphableModel, got {type(model).__name__}")


def landmark_channels(model: MorphableModel) -> list[int]:
    """The network's landmark channel of each of ``model``'s landmarks, matched by name.

    Raises:
        ValueError: naming the model's landmarks the network does not predict.

    Example:
        >>> from facenormals.models import builtin_head_model
        >>> tuple(landmark_channels(builtin_head_model())[:4])
        (0, 1, 2, 3)
    """
    _check_model(model)
    missing = [name for name in model.landmark_names if name not in LANDMARK_NAMES]
    if missing:
        raise ValueError(f"model: landmarks {missing} of model {model.name!r} are not among the network's "
                         f"{len(LANDMARK_NAMES)} landmarks {LANDMARK_NAMES}")
    return [LANDMARK_NAMES.index(name) for name in model.landmark_names]


@dataclass
class FitInputs:
    """What :func:`~facenormals.fitting.fit_head` takes from the network's maps of ``V`` views.

    Attributes:
        normal_maps: ``(V, 3, S, S)`` in the model's dtype.
        landmarks: ``(V, L, 2)`` in the order of ``model.landmark_names``, NaN where not detected or
            dropped.
        intrinsics: ``(V, 3)`` prior ``(f, u0, v0)``: the focal length prior and the crop centre.
        dropped: ``(V, L)`` detections dropped as hidden by the pre-aligned mean head.
        prealignment: the pose the drop was judged at; ``None`` without the drop or when some view
            had too few detections to pre-align.
    """

    normal_maps: Tensor
    landmarks: Tensor
    intrinsics: Tensor
    dropped: Tensor
    prealignment: PoseEstimate | None = None

    @property
    def initial_pose(self) -> tuple[Tensor, Tensor] | None:
        """``(angles, translation)`` for ``fit_head(..., initial_pose=)``: fit from the pose the drop
        was judged at (see :func:`~facenormals.fitting.drop_hidden_landmarks`)."""
        return None if self.prealignment is None else (self.prealignment.angles, self.prealignment.translation)


def fit_inputs(maps: NetworkMaps, model: MorphableModel, focal: float = DEFAULT_FOCAL,
               drop_hidden: bool = True) -> FitInputs:
    """Turn the network's maps into the inputs of the fit, as :func:`reconstruct_views` does.

    The network's landmark channels are matched to ``model``'s landmarks by name
    (:func:`landmark_channels`), the intrinsics prior is ``focal`` with the principal point at the crop
    centre, and with ``drop_hidden`` the detections that the mean head, pre-aligned to them, hides are
    dropped (:func:`~facenormals.fitting.drop_hidden_landmarks`). ``maps`` is not changed.

    Raises:
        ValueError: naming ``maps`` when its fields disagree in shape, or ``focal`` when it is not
            positive.

    Example:
        >>> from facenormals.models import builtin_head_model
        >>> model = builtin_head_model()
        >>> maps = NetworkMaps(torch.zeros(2, 3, 128, 128), torch.zeros(2, 24, 128, 128),
        ...                    torch.full((2, 24, 2), float("nan")), torch.zeros(2, 24, dtype=torch.bool))
        >>> inputs = fit_inputs(maps, model)
        >>> tuple(inputs.landmarks.shape), inputs.intrinsics[0].tolist(), inputs.prealignment is None
        ((2, 24, 2), [300.0, 63.5, 63.5], True)
    """
    dims = check_shape(maps.normal_maps, ["V", 3, "S", "S"], "maps.normal_maps")
    check_shape(maps.landmarks, ["V", "C", 2], "maps.landmarks", dims)
    check_shape(maps.found, ["V", "C"], "maps.found", dims)
    check_floating(maps.normal_maps, "maps.normal_maps")  # integer maps would truncate the unit normals to 0
    check_floating(maps.landmarks, "maps.landmarks")  # bool or integer points would pre-align a wrong head
    V, S = dims["V"], dims["S"]
    _check_model(model)
    require_pose_landmarks(model)
    if not check_nonnegative(focal, "focal") > 0:
        raise ValueError(f"focal: expected a positive focal length in pixels, got {focal}")
    channels = landmark_channels(model)
    if max(channels) >= dims["C"]:
        raise ValueError(f"maps.landmarks: expected the network's {len(LANDMARK_NAMES)} landmark channels, "
                         f"got {dims['C']}")
    dtype = model.mean.dtype
    intrinsics = torch.tensor([focal, (S - 1) / 2, (S - 1) / 2], dtype=dtype).expand(V, 3)
    if maps.found.dtype != torch.bool:
        raise ValueError(f"maps.found: expected a bool tensor, got dtype {maps.found.dtype}")
    landmarks, found = maps.landmarks[:, channels].to(dtype), maps.found[:, channels]
    landmarks = landmarks.masked_fill(~found[..., None], float("nan"))  # a landmark not found is no landmark
    dropped, pose = torch.zeros_like(found), None
    if drop_hidden:
        kept, pose = drop_hidden_landmarks(landmarks, found, model, intrinsics, (S, S))
        dropped = found & ~kept
        landmarks = landmarks.masked_fill(dropped[..., None], float("nan"))
    return FitInputs(maps.normal_maps.to(dtype), landmarks, intrinsics, dropped, pose)


def reconstruct_views(crops: Tensor, net: NormalLandmarkUNet, model: MorphableModel,
                      focal: float = DEFAULT_FOCAL, log: Callable[[str], None] | None = None,
                      mirror: bool = True, drop_hidden: bool = True, view_names: Sequence[str] | None = None,
                      maps: NetworkMaps | None = None, **fit_options: Any) -> tuple[NetworkMaps, FitResult]:
    """Predict the maps of ``V`` crops of one person (or take ``maps``) and fit one shared head to all of them.

    Args:
        crops: ``(V, 3, S, S)`` network inputs in ``[0, 1]``.
        net: the trained network.
        model: the morphable model (its landmarks are matched to the network's by name).
        focal: focal length prior in crop pixels (the fit refines it per view).
        log: progress messages go here.
        mirror: average the network's maps with those of the mirrored crops (:func:`predict_maps`).
        drop_hidden: drop the detected landmarks that the mean head, pre-aligned to them, hides
            (:func:`~facenormals.fitting.drop_hidden_landmarks`), and fit from that pre-alignment;
            ``maps.found`` and ``maps.landmarks`` then hold the landmarks the fit uses.
        view_names: how error messages name the views (e.g. their files); default ``view 0``, ...
        maps: ``predict_maps(net, crops, mirror=mirror)`` if already computed (it is then used, and
            changed as ``drop_hidden`` says, instead of predicting again).
        **fit_options: passed to :func:`~facenormals.fitting.fit_head` (``weights`` defaults to
            :func:`network_fit_weights` of ``net``); not ``intrinsics``, which come from ``focal``
            and the crop size.

    Raises:
        NoFaceError: naming the view when the network finds fewer than 4 of the model's landmarks in
            it (too few to pre-align: no face, or a crop that misses it), or when the fit puts the
            landmarks found on a head turned away from the camera (spurious peaks in a crop without
            a face), or when the network's normal map of the view points against the head posed by
            its landmarks (under-trained weights, or no face in the crop).
        ValueError: when ``fit_options`` holds ``intrinsics``.
    """
    if "intrinsics" in fit_options:  # fit_head would get them twice, a TypeError deep inside
        raise ValueError("intrinsics: not a fit option here; the intrinsics are (focal, (S - 1) / 2, (S - 1) / 2) "
                         "in crop pixels: give focal= (the fit refines it per view)")
    log = log or (lambda message: None)
    fit_options.setdefault("weights", network_fit_weights(net))
    dims = check_shape(crops, ["V", 3, "S", "S"], "crops")
    V, S = dims["V"], dims["S"]
    if V < 1 or S < 1:  # fit_head would name its normal_maps instead
        raise ValueError(f"crops: expected at least one view of at least one pixel, got shape {tuple(crops.shape)}")
    _check_model(model)
    if maps is None:
        maps = predict_maps(net, crops, mirror=mirror)
    else:
        L = maps.found.shape[-1]
        for name, shape in (("normal_maps", (V, 3, S, S)), ("landmark_maps", (V, L, S, S)),
                            ("landmarks", (V, L, 2)), ("found", (V, L))):
            if tuple(getattr(maps, name).shape) != shape:
                raise ValueError(f"maps: expected the maps of the {V} crops of {S}x{S} px, {name} of shape {shape}, "
                                 f"got {tuple(getattr(maps, name).shape)}")
    log(f"network: {V} view(s) in {maps.seconds * 1e3:.0f} ms; landmarks found per view: "
        f"{', '.join(str(int(n)) for n in maps.found.sum(1).tolist())} of {maps.found.shape[1]}")
    inputs = fit_inputs(maps, model, focal, drop_hidden and "initial_pose" not in fit_options)
    if inputs.prealignment is not None:
        fit_options["initial_pose"] = inputs.initial_pose
    if bool(inputs.dropped.any()):
        channels = landmark_channels(model)
        maps.found[:, channels] &= ~inputs.dropped
        maps.landmarks[:, channels] = maps.landmarks[:, channels].masked_fill(inputs.dropped[..., None], float("nan"))
        log(f"landmarks hidden by the pre-aligned head, dropped per view: "
            f"{', '.join(str(int(n)) for n in inputs.dropped.sum(1).tolist())}")
    names = list(view_names) if view_names is not None else [f"view {v}" for v in range(V)]
    if len(names) != V:
        raise ValueError(f"view_names: expected one per view ({V}), got {len(names)}")
    used = torch.isfinite(inputs.landmarks).all(-1).sum(1).tolist()  # landmarks the fit gets, per view
    for name, count in zip(names, used):
        if count < 4:
            raise NoFaceError(f"{name}: the network found {count} of the model's {len(model.landmark_names)} "
                              "landmarks, too few (< 4) to pre-align a head: is there a face in its crop? (a "
                              "profile view may need its face box, --box X,Y,W,H)")
    start = time.perf_counter()
    with warnings.catch_warnings():  # a head facing away is refused below, naming the photo
        warnings.simplefilter("ignore", FacingAwayWarning)
        try:
            fit = fit_head(inputs.normal_maps, inputs.landmarks, model, intrinsics=inputs.intrinsics, **fit_options)
        except NormalAxisError as error:
            raise _map_disagreement(error, names, used) from None
    if inputs.prealignment is not None:  # fit_head skipped its pre-alignment: report this one (over all detections)
        fit.prealignment_rms_px = inputs.prealignment.rms_px.reshape(1, V).to(fit.prealignment_rms_px)
    log(f"fit: {fit.summary()} in {(time.perf_counter() - start) * 1e3:.0f} ms")
    _require_facing_heads(fit, names, used)
    dropped = inputs.dropped.sum(1).tolist()
    for v in range(V):
        f_v, median = float(fit.intrinsics[0, v, 0]), float(fit.landmark_median_px[0, v])
        # few landmarks left, or most detections hidden by the head posed to them: a pose the
        # landmarks barely constrain (seen: a weak network's frontal photo fitted at 62 deg yaw)
        if (not (0.25 * focal <= f_v <= 4.0 * focal) or not median <= 0.05 * S or used[v] < MIN_RELIABLE_LANDMARKS
                or dropped[v] > used[v]):
            log(f"warning: view {v} looks unreliable (focal {f_v:.0f} px against the prior {focal:.0f} px, "
                f"median landmark error {median:.1f} px, {used[v]} landmarks fitted, {dropped[v]} dropped as "
                f"hidden): check view{v}_overlay.png and view{v}_landmarks.png")
    return maps, fit


def _map_disagreement(error: NormalAxisError, names: list[str], used: list[int]) -> NoFaceError:
    """The :class:`NoFaceError` naming the view of ``error``, fit_head's refusal of a normal map whose x
    or y axis points against the head pre-aligned to the view's landmarks. The caller gave no normal
    maps: the network's map disagrees with its own landmarks (under-trained weights, or spurious
    detections in a crop without a face), not a flipped axis."""
    return NoFaceError(f"{names[error.view]}: the network's normal map disagrees with the head posed by its "
                       f"{used[error.view]} landmarks (its {error.axis} components point against the head's: cosine "
                       f"{error.cosine:.2f} over {error.pixels} pixels): are the network's weights trained enough (if "
                       "--weights was given), and is there a face in its crop? (a profile view may need its face "
                       "box, --box X,Y,W,H)")


def _require_facing_heads(fit: FitResult, names: list[str], used: list[int]) -> None:
    """Raise :class:`NoFaceError` naming a view whose found landmarks the fit placed on a head turned
    away from the camera (:attr:`FitResult.landmark_facing` above ``FACING_AWAY_COSINE``): landmarks
    that are seen cannot face away. Spurious peaks in a crop without a face (a wrong ``--box``, a
    black image) fitted such heads at 130 deg of yaw, "converged"; on held-out renders at any yaw
    the fitted heads score at most -0.18."""
    for v, cosine in enumerate(fit.landmark_facing[0].tolist()):
        if cosine > FACING_AWAY_COSINE:
            yaw = math.degrees(float(fit.angles[0, v, 2]))
            raise NoFaceError(f"{names[v]}: the {used[v]} landmarks the network found fit only a head turned away "
                              f"from the camera (yaw {yaw:.0f} deg): is there a face in its crop? (a profile view "
                              "may need its face box, --box X,Y,W,H)")


@dataclass
class Reconstruction:
    """Everything :func:`write_reconstruction` writes."""

    views: list[PhotoView]
    maps: NetworkMaps
    fit: FitResult
    model: MorphableModel
    timings: dict[str, float] = field(default_factory=dict)
    #: what :func:`~facenormals.models.load_model` reloads the model from (``"ict"``, ``"builtin"`` or
    #: an absolute path), ``None`` when the model was given as an object.
    model_spec: str | None = None


class _Staged(StagedFiles):
    """:class:`~facenormals.core.files.StagedFiles` that also writes RGB images as PNG."""

    def png(self, path: Path, rgb: np.ndarray) -> Path:
        import cv2

        def write(tmp: Path) -> None:
            if not cv2.imwrite(str(tmp), np.ascontiguousarray(rgb[..., ::-1])):
                raise OSError(f"{path}: cannot write the PNG")

        return self.write(path, write)


def landmark_map_image(crop: np.ndarray, landmark_maps: Tensor, scale: int = 4) -> np.ndarray:
    """Landmark maps Z over a dimmed crop: the maximum over channels in a heat colour, ``(S·scale, S·scale, 3)``."""
    import cv2

    heat = landmark_maps.detach().float().clamp(0, 1).amax(0).numpy()
    colour = cv2.applyColorMap((heat * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)[..., ::-1]
    alpha = heat[..., None]
    out = (crop.astype(np.float32) * 0.35 * (1 - alpha) + colour.astype(np.float32) * alpha).astype(np.uint8)
    return cv2.resize(out, (out.shape[1] * scale, out.shape[0] * scale), interpolation=cv2.INTER_NEAREST)


def _wrap_degrees(radians: float) -> float:
    """An angle in degrees in (-180, 180]."""
    degrees = math.degrees(radians) % 360.0
    return degrees - 360.0 if degrees > 180.0 else degrees


#: The files :func:`write_reconstruction` writes besides the per-view pictures (``_VIEW_PICTURE``).
RECONSTRUCTION_FILES = ("head.ply", "head.obj", "params.json")
#: The pictures written per view, ``view{v}_{kind}.png``.
VIEW_PICTURE_KINDS = ("overlay", "normals", "landmarks")
_VIEW_PICTURE = re.compile(rf"view(\d+)_({'|'.join(VIEW_PICTURE_KINDS)})\.png")


def reconstruction_would_replace(path: str | Path, out_dir: str | Path) -> bool:
    """Whether writing a reconstruction into ``out_dir`` may replace or remove the file ``path``: one
    of :data:`RECONSTRUCTION_FILES` or a view picture (earlier runs' extra views are removed)."""
    path = Path(path).resolve()
    return path.parent == Path(out_dir).resolve() and (
        path.name in RECONSTRUCTION_FILES or _VIEW_PICTURE.fullmatch(path.name) is not None)


def write_reconstruction(rec: Reconstruction, out_dir: str | Path) -> list[Path]:
    """Write ``head.ply``, ``head.obj``, ``params.json`` and per view an overlay, N and Z pictures.

    Every file is written to a unique temporary name first and all are renamed into place together
    once all are written, so an interrupted or failed run never leaves a half-written file nor a mix
    of old and new files. The view pictures of an earlier run with more photos (those its
    ``params.json`` lists beyond this run's views) are removed in the same step; other files are
    left alone.
    """
    if not isinstance(rec, Reconstruction):
        raise ValueError(f"rec: expected a Reconstruction, got {type(rec).__name__}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    staged = _Staged()
    try:
        _stage_reconstruction(rec, out, staged)
        # an earlier run with more photos left views this one does not have: they would not match params.json
        inputs = {Path(view.path).resolve() for view in rec.views if view.path is not None}
        for v in range(len(rec.views), _written_views(out / "params.json")):
            for kind in VIEW_PICTURE_KINDS:
                stale = out / f"view{v}_{kind}.png"
                if (stale.is_file() or stale.is_symlink()) and stale.resolve() not in inputs:
                    staged.remove(stale)
        return staged.commit()
    finally:
        staged.discard()


def _written_views(params: Path) -> int:
    """The number of views in an earlier run's ``params.json``; 0 if there is none or it is not one."""
    try:
        with open(params, encoding="utf-8") as handle:
            earlier = json.load(handle)
    except (OSError, ValueError):
        return 0
    if not isinstance(earlier, dict) or earlier.get("format") != "facenormals-reconstruction":
        return 0
    views = earlier.get("views")
    return len(views) if isinstance(views, list) else 0


def _stage_reconstruction(rec: Reconstruction, out: Path, staged: _Staged) -> None:
    from facenormals.mesh import save_mesh
    from facenormals.render import draw_alignment, normal_map_to_image

    import cv2

    fit, maps = rec.fit, rec.maps
    fitted, predicted = fit.angles.shape[1], maps.normal_maps.shape[0]
    if not len(rec.views) == fitted == predicted:
        raise ValueError(f"rec: {len(rec.views)} views, {predicted} network maps and {fitted} fitted views; "
                         "expected one of each per photo")
    staged.write(out / "head.ply", lambda p: save_mesh(p, fit.vertices[0], fit.faces))
    staged.write(out / "head.obj", lambda p: save_mesh(p, fit.vertices[0], fit.faces))
    R = euler_to_rotation_matrix(fit.angles[0])
    pixels, _ = project_points(fit.vertices.expand(R.shape[0], -1, -1), R, fit.translation[0], fit.intrinsics[0])
    views_json = []
    for v, view in enumerate(rec.views):
        stem = f"view{v}"
        overlay = draw_alignment(view.crop, pixels[v], maps.landmarks[v], visible=fit.visible[0, v])
        normals = cv2.resize(normal_map_to_image(maps.normal_maps[v]), overlay.shape[1::-1],
                             interpolation=cv2.INTER_NEAREST)
        staged.png(out / f"{stem}_overlay.png", overlay)
        staged.png(out / f"{stem}_normals.png", normals)
        staged.png(out / f"{stem}_landmarks.png", landmark_map_image(view.crop, maps.landmark_maps[v]))
        f, u0, v0 = fit.intrinsics[0, v].tolist()
        x0, y0, side = view.box
        s = side / view.crop.shape[0]
        u0_image, v0_image = view.to_image(fit.intrinsics[0, v, 1:].double()).tolist()
        views_json.append({
            "image": view.path,
            "image_size": list(view.image_size),
            "crop_box_xy_side": [x0, y0, side],
            "angles_deg": dict(zip(("roll", "pitch", "yaw"), (_wrap_degrees(a) for a in fit.angles[0, v].tolist()))),
            "rotation": fit.rotation[0, v].tolist(),
            "translation_mm": fit.translation[0, v].tolist(),
            "intrinsics_crop_px": {"f": f, "u0": u0, "v0": v0},
            "intrinsics_image_px": {"f": f * s, "u0": u0_image, "v0": v0_image},
            "landmarks_crop_px": {name: (None if not bool(maps.found[v, i]) else maps.landmarks[v, i].tolist())
                                  for i, name in enumerate(LANDMARK_NAMES)},
            "landmark_rms_px": float(fit.landmark_rms_px[0, v]),
            "landmark_median_px": float(fit.landmark_median_px[0, v]),
        })
    params = {
        "format": "facenormals-reconstruction", "version": 1,
        "model": rec.model.name, "model_spec": rec.model_spec, "units": "mm",
        "convention": "X_camera = R (X_model + t); pixel = (f X/Z + u0, f Y/Z + v0); see docs/conventions.md",
        "shape_coeffs": fit.shape_coeffs[0].tolist(),
        "expression_coeffs": None if fit.expression_coeffs is None else fit.expression_coeffs[0].tolist(),
        "views": views_json,
        "energies": {k: float(e[0]) for k, e in fit.energies.items()},
        "iterations": int(fit.iterations[0]),
        "status": fit.reasons[0] if fit.reasons else None,
        "timings_s": rec.timings,
    }
    staged.write(out / "params.json", lambda p: p.write_text(json.dumps(params, indent=2)))
