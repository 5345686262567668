"""``reconstruct_photos``: the whole product path from image files to the output folder."""

from __future__ import annotations

import copy
import math
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np
import torch

from facenormals.core.check import check_device, check_folder_name
from facenormals.fitting.pose import require_pose_landmarks
from facenormals.reconstruct.detect import FaceBox, NoFaceError, crop_square, detect_faces, head_crop_box
from facenormals.reconstruct.images import read_image
from facenormals.models import LANDMARK_NAMES
from facenormals.reconstruct.pipeline import (NetworkMaps, PhotoView, Reconstruction, landmark_channels,
                                              network_fit_weights, predict_maps, reconstruct_views,
                                              reconstruction_would_replace, write_reconstruction)

if TYPE_CHECKING:
    from facenormals.fitting import FitWeights
    from facenormals.models import MorphableModel

__all__ = ["prepare_view", "reconstruct_photos"]


def prepare_view(path: str | Path, box: tuple[float, float, float, float] | None = None, size: int = 128,
                 max_alternatives: int = 2) -> PhotoView:
    """Read a photo, find the face (or use ``box = (x, y, w, h)``) and crop the head to ``size``².

    The detector's next ``max_alternatives`` faces, if any, come along as ``view.alternatives``.

    Raises:
        ImageReadError: the file is missing or not an image.
        NoFaceError: no face was detected; the message names the file.
    """
    image = read_image(path)
    if box is None:
        faces = detect_faces(image)
        if not faces:
            raise NoFaceError(f"{path}: no face found (the detector finds roughly frontal faces; "
                              "for a profile view pass its face box with --box X,Y,W,H)")
        face, others = faces[0], faces[1 : 1 + max_alternatives]
    else:
        others = []
        try:
            x, y, w, h = (float(v) for v in box)
        except (TypeError, ValueError):
            raise ValueError(f"{path}: face box: expected four numbers (x, y, width, height), got {box!r}") from None
        H, W = image.shape[:2]
        if not all(math.isfinite(v) for v in (x, y, w, h)) or not (w > 0 and h > 0):
            raise ValueError(f"{path}: face box: expected finite numbers and a positive width and height, got {box}")
        if not (x < W and y < H and x + w > 0 and y + h > 0) or max(w, h) > 4 * max(H, W):
            raise ValueError(f"{path}: face box {box} does not frame a face in the {W}x{H} image (it must overlap "
                             "the image and be at most 4 times its size)")
        face = FaceBox(x, y, w, h)
    views = [PhotoView(crop=crop_square(image, b, size), box=b, image_size=image.shape[:2], path=str(path))
             for b in (head_crop_box(f) for f in (face, *others))]
    views[0].alternatives = views[1:]
    return views[0]


def _network_input(crops: list[np.ndarray]) -> torch.Tensor:
    """``(V, 3, S, S)`` float32 in ``[0, 1]`` from ``V`` ``(S, S, 3)`` uint8 crops."""
    return torch.from_numpy(np.stack(crops)).permute(0, 3, 1, 2).float() / 255.0


#: landmarks the network must find in another detected face for the photo's log to mention it (a
#: real face shows 18-19 of 24, a stray detection none or one)
OTHER_FACE_LANDMARKS = 12


def _pick_faces(views: list[PhotoView], net, model, mirror: bool,
                log: Callable[[str], None]) -> tuple[list[PhotoView], NetworkMaps]:
    """The network's maps of every photo's first detected face (one batch); for a photo whose first
    face shows the network too few (< 4) of ``model``'s landmarks (a stray detection can rank first),
    the first of its other detected faces that shows enough, with its maps. Other detected faces in
    which the network finds a face (:data:`OTHER_FACE_LANDMARKS`) are logged: the fit uses one."""
    channels = landmark_channels(model)

    def predict(crops: list[np.ndarray]) -> NetworkMaps:
        return predict_maps(net, _network_input(crops), mirror=mirror)

    maps = predict([v.crop for v in views])
    candidates = [(i, c) for i, v in enumerate(views) for c in v.alternatives]  # one batch for all photos
    others = predict([c.crop for _, c in candidates]) if candidates else None
    if others is not None:
        maps.seconds += others.seconds
    picked = list(views)
    for k, (i, candidate) in enumerate(candidates):
        found = int(others.found[k, channels].sum())
        if picked[i] is views[i] and int(maps.found[i, channels].sum()) < 4 and found >= 4:
            picked[i] = candidate
            for field in ("normal_maps", "landmark_maps", "landmarks", "found"):
                getattr(maps, field)[i] = getattr(others, field)[k]
            log(f"{views[i].path}: too few landmarks in the first detected face; using the next one, head crop "
                f"{candidate.box[2]:.0f} px at ({candidate.box[0]:.0f}, {candidate.box[1]:.0f})")
        elif found >= OTHER_FACE_LANDMARKS:
            log(f"{views[i].path}: another face, head crop {candidate.box[2]:.0f} px at ({candidate.box[0]:.0f}, "
                f"{candidate.box[1]:.0f}), is not fitted; pass its face box with --box X,Y,W,H to fit it instead")
    return picked, maps


