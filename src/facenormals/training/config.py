"""Configuration of a training run of :class:`~facenormals.nn.NormalLandmarkUNet`."""

from __future__ import annotations

import dataclasses
import math
import numbers
import os
import re
from dataclasses import dataclass
from pathlib import Path

__all__ = ["TrainConfig"]


#: The most DataLoader workers a config takes (each is a process): 99,999 exhausted the memory of the
#: machine running it; 256 is far above the 1-14 the recipe has been run with.
MAX_WORKERS = 256

#: The largest peak learning rate a config takes: the recipe uses 2e-3 and AdamW steps of ~lr per
#: weight diverge far below this; 1e38 was accepted and failed at the first step with a float
#: overflow that named no option.
MAX_LR = 1e4

#: The narrowest landmark Gaussian a config takes, in pixels: below it the target maps do not decode
#: to their own points (``landmarks_from_maps`` is 0.2-0.4 px off at sigma 0.2-0.4, loses peaks under
#: its threshold below 0.3, and at 1e-9 every map is 0), so the network would learn blank or biased maps.
MIN_SIGMA = 0.5

#: Settings that shape the optimisation: a resume that changes one says so (``steps``, ``data``,
#: ``seed`` and ``batch_size`` have their own notes or are meant to change), and ``facenormals train``
#: takes them from the checkpoint unless its command line gives them.
RESUMED_SETTINGS = ("lr", "warmup_steps", "min_lr_ratio", "weight_decay", "ema_decay", "landmark_weight",
                    "landmark_peak_weight", "foreground_weight", "sigma", "precision")
#: The network's shape: a resume must keep it (another is refused), so ``facenormals train`` takes it
#: from the checkpoint too unless its command line gives it.
ARCHITECTURE_SETTINGS = ("base_channels", "depth")


#: The device names training takes besides "auto": "cpu", "cuda" or "cuda:N".
_DEVICE_NAME = re.compile(r"cpu|cuda(:[0-9]+)?")


def is_device_name(value: object) -> bool:
    """``value`` is ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` (what "auto" resolves to, or names)."""
    return isinstance(value, str) and _DEVICE_NAME.fullmatch(value) is not None


