"""The 24 landmarks sit on the right anatomy, on ICT-FaceKit and on the built-in head."""

import numpy as np
import pytest

from facenormals.models import LANDMARK_NAMES, LANDMARK_PAIRS, builtin_head_model, load_ict_npz
from facenormals.models.landmarks import ICT_EAR_VERTICES, ict_landmark_indices

EARS = [n for n in LANDMARK_NAMES if "_ear_" in n]


def check_anatomy(model):
    assert list(model.landmarks) == list(LANDMARK_NAMES)
    P = model.mean.double().numpy()
    lm = {name: P[index] for name, index in model.landmarks.items()}
    # the frontal mean head looks along -z: the nose tip is the most forward landmark
    assert min(lm, key=lambda n: lm[n][2]) == "nose_tip"
    # paired landmarks mirror each other across the mid-sagittal plane x = 0 within 2 mm
    for right, left in LANDMARK_PAIRS:
        assert np.linalg.norm(lm[right] - lm[left] * np.array([-1.0, 1.0, 1.0])) < 2.0, (right, left)
        assert lm[right][0] < 0 < lm[left][0], (right, left)  # the subject's right is image left
    # the ear points are the most lateral
    assert min(abs(lm[n][0]) for n in EARS) > max(abs(lm[n][0]) for n in LANDMARK_NAMES if n not in EARS)
    # top to bottom (y down): brows, eyes, nose tip, upper lip, lower lip, chin; ear top above the lobe
    order = ["right_brow_center", "right_eye_outer", "nose_tip", "upper_lip", "lower_lip", "chin"]
    assert [lm[n][1] for n in order] == sorted(lm[n][1] for n in order)
    assert lm["right_ear_top"][1] < lm["right_ear_tragus"][1] < lm["right_ear_lobe"][1]
    # midline points lie on the mid-sagittal plane
    for name in ("nose_bridge", "nose_tip", "subnasale", "upper_lip", "lower_lip", "chin"):
        assert abs(lm[name][0]) < 1.0, name


def test_ict_anatomy(ict_npz):
    check_anatomy(load_ict_npz(ict_npz))


def test_builtin_anatomy():
    check_anatomy(builtin_head_model())


def test_ict_landmark_indices():
    ibug = list(range(1000, 1068))
    out = ict_landmark_indices(ibug)
    assert out["nose_tip"] == 1030 and out["chin"] == 1008 and out["right_eye_outer"] == 1036
    assert {k: out[k] for k in ICT_EAR_VERTICES} == ICT_EAR_VERTICES
    with pytest.raises(ValueError, match="ibug68: expected 68"):
        ict_landmark_indices(ibug[:10])


def test_ear_script_reproduces_the_hard_coded_indices(ict_npz):
    """``python scripts/ict_ear_landmarks.py ARCHIVE``, run as docs/models.md says, prints them."""
    import re
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    run = subprocess.run([sys.executable, "scripts/ict_ear_landmarks.py", str(ict_npz)], cwd=root,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    printed = {name: int(index) for name, index in re.findall(r'"(\w+_ear_\w+)": (\d+)', run.stdout)}
    assert printed == ICT_EAR_VERTICES
