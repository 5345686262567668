"""Training the normal + landmark network on synthetic data (CPU, CUDA, ``torchrun``/DDP), its metrics and weights.

See ``docs/tutorials/train.md`` and ``docs/model_card.md``.
"""

from facenormals.training.checkpoint import export_weights, load_checkpoint, save_checkpoint
from facenormals.training.config import TrainConfig
from facenormals.training.loop import TrainSummary, train
from facenormals.training.metrics import (
    NetworkMetrics,
    calibrate_landmark_threshold,
    evaluate_network,
    landmark_threshold,
    normal_angles,
)

__all__ = [
    "NetworkMetrics",
    "TrainConfig",
    "TrainSummary",
    "calibrate_landmark_threshold",
    "evaluate_network",
    "export_weights",
    "landmark_threshold",
    "load_checkpoint",
    "normal_angles",
    "save_checkpoint",
    "train",
]