def _is_real(value: object) -> bool:
    """A plain real number (``bool`` is not one, nor a string)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


@dataclass
class TrainConfig:
    r"""Everything that defines a training run (stored in every checkpoint).

    The defaults are the project's recipe for a 2-core CPU or one GPU; ``docs/model_card.md``
    compares it with the paper's (RMSprop, learning rate 1e-5, batch 32, ~3,000 epochs).

    Attributes:
        data: training dataset folder written by ``facenormals synth``.
        out: run folder: ``last.pt`` (checkpoint), ``log.csv``, ``eval.csv``.
        holdout: held-out dataset folder scored every ``eval_every`` steps (optional).
        steps: optimiser steps in the whole run (the learning-rate schedule spans them).
        batch_size: images per step *per process* (DDP multiplies it by the world size).
        lr: peak AdamW learning rate (at most ``MAX_LR``, 1e4), reached after ``warmup_steps``
            linear steps, then a cosine decay to ``min_lr_ratio * lr`` at ``steps``.
        weight_decay: AdamW's decoupled weight decay.
        ema_decay: decay of the exponential moving average of the weights that is evaluated and
            exported (an "anytime" model: good even if the run is stopped early).
        landmark_weight: :math:`w_Z` of the loss. The paper's :math:`L_N + L_Z` sums the two
            unweighted; with :math:`L_Z` averaged over all ``L·H·W`` entries, most of them zero,
            :math:`L_Z` is orders of magnitude smaller than :math:`L_N`, so it is scaled up (100
            with ``landmark_peak_weight = 200`` gives the two terms similar magnitudes early on).
        landmark_peak_weight: :math:`\alpha` of :func:`~facenormals.nn.normal_landmark_loss`: pixels
            under the landmark Gaussians weigh ``1 + α·Z`` (0: the paper's plain squared error, which
            learned nothing but empty maps in the first 2,000 steps of our CPU run).
        foreground_weight: weight of the foreground cross-entropy (our addition).
        sigma: landmark Gaussian standard deviation in pixels, at least :data:`MIN_SIGMA`.
        workers: DataLoader worker processes per training process (at most ``MAX_WORKERS``, 256).
        device: ``"auto"`` (CUDA if available), ``"cpu"``, ``"cuda"`` or ``"cuda:N"``.
        precision: ``"bf16"`` (autocast), ``"fp32"`` or ``"auto"`` (bf16 where the hardware has
            native bf16: CUDA compute capability ≥ 8, or a CPU with AVX512-BF16/AMX).
        threads: torch intra-op threads on CPU (``None``: torch's default).
        seed: seed of the data order, the augmentation and the initial weights.
        log_every, checkpoint_every, eval_every: intervals in steps.
        eval_samples: held-out samples scored at each evaluation (all at the end of the run).
        max_minutes: stop cleanly (with a checkpoint) after this wall time; resume later.
        base_channels, depth: the network's width and depth.
        init: a weight file (:func:`~facenormals.training.export_weights`) whose weights start a
            new run, both the trained and the averaged copy (fine-tuning, or a new schedule on
            other hardware); its architecture must match. Ignored when ``out/last.pt`` exists.
    """

    data: str
    out: str
    holdout: str | None = None
    steps: int = 12000
    batch_size: int = 32
    lr: float = 2e-3
    warmup_steps: int = 200
    min_lr_ratio: float = 0.05
    weight_decay: float = 1e-4
    ema_decay: float = 0.999
    landmark_weight: float = 100.0
    landmark_peak_weight: float = 200.0
    foreground_weight: float = 1.0
    sigma: float = 1.5
    workers: int = 1
    device: str = "auto"
    precision: str = "auto"
    threads: int | None = None
    seed: int = 0
    log_every: int = 25
    checkpoint_every: int = 250
    eval_every: int = 1000
    eval_samples: int = 256
    max_minutes: float | None = None
    base_channels: int = 16
    depth: int = 5
    init: str | None = None

    def __post_init__(self) -> None:
        self._normalise_types()
        if Path(self.out).exists() and not Path(self.out).is_dir():
            raise ValueError(f"out: {self.out} exists and is not a folder")
        for name in ("steps", "batch_size", "log_every", "checkpoint_every", "eval_every", "eval_samples",
                     "base_channels", "depth"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name}: expected a positive integer, got {value!r}")
        for name in ("warmup_steps", "workers", "seed"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ValueError(f"{name}: expected a non-negative integer, got {value!r}")
        if self.workers > MAX_WORKERS:  # each is a process with its own copy of the dataset's state
            raise ValueError(f"workers: expected at most {MAX_WORKERS} DataLoader worker processes, got {self.workers}")
        if self.seed >= 1 << 63:  # torch's generators take seeds below 2**64; the derived ones stay below 2**63
            raise ValueError(f"seed: expected an integer below 2**63, got {self.seed}")
        for names, positive in ((("lr", "sigma"), True),
                                (("weight_decay", "landmark_weight", "landmark_peak_weight", "foreground_weight"), False)):
            for name in names:
                value = getattr(self, name)
                if not (_is_real(value) and math.isfinite(value) and (value > 0 if positive else value >= 0)):
                    raise ValueError(f"{name}: expected a finite {'positive' if positive else 'non-negative'} value, "
                                     f"got {value!r}")
        if self.sigma < MIN_SIGMA:
            raise ValueError(f"sigma: expected a landmark Gaussian of at least {MIN_SIGMA:g} px (narrower target "
                             f"maps do not decode to their own points), got {self.sigma!r}")
        if self.lr > MAX_LR:
            raise ValueError(f"lr: expected a learning rate of at most {MAX_LR:g}, got {self.lr!r}")
        if not (_is_real(self.ema_decay) and 0.0 <= self.ema_decay < 1.0):
            raise ValueError(f"ema_decay: expected a value in [0, 1), got {self.ema_decay!r}")
        if not (_is_real(self.min_lr_ratio) and 0.0 <= self.min_lr_ratio <= 1.0):
            raise ValueError(f"min_lr_ratio: expected a value in [0, 1], got {self.min_lr_ratio!r}")
        if not (is_device_name(self.device) or (isinstance(self.device, str) and self.device == "auto")):
            raise ValueError(f"device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got {self.device!r}")
        if self.precision not in ("auto", "bf16", "fp32"):
            raise ValueError(f"precision: expected 'auto', 'bf16' or 'fp32', got {self.precision!r}")
        if self.threads is not None and (not isinstance(self.threads, int) or isinstance(self.threads, bool)
                                         or self.threads < 1):
            raise ValueError(f"threads: expected a positive integer or None, got {self.threads!r}")
        if self.max_minutes is not None and not (_is_real(self.max_minutes) and 0 < self.max_minutes < math.inf):
            raise ValueError(f"max_minutes: expected a finite positive value or None (no limit), got {self.max_minutes!r}")

    def _normalise_types(self) -> None:
        """Paths become ``str``, NumPy (or other) integers and reals plain ``int`` and ``float``: the
        config is stored in every checkpoint, which is read back with ``weights_only=True`` and
        accepts only plain Python values (a ``pathlib.Path`` there made a checkpoint unreadable)."""
        for field in dataclasses.fields(self):
            name, value = field.name, getattr(self, field.name)
            if value is None or isinstance(value, bool):
                continue
            if name in ("data", "out", "holdout", "init"):
                if not isinstance(value, (str, os.PathLike)):
                    raise ValueError(f"{name}: expected a path (str or os.PathLike), got {type(value).__name__}")
                if not os.fspath(value):  # e.g. an unset $OUT: Path("") is the current folder
                    raise ValueError(f"{name}: expected a folder or file name, got an empty string")
                setattr(self, name, os.fspath(value))
            elif field.type in ("int", "int | None") and isinstance(value, numbers.Integral):
                setattr(self, name, int(value))
            elif field.type in ("float", "float | None") and isinstance(value, numbers.Real):
                setattr(self, name, float(value))

    def learning_rate(self, step: int) -> float:
        """The learning rate of optimiser step ``step`` (0-based): linear warm-up, then cosine decay."""
        if step < self.warmup_steps:
            return self.lr * (step + 1) / self.warmup_steps
        span = max(1, self.steps - self.warmup_steps)
        progress = min(1.0, (step - self.warmup_steps) / span)
        floor = self.min_lr_ratio * self.lr
        return floor + (self.lr - floor) * 0.5 * (1.0 + math.cos(math.pi * progress))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> "TrainConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"config: unknown fields {unknown}")
        return cls(**values)
