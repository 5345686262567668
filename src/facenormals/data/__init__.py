"""Synthetic training data: rendered heads with exact normal maps, landmarks and ground truth.

Importing this package imports no OpenGL; the renderer selects a headless platform (EGL, else
OSMesa) when it is first created. See ``docs/synthetic_data.md``.
"""

from facenormals.data.augment import PhotoAugmentation
from facenormals.data.backgrounds import random_background
from facenormals.data.dataset import SyntheticHeadDataset
from facenormals.data.generator import SynthBatch, SynthConfig, SyntheticHeadGenerator
from facenormals.data.landmark_maps import landmark_maps, landmarks_from_maps
from facenormals.data.raycast import blocked_rays
from facenormals.data.gl_platform import HeadlessGLError, select_gl_platform
from facenormals.data.scene import HEAD_LABELS, LABELS
from facenormals.data.shards import SynthSummary, read_manifest, write_dataset

__all__ = [
    "HEAD_LABELS",
    "HeadlessGLError",
    "LABELS",
    "PhotoAugmentation",
    "SynthBatch",
    "SynthConfig",
    "SynthSummary",
    "SyntheticHeadDataset",
    "SyntheticHeadGenerator",
    "blocked_rays",
    "landmark_maps",
    "landmarks_from_maps",
    "random_background",
    "read_manifest",
    "select_gl_platform",
    "write_dataset",
]
