"""DDP on CPU (Gloo): two processes train one model (their weights stay identical) and stop together."""

import os
import socket
import time

import pytest
import torch
import torch.multiprocessing as mp

from facenormals.nn import NormalLandmarkUNet
from facenormals.training import TrainConfig, load_checkpoint, train
from facenormals.training.distributed import init_distributed

from .conftest import TinyHeads


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _worker(rank: int, world: int, port: int, out: str, results, max_minutes: dict) -> None:
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port))
    torch.set_num_threads(1)
    from facenormals.training import loop

    built = []

    def recording_unet(*args, **kwargs):  # keep this rank's network to compare the ranks' weights
        built.append(NormalLandmarkUNet(*args, **kwargs))
        return built[-1]

    loop.NormalLandmarkUNet = recording_unet
    config = TrainConfig(data="unused", out=out, steps=3, batch_size=2, workers=0, device="cpu", precision="fp32",
                         log_every=1, checkpoint_every=3, base_channels=4, depth=2, max_minutes=max_minutes.get(rank))
    summary = train(config, TinyHeads(16), progress=False)
    results[rank] = (summary.samples_seen, summary.step, summary.stopped_by,
                     [p.detach().clone() for p in built[0].parameters()])


def _run(world: int, out: str, max_minutes: dict | None = None, timeout: float = 240.0) -> dict:
    with mp.Manager() as manager:
        results = manager.dict()
        context = mp.spawn(_worker, args=(world, _free_port(), out, results, max_minutes or {}), nprocs=world,
                           join=False)
        deadline = time.monotonic() + timeout
        while not context.join(timeout=5):
            if time.monotonic() > deadline:  # a rank waiting for another forever
                for process in context.processes:
                    process.kill()
                pytest.fail(f"the {world} DDP processes did not finish within {timeout:.0f} s")
        return dict(results)


def test_two_process_ddp_on_cpu(tmp_path):
    results = _run(2, str(tmp_path / "run"))
    assert {rank: r[0] for rank, r in results.items()} == {0: 12, 1: 12}  # 3 steps x 2 images x 2 processes
    for a, b in zip(results[0][3], results[1][3]):  # one model: the ranks' weights are identical
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert any(not torch.equal(a, b) for a, b in zip(results[0][3], _initial_params()))  # and they did train
    state = load_checkpoint(tmp_path / "run" / "last.pt")
    assert state["world_size"] == 2 and state["samples_seen"] == 12
    torch.testing.assert_close(list(state["model"].values()), results[0][3], rtol=0, atol=0)


def test_a_stop_on_one_rank_stops_every_rank(tmp_path):
    """Rank 1 reaches its time limit at once; rank 0 has none. Both stop at the same step and rank 0
    still writes the checkpoint (before, rank 0 waited for rank 1 in the next all-reduce)."""
    results = _run(2, str(tmp_path / "run"), max_minutes={1: 1e-9})
    assert {rank: r[1:3] for rank, r in results.items()} == {0: (0, "max_minutes"), 1: (0, "max_minutes")}
    assert load_checkpoint(tmp_path / "run" / "last.pt")["step"] == 0


def _initial_params():
    torch.manual_seed(0)  # TrainConfig's default seed, as train() seeds it before building the network
    return list(NormalLandmarkUNet(base_channels=4, depth=2).parameters())


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


@pytest.mark.parametrize("capability, expected", [((7, 0), None), ((8, 0), torch.bfloat16), ((9, 0), torch.bfloat16)])
def test_auto_precision_takes_bf16_from_ampere_on(monkeypatch, capability, expected):
    """torch.cuda.is_bf16_supported() also answers yes on a V100 or T4, where bf16 is emulated (slow)."""
    from facenormals.training.distributed import resolve_precision

    monkeypatch.setattr(torch.cuda, "get_device_capability", lambda device=None: capability)
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *args, **kwargs: True)
    assert resolve_precision("auto", torch.device("cuda", 0)) is expected


def test_the_global_foreground_is_counted_as_the_loss_counts_it():
    """A soft (float) foreground counts its pixels > 0.5, as normal_landmark_loss masks them."""
    import torch.distributed as dist

    from facenormals.training.loop import _foreground_per_rank

    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{_free_port()}", rank=0, world_size=1)
    try:
        soft = torch.tensor([0.2, 0.6, 1.0, 0.5, 0.9]).view(1, 1, 1, 5)
        assert float(_foreground_per_rank(soft, 2)) == 1.5  # 3 pixels over 2 ranks
        assert float(_foreground_per_rank(soft > 0.5, 1)) == 3.0
    finally:
        dist.destroy_process_group()


@pytest.mark.parametrize("env, message", [
    ({"WORLD_SIZE": "0"}, r"\$WORLD_SIZE: expected an integer >= 1, got 0"),
    ({"RANK": "3", "WORLD_SIZE": "1"}, r"\$RANK: expected 0 <= RANK < WORLD_SIZE=1, got 3"),
    ({"RANK": "-1"}, r"\$RANK: expected 0 <= RANK < WORLD_SIZE=1, got -1"),
    ({"RANK": "2", "WORLD_SIZE": "2"}, r"\$RANK: expected 0 <= RANK < WORLD_SIZE=2, got 2"),
    ({"LOCAL_RANK": "-2"}, r"\$LOCAL_RANK: expected an integer >= 0, got -2"),
])
def test_a_rank_or_world_size_out_of_range_is_refused_before_anything_is_written(monkeypatch, tmp_path, capsys,
                                                                                 env, message):
    """RANK=3 WORLD_SIZE=1 or RANK=-1 made no process rank 0: the run exited 0 having written
    nothing; WORLD_SIZE=0 failed with a division by zero and left an empty --out folder."""
    from facenormals.cli import main

    for name in ("RANK", "WORLD_SIZE", "LOCAL_RANK"):
        monkeypatch.delenv(name, raising=False)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    with pytest.raises(ValueError, match=message):
        init_distributed("cpu")
    out = tmp_path / "run"
    config = TrainConfig(data="unused", out=str(out), steps=1, batch_size=2, workers=0, device="cpu",
                         precision="fp32", base_channels=4, depth=2)
    with pytest.raises(ValueError, match=message):
        train(config, TinyHeads(8), progress=False)
    assert not out.exists()
    assert main(["train", "--data", str(tmp_path), "--out", str(out), "--device", "cpu", "--quiet"]) == 1
    assert f"facenormals train: error: {message.replace(chr(92), '')}" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("device", ["cudafoo", "cuda:x", "cuda:-1", "cuda:", "gpu", 3])
def test_init_distributed_takes_only_the_documented_devices(device):
    with pytest.raises(ValueError, match="device: expected 'auto', 'cpu', 'cuda' or 'cuda:N'"):
        init_distributed(device)
