"""Process setup for single-process and ``torchrun`` (DistributedDataParallel) training."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from facenormals.core.check import environment_integer
from facenormals.training.config import is_device_name

__all__ = ["DistContext", "init_distributed", "resolve_precision"]


@dataclass(frozen=True)
class DistContext:
    """Where this training process runs.

    Attributes:
        rank, world_size, local_rank: from ``torchrun``'s environment (``0, 1, 0`` without it).
        device: the process's device.
    """

    rank: int
    world_size: int
    local_rank: int
    device: torch.device

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def init_distributed(device: str = "auto") -> DistContext:
    """Read ``torchrun``'s ``RANK``/``WORLD_SIZE``/``LOCAL_RANK`` and join the process group.

    With ``WORLD_SIZE > 1`` the NCCL backend is used on CUDA and Gloo on CPU, and each process takes
    the GPU ``cuda:LOCAL_RANK``. Without ``torchrun`` nothing is initialised.

    Args:
        device: ``"auto"`` (CUDA when available), ``"cpu"``, ``"cuda"`` or ``"cuda:N"``.

    Raises:
        ValueError: on an unknown device, CUDA requested where there is none, or a ``RANK``,
            ``WORLD_SIZE`` or ``LOCAL_RANK`` that is not an integer or out of range
            (``WORLD_SIZE >= 1``, ``0 <= RANK < WORLD_SIZE``, ``LOCAL_RANK >= 0``).
    """
    rank, world = environment_integer("RANK", 0), environment_integer("WORLD_SIZE", 1)
    local = environment_integer("LOCAL_RANK", 0)
    # checked before anything is created: a rank outside [0, WORLD_SIZE) made no process rank 0, so
    # a run exited 0 having written nothing, and WORLD_SIZE=0 failed with a division by zero
    if world < 1:
        raise ValueError(f"$WORLD_SIZE: expected an integer >= 1, got {world}")
    if not 0 <= rank < world:
        raise ValueError(f"$RANK: expected 0 <= RANK < WORLD_SIZE={world}, got {rank}")
    if local < 0:
        raise ValueError(f"$LOCAL_RANK: expected an integer >= 0, got {local}")
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if not is_device_name(device):
        raise ValueError(f"device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got {device!r}")
    if device.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ValueError(f"device: {device!r} requested but torch has no CUDA device here "
                             f"(torch {torch.__version__}); use --device cpu")
        # a bare "cuda" names this process's GPU: torch.cuda.set_device needs an index
        dev = torch.device(f"cuda:{local}") if device == "cuda" else torch.device(device)
        torch.cuda.set_device(dev)
    else:
        dev = torch.device("cpu")
    if world > 1 and not torch.distributed.is_initialized():
        backend = "nccl" if dev.type == "cuda" else "gloo"
        torch.distributed.init_process_group(backend=backend, rank=rank, world_size=world)
    return DistContext(rank=rank, world_size=world, local_rank=local, device=dev)


def _cpu_has_bf16() -> bool:
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return "avx512_bf16" in flags or "amx_bf16" in flags


def resolve_precision(precision: str, device: torch.device) -> torch.dtype | None:
    """The autocast dtype for ``precision`` on ``device`` (``None``: plain float32)."""
    if precision == "fp32":
        return None
    if precision == "bf16":
        return torch.bfloat16
    if precision != "auto":
        raise ValueError(f"precision: expected 'auto', 'bf16' or 'fp32', got {precision!r}")
    if device.type == "cuda":
        # compute capability 8 (Ampere) or newer: is_bf16_supported() also says yes where bf16 is emulated
        return torch.bfloat16 if torch.cuda.get_device_capability(device)[0] >= 8 else None
    return torch.bfloat16 if _cpu_has_bf16() else None
