"""The paper's 24 landmarks: eyes, brows, nose, mouth, chin, jaw and ears.

"right" and "left" are the subject's: the subject's right eye appears on the image's left in a
frontal view (negative x in the model frame).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

__all__ = [
    "IBUG68_OF_LANDMARK",
    "ICT_EAR_VERTICES",
    "LANDMARK_NAMES",
    "LANDMARK_PAIRS",
    "builtin_landmark_indices",
    "ict_landmark_indices",
]

#: The 24 landmark names, in channel order of the landmark map Z.
LANDMARK_NAMES: tuple[str, ...] = (
    "right_eye_outer", "right_eye_inner", "left_eye_inner", "left_eye_outer",
    "right_brow_center", "left_brow_center",
    "nose_bridge", "nose_tip", "right_alar", "left_alar", "subnasale",
    "right_mouth_corner", "left_mouth_corner", "upper_lip", "lower_lip",
    "chin", "right_jaw_angle", "left_jaw_angle",
    "right_ear_top", "right_ear_lobe", "right_ear_tragus",
    "left_ear_top", "left_ear_lobe", "left_ear_tragus",
)  # fmt: skip

#: The landmarks that exist in the 68-point iBUG / multi-PIE scheme (0-based index); ears do not.
IBUG68_OF_LANDMARK: dict[str, int] = {
    "right_eye_outer": 36, "right_eye_inner": 39, "left_eye_inner": 42, "left_eye_outer": 45,
    "right_brow_center": 19, "left_brow_center": 24,
    "nose_bridge": 27, "nose_tip": 30, "right_alar": 31, "left_alar": 35, "subnasale": 33,
    "right_mouth_corner": 48, "left_mouth_corner": 54, "upper_lip": 51, "lower_lip": 57,
    "chin": 8, "right_jaw_angle": 3, "left_jaw_angle": 13,
}  # fmt: skip


#: ICT-FaceKit ear vertices, picked by ``scripts/ict_ear_landmarks.py`` (rerun it to reproduce them):
#: the highest, lowest and most anterior mid-height vertex of the auricle, found as the connected
#: region standing out sideways behind the jaw line.
ICT_EAR_VERTICES: dict[str, int] = {
    "right_ear_top": 7571, "right_ear_lobe": 7472, "right_ear_tragus": 7547,
    "left_ear_top": 6844, "left_ear_lobe": 6745, "left_ear_tragus": 6820,
}  # fmt: skip


def ict_landmark_indices(ibug68: Sequence[int]) -> dict[str, int]:
    """The 24 landmarks of ICT-FaceKit: iBUG points where they exist, the scripted ear vertices otherwise."""
    if len(ibug68) != 68:
        raise ValueError(f"ibug68: expected 68 vertex indices, got {len(ibug68)}")
    out = {name: int(ibug68[i]) for name, i in IBUG68_OF_LANDMARK.items()}
    out.update(ICT_EAR_VERTICES)
    return {name: out[name] for name in LANDMARK_NAMES}


def _mirror_pairs(names: Sequence[str]) -> list[tuple[str, str]]:
    return [(n, "left_" + n[len("right_"):]) for n in names if n.startswith("right_")]


#: Bilaterally symmetric pairs (right, left).
LANDMARK_PAIRS: tuple[tuple[str, str], ...] = tuple(_mirror_pairs(LANDMARK_NAMES))


def _nearest(points: np.ndarray, candidates: np.ndarray, target: Sequence[float], axes: Sequence[int]) -> int:
    """Index of the candidate vertex whose coordinates ``axes`` are nearest to ``target``."""
    index = np.nonzero(candidates)[0]
    d = sum((points[index, a] - t) ** 2 for a, t in zip(axes, target))
    return int(index[np.argmin(d)])


def builtin_landmark_indices(mean: np.ndarray, parameters) -> dict[str, int]:
    """Landmark vertices of the built-in head, from the analytic positions of its features.

    Front landmarks are the front-facing vertices nearest to the feature's (x, up) position; ear
    points are the outermost vertices nearest to the ear's (up, forward) outline points.
    """
    p = {spec.name: spec.mean for spec in parameters}
    x, up, fwd = mean[:, 0], -mean[:, 1], -mean[:, 2]
    front = fwd > 0.5 * np.percentile(fwd, 99)
    eye_x = 0.5 * p["eye_separation"]
    tip_u = -p["nose_length"] + 8.0
    mouth_u = -p["mouth_level"]
    out: dict[str, int] = {}
    for side, tag in ((-1.0, "right"), (1.0, "left")):
        out[f"{tag}_eye_outer"] = _nearest(mean, front, (side * (eye_x + 14.0), 0.0), (0, 1))
        out[f"{tag}_eye_inner"] = _nearest(mean, front, (side * (eye_x - 14.0), 0.0), (0, 1))
        out[f"{tag}_brow_center"] = _nearest(mean, front, (side * (eye_x - 2.0), -16.0), (0, 1))
        out[f"{tag}_alar"] = _nearest(mean, front, (side * 0.375 * p["nose_width"], -(tip_u + 3.0)), (0, 1))
        out[f"{tag}_mouth_corner"] = _nearest(mean, front, (side * 0.5 * p["mouth_width"], -mouth_u), (0, 1))
        lateral = side * x > 0.2 * p["head_breadth"]
        jaw_u = -p["face_height"] + 38.0
        band = lateral & (np.abs(up - jaw_u) < 4.0) & (fwd > -10.0) & (fwd < 40.0)
        out[f"{tag}_jaw_angle"] = int(np.nonzero(band)[0][np.argmax(side * x[band])])
        ear = side * x > 0.45 * p["head_breadth"]
        half_len = 0.5 * p["ear_length"]
        ear_u, ear_f = -p["ear_level"], -p["ear_position"]
        out[f"{tag}_ear_top"] = _nearest(mean, ear, (-(ear_u + 0.85 * half_len), -ear_f), (1, 2))
        out[f"{tag}_ear_lobe"] = _nearest(mean, ear, (-(ear_u - 0.85 * half_len), -ear_f), (1, 2))
        out[f"{tag}_ear_tragus"] = _nearest(mean, ear, (-(ear_u - 0.1 * half_len), -(ear_f + 0.8 * 0.55 * half_len)), (1, 2))
    out["nose_bridge"] = _nearest(mean, front, (0.0, -4.0), (0, 1))
    out["nose_tip"] = int(np.argmax(np.where(np.abs(x) < 0.5, fwd, -np.inf)))
    out["subnasale"] = _nearest(mean, front & (np.abs(x) < 3.0) & (up < tip_u - 4.0), (0.0, -(tip_u - 9.0)), (0, 1))
    out["upper_lip"] = _nearest(mean, front, (0.0, -(mouth_u + 5.0)), (0, 1))
    out["lower_lip"] = _nearest(mean, front, (0.0, -(mouth_u - 6.0)), (0, 1))
    out["chin"] = _nearest(mean, front, (0.0, p["face_height"] - 18.0), (0, 1))
    return {name: out[name] for name in LANDMARK_NAMES}
