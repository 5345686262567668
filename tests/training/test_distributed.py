"""DDP on CPU (Gloo): two processes train one model; their weights stay identical."""

import os
import socket

import torch
import torch.multiprocessing as mp

from facenormals.training import TrainConfig, load_checkpoint, train
from facenormals.training.distributed import init_distributed

from .conftest import TinyHeads


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _worker(rank: int, world: int, port: int, out: str, results) -> None:
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port))
    torch.set_num_threads(1)
    config = TrainConfig(data="unused", out=out, steps=3, batch_size=2, workers=0, device="cpu", precision="fp32",
                         log_every=1, checkpoint_every=3, base_channels=4, depth=2)
    summary = train(config, TinyHeads(16), progress=False)
    results[rank] = (summary.samples_seen, [p.detach().clone() for p in _last_params(out)] if rank == 0 else None)


def _last_params(out: str):
    return list(load_checkpoint(os.path.join(out, "last.pt"))["model"].values())


def test_two_process_ddp_on_cpu(tmp_path):
    world, port = 2, _free_port()
    with mp.Manager() as manager:
        results = manager.dict()
        mp.spawn(_worker, args=(world, port, str(tmp_path / "run"), results), nprocs=world, join=True)
        seen = {rank: results[rank][0] for rank in range(world)}
    assert seen == {0: 12, 1: 12}  # 3 steps x 2 images x 2 processes
    state = load_checkpoint(tmp_path / "run" / "last.pt")
    assert state["world_size"] == 2 and state["samples_seen"] == 12


def test_a_bare_cuda_device_names_this_process_gpu(monkeypatch):
    # torch.cuda.set_device refuses an index-less "cuda"; init_distributed must pass cuda:LOCAL_RANK
    chosen = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "set_device", lambda device: chosen.append(torch.device(device)))
    for name in ("RANK", "WORLD_SIZE", "LOCAL_RANK"):
        monkeypatch.delenv(name, raising=False)
    assert init_distributed("cuda").device == torch.device("cuda:0")
    assert init_distributed("auto").device == torch.device("cuda:0")
    assert init_distributed("cuda:3").device == torch.device("cuda:3")
    monkeypatch.setenv("LOCAL_RANK", "2")
    assert init_distributed("cuda").device == torch.device("cuda:2")
    assert all(d.index is not None for d in chosen)
