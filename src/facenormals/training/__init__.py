"""Training the normal + landmark network on synthetic data (CPU, CUDA, ``torchrun``/DDP), its metrics and weights.

See ``docs/tutorials/train.md`` and ``docs/model_card.md``.
"""

from facenormals.training.checkpoint import export_weights, load_checkpoint, save_checkpoint
from facenormals.training.config import TrainConfig
from facenormals.training.loop import TrainSummary, train
from facenormals.training.metrics import NetworkMetrics, evaluate_network, normal_angles

__all__ = [
    "NetworkMetrics",
    "TrainConfig",
    "TrainSummary",
    "evaluate_network",
    "export_weights",
    "load_checkpoint",
    "normal_angles",
    "save_checkpoint",
    "train",
]