def reconstruct_photos(paths: Sequence[str | Path], out_dir: str | Path | None,
                       model: "MorphableModel | str" = "auto", weights: str | Path | None = None,
                       device: str = "cpu", boxes: Sequence | None = None,
                       log: Callable[[str], None] = print, fit_weights: "FitWeights | None" = None,
                       mirror: bool = True, **fit_options: Any) -> Reconstruction:
    """Reconstruct one head from one or more photos of a person and write the results.

    The model and the weights are loaded, then all photos read and their faces found, before anything
    is computed or written: a bad model, weight file or photo stops the run early with a message
    naming it and leaves ``out_dir`` untouched.

    Args:
        paths: image files (or one file); several give a multi-view fit with one shared shape.
        out_dir: output folder (``None``: write nothing).
        model: a :class:`~facenormals.models.MorphableModel` or a spec for
            :func:`~facenormals.models.load_model` (``"auto"``: ICT-FaceKit when installed, else
            the built-in head).
        weights: network weight file (default: the shipped weights).
        device: where the network runs.
        boxes: optional face boxes ``(x, y, w, h)`` per photo (``None`` entries: detect).
        log: progress messages.
        fit_weights: the fit's energy weights (default: those stored with the network's weights,
            :func:`~facenormals.reconstruct.network_fit_weights`).
        mirror: average the network's maps with those of the mirrored crops.
        **fit_options: passed to :func:`~facenormals.fitting.fit_head`.
    """
    from facenormals.models import MorphableModel, load_model
    from facenormals.nn import load_weights

    if isinstance(paths, (str, os.PathLike)):  # one photo, not a sequence of one-letter file names
        paths = [paths]
    if isinstance(paths, (bytes, bytearray)) or not isinstance(paths, Sequence):
        raise ValueError(f"paths: expected an image file name or a sequence of them, got {type(paths).__name__}")
    if not paths:
        raise ValueError("paths: expected at least one image, got none")
    for path in paths:
        if not isinstance(path, (str, os.PathLike)):
            raise ValueError(f"paths: expected file names (str or os.PathLike), got {type(path).__name__} {path!r}")
    check_folder_name(out_dir, "out_dir")  # Path("") would write and remove files in the working folder
    check_device(device, hint="; use --device cpu")
    if out_dir is not None and Path(out_dir).exists() and not Path(out_dir).is_dir():
        raise ValueError(f"{out_dir}: the output folder exists as a file")
    for path in paths if out_dir is not None else ():
        if reconstruction_would_replace(path, out_dir):
            raise ValueError(f"{path}: this photo is in the output folder under a name the reconstruction writes or "
                             "removes; move it, or choose another output folder")
    boxes = list(boxes) if boxes is not None else [None] * len(paths)
    if len(boxes) != len(paths):
        raise ValueError(f"boxes: expected one per image ({len(paths)}), got {len(boxes)}")
    timings: dict[str, float] = {}
    start = time.perf_counter()
    # the model and the weights before the photos: a mistyped --model or --weights stops the run before
    # the detector has gone through every photo
    model_spec = None  # what load_model reloads this model from, for params.json
    fallback = False
    if not isinstance(model, MorphableModel):
        spec = model
        model = load_model(spec)
        model_spec = model.name if spec in ("auto", "ict", "builtin") else str(Path(spec).resolve())
        fallback = spec == "auto" and model.name == "builtin"
    if model.mean.dtype != torch.float32:  # the fit runs in float32; a caller's model stays as it is
        model = copy.deepcopy(model).to(torch.float32)
    model.check_millimetres()  # before the network runs: mm units, enough named landmarks, known names
    require_pose_landmarks(model)
    landmark_channels(model)
    net = load_weights(weights, device=device)
    try:  # what the weight file says about itself, before the photos are read
        if fit_weights is None:
            network_fit_weights(net)
        if mirror and net.num_landmarks != len(LANDMARK_NAMES):
            raise ValueError(f"the built-in mirror averaging needs the library's {len(LANDMARK_NAMES)} landmark "
                             f"channels, and this network predicts {net.num_landmarks} (mirror=False fits without it)")
    except ValueError as error:
        raise ValueError(f"{weights if weights is not None else 'the shipped weights'}: {error}") from None
    timings["load"] = time.perf_counter() - start

    t = time.perf_counter()
    views = []
    for i, (path, box) in enumerate(zip(paths, boxes)):
        view = prepare_view(path, box)
        views.append(view)
        log(f"[{i + 1}/{len(paths)}] {path}: {view.image_size[1]}x{view.image_size[0]}, head crop "
            f"{view.box[2]:.0f} px at ({view.box[0]:.0f}, {view.box[1]:.0f})")
    timings["read_and_detect"] = time.perf_counter() - t
    for i, view in enumerate(views):  # the same photo twice (a path repeated, or a copy) adds no viewpoint
        twin = next((j for j in range(i) if views[j].crop.shape == view.crop.shape
                     and np.array_equal(views[j].crop, view.crop)), None)
        if twin is not None:
            log(f"warning: {paths[i]} shows the same head crop as {paths[twin]}: the same photo counts twice in "
                "the multi-view fit, which then weighs that view double and adds no other viewpoint")
    if fallback:
        log("ICT-FaceKit is not installed: using the built-in head "
            "(`facenormals models fetch ict` gets the full model)")
    log(f"model {model.name} ({model.num_vertices} vertices, {model.num_shape} shape components); "
        f"network on {device}")

    t = time.perf_counter()
    views, maps = _pick_faces(views, net, model, mirror, log)
    crops = _network_input([v.crop for v in views])
    if fit_weights is not None:
        fit_options["weights"] = fit_weights
    maps, fit = reconstruct_views(crops, net, model, log=log, mirror=mirror, view_names=[str(p) for p in paths],
                                  maps=maps, **fit_options)
    timings["network"] = maps.seconds
    timings["fit"] = float(fit.timings.get("total_s", time.perf_counter() - t - maps.seconds))
    timings["reconstruct"] = time.perf_counter() - t
    rec = Reconstruction(views=views, maps=maps, fit=fit, model=model, timings=timings, model_spec=model_spec)
    if out_dir is not None:
        written = write_reconstruction(rec, out_dir)
        log(f"wrote {len(written)} files to {out_dir}: " + ", ".join(p.name for p in written))
    timings["total"] = time.perf_counter() - start
    return rec
