"""Pick the six ear landmarks of ICT-FaceKit by a rerunnable geometric criterion.

The auricle is the part of the head that stands out sideways behind the jaw line. Per side:

1. the **ear region** is the connected set of vertices (mesh edges) around the most lateral vertex
   between eye level and the mouth, whose distance from the mid-sagittal plane exceeds the halfway
   jaw-line landmark at the ear (iBUG 0 / 16) plus 30 % of the way to that vertex, and above the
   mouth corners;
2. **ear_top** (superaurale) is the region's highest vertex, **ear_lobe** (subaurale) its lowest,
   and **ear_tragus** its most anterior vertex between 40 % and 75 % of the ear's height (the
   tragus sits in front of the ear canal, below the helix root).

Run from the repository root; prints the indices that `facenormals.models.landmarks` hard-codes:

    python scripts/ict_ear_landmarks.py [path/to/ict_face_head.npz]
"""

from __future__ import annotations

import sys

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph

from facenormals.models import load_model
from facenormals.models.ict import load_ict_npz


def ear_landmarks(mean: np.ndarray, faces: np.ndarray, ibug68: list[int]) -> dict[str, int]:
    """The six ear landmarks from the mean shape, its faces and the 68 iBUG vertex indices."""
    n = len(mean)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    x, y, z = mean.T  # model frame: x to image right, y down, face along -z
    eye_y = mean[ibug68[36], 1]
    mouth_y = mean[ibug68[48], 1]
    out = {}
    for tag, sign, jaw in (("right", -1.0, 0), ("left", 1.0, 16)):
        lateral = sign * x
        band = (y > eye_y - 30.0) & (y < mouth_y) & (lateral > 0)
        apex = int(np.argmax(np.where(band, lateral, -np.inf)))
        threshold = lateral[ibug68[jaw]] + 0.3 * (lateral[apex] - lateral[ibug68[jaw]])
        keep = (lateral > threshold) & (y < mouth_y)
        e = edges[keep[edges[:, 0]] & keep[edges[:, 1]]]
        graph = scipy.sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
        _, labels = scipy.sparse.csgraph.connected_components(graph, directed=False)
        region = np.nonzero(keep & (labels == labels[apex]))[0]
        top = region[np.argmin(y[region])]
        lobe = region[np.argmax(y[region])]
        height = y[lobe] - y[top]
        middle = region[(y[region] > y[top] + 0.4 * height) & (y[region] < y[top] + 0.75 * height)]
        tragus = middle[np.argmin(z[middle])]
        out[f"{tag}_ear_top"], out[f"{tag}_ear_lobe"], out[f"{tag}_ear_tragus"] = int(top), int(lobe), int(tragus)
        print(f"{tag}: region of {len(region)} vertices beyond |x| = {threshold:.1f} mm; "
              f"height {y[lobe] - y[top]:.1f} mm")
    return out


def main() -> None:
    model = load_ict_npz(sys.argv[1]) if len(sys.argv) > 1 else load_model("ict")
    picks = ear_landmarks(model.mean.numpy(), model.faces.numpy(), model.metadata["landmarks_ibug68"])
    for name, index in picks.items():
        print(f'    "{name}": {index},  # {np.round(model.mean[index].numpy(), 1).tolist()}')


if __name__ == "__main__":
    main()
