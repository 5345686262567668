"""Training the normal + landmark network on synthetic data (CPU, CUDA, ``torchrun``/DDP), its metrics and weights.

See ``docs/tutorials/train.md`` and ``docs/model_card.md``. The names load on first use (PEP 562), so
that ``facenormals.training.config`` (what ``facenormals --help`` reads) imports without torch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from facenormals._lazy import lazy_names

#: each name and the module it comes from
_SOURCES = {
    "NetworkMetrics": "metrics",
    "TrainConfig": "config",
    "TrainSummary": "loop",
    "calibrate_landmark_threshold": "metrics",
    "evaluate_network": "metrics",
    "export_weights": "checkpoint",
    "landmark_threshold": "metrics",
    "load_checkpoint": "checkpoint",
    "normal_angles": "metrics",
    "save_checkpoint": "checkpoint",
    "train": "loop",
}

__all__ = [  # the keys of _SOURCES, spelt out for linters
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


__getattr__, __dir__ = lazy_names(__name__, _SOURCES, globals())

if TYPE_CHECKING:  # type checkers and editors do not run __getattr__
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
