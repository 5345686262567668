r"""The training loop: resumable, logged, on CPU or CUDA, single-process or under ``torchrun`` (DDP).

One optimiser step takes ``batch_size`` samples per process in a deterministic order (a fresh
permutation of the dataset per epoch from ``(seed, epoch)``, dealt round-robin to the ranks), so a
run resumed from ``last.pt`` continues exactly where it stopped. The landmark maps are rasterised
per batch on the training device and the paper's blur + noise augmentation runs there too.
"""

from __future__ import annotations

import contextlib
import copy
import csv
import io
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset, Sampler

from facenormals.core.files import PART, atomic_write, hold_locks
from facenormals.data.augment import PhotoAugmentation
from facenormals.data.landmark_maps import landmark_maps
from facenormals.nn.loss import _foreground_pixel_mask, normal_landmark_loss
from facenormals.nn.unet import NormalLandmarkUNet, UNetOutput
from facenormals.training.checkpoint import load_checkpoint, save_checkpoint
from facenormals.training.config import ARCHITECTURE_SETTINGS, RESUMED_SETTINGS, TrainConfig
from facenormals.training.distributed import init_distributed, resolve_precision
from facenormals.training.metrics import NetworkMetrics, evaluate_network

__all__ = ["TrainSummary", "train"]

#: The lock file of a run folder, held by the process that writes it (rank 0).
LOCK = ".train.lock"
_LOG_FIELDS = ["step", "epoch", "samples_seen", "loss", "normals", "landmarks", "foreground", "lr",
               "images_per_s", "elapsed_s"]
_EVAL_FIELDS = ["step", "samples_seen"] + list(NetworkMetrics.__dataclass_fields__)


@dataclass
class TrainSummary:
    """What :func:`train` did.

    Attributes:
        step: optimiser steps completed in the whole run (including earlier sessions).
        samples_seen: training samples consumed in the whole run, over all processes.
        finished: ``step == config.steps``.
        stopped_by: ``"steps"``, ``"max_minutes"`` or ``"signal"``.
        seconds: wall time of this call.
        metrics: the last held-out evaluation (``None`` without a holdout).
        checkpoint: path of ``last.pt``.
    """

    step: int
    samples_seen: int
    finished: bool
    stopped_by: str
    seconds: float
    metrics: NetworkMetrics | None
    checkpoint: Path


def _derived_seed(seed: int, counter: int, world_size: int = 1, rank: int = 0) -> int:
    """The seed of epoch or step ``counter`` (and rank): below 2**63, which torch accepts, for any seed."""
    return ((seed * 1_000_003 + counter) * world_size + rank) % (1 << 63)


class _EpochSampler(Sampler[int]):
    """Endless, deterministic sample order: per-epoch permutations from ``(seed, epoch)``, split by rank."""

    def __init__(self, size: int, seed: int, rank: int, world_size: int, start: int = 0) -> None:
        self.size, self.seed, self.rank, self.world = size, seed, rank, world_size
        self.per_rank = size // world_size
        if self.per_rank == 0:
            raise ValueError(f"data: {size} samples cannot be split over {world_size} processes")
        self.start = start  # samples of this rank already consumed

    def __iter__(self) -> Iterator[int]:
        epoch, offset = divmod(self.start, self.per_rank)
        while True:
            g = torch.Generator().manual_seed(_derived_seed(self.seed, epoch))
            order = torch.randperm(self.size, generator=g)[self.rank : self.per_rank * self.world : self.world]
            yield from order[offset:].tolist()
            epoch, offset = epoch + 1, 0


def _open_dataset(root: str, config: TrainConfig, with_maps: bool) -> Dataset:
    from facenormals.data.dataset import SyntheticHeadDataset

    return SyntheticHeadDataset(root, sigma=config.sigma, with_landmark_maps=with_maps)


def _append_csv(path: Path, fields: list[str], row: dict) -> None:
    new = not path.exists() or path.stat().st_size == 0  # a run killed before its first row was flushed
    with path.open("a", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields)
        if new:
            writer.writeheader()
        writer.writerow({k: row[k] for k in fields})


def _read_rows(path: Path) -> list[dict]:
    """The rows of a CSV log (none if it does not exist)."""
    if not path.exists():
        return []
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def _logged_step(path: Path, row: dict, line: int) -> int:
    try:
        return int(row["step"])
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{path}: line {line}: expected a training log row with an integer step, got "
                         f"{row.get('step')!r}; move the file away or choose another --out") from None


def _truncate_csv(path: Path, step: int, fields: list[str]) -> None:
    """Drop the rows logged after ``step`` (a run that died after its last checkpoint repeats them).

    A log written before a column was added gets the current header (its rows leave the new columns
    empty), so that rows appended now line up; a file that is no log of ours is an error naming it,
    rather than rows appended under a foreign header. A last line without its line end was cut off
    by a kill in the middle of a write: it is dropped (appending would have run the next row into it)."""
    if not path.exists():
        return
    with path.open(newline="") as handle:
        text = handle.read()
    torn = bool(text) and not text.endswith("\n")
    if torn and "\n" not in text:  # not even the header was written whole: a log like none
        path.unlink()
        return
    reader = csv.DictReader(io.StringIO(text[:text.rindex("\n") + 1] if torn else text, newline=""))
    rows, header = list(reader), reader.fieldnames
    if header is None:  # empty: a run killed before its first row was flushed
        return
    if "step" not in header or not set(header) <= set(fields):
        raise ValueError(f"{path}: not a facenormals training log (columns {header}, expected {fields}); move "
                         "the file away or choose another --out")
    kept = [r for line, r in enumerate(rows, start=2) if _logged_step(path, r, line) <= step]
    if torn or len(kept) != len(rows) or header != fields:  # rewritten beside and renamed over it: an error leaves the old log
        with atomic_write(path) as part, part.open("w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=fields, restval="")
            writer.writeheader()
            writer.writerows(kept)


def _last_logged_step(path: Path) -> int | None:
    rows = _read_rows(path)
    return _logged_step(path, rows[-1], len(rows) + 1) if rows else None


def _check_holdout_is_not_training_data(dataset: Dataset, holdout: str) -> None:
    """Refuse a held-out folder that is the training folder, or whose samples are training samples:
    rendered with the same seed, generator and model, sample ``i`` of both is the same head."""
    from facenormals.data.shards import read_manifest

    held = read_manifest(holdout)
    root, train = getattr(dataset, "root", None), getattr(dataset, "manifest", None)
    if root is not None and Path(holdout).resolve() == Path(root).resolve():
        raise ValueError(f"holdout: {holdout} is the training data folder; render a held-out set with another "
                         "--seed (e.g. `facenormals synth --seed 1`)")
    if isinstance(train, dict) and all(train.get(key) == held.get(key) for key in ("seed", "generator", "model")):
        raise ValueError(f"holdout: {holdout} was rendered with the training data's seed {train.get('seed')}, "
                         f"generator and model: its samples are samples of the training data {root}; render the "
                         "held-out set with another --seed")


def _foreground_per_rank(foreground: Tensor, world_size: int) -> Tensor:
    """The global batch's foreground pixels (counted as the loss counts them) divided by the number
    of processes: each rank's L_N divided by it averages, over the ranks, to the global batch's L_N."""
    count = _foreground_pixel_mask(foreground).sum(dtype=torch.float32)
    torch.distributed.all_reduce(count)
    return count / world_size


def _image_size(dataset: Dataset) -> tuple[int, int]:
    """``(H, W)`` of the training images: the dataset's ``image_size``, else its first image's."""
    size = getattr(dataset, "image_size", None)
    return (size, size) if isinstance(size, int) else tuple(int(n) for n in dataset[0]["image"].shape[-2:])


def _check_depth_fits_the_images(image_size: tuple[int, int], depth: int) -> None:
    """Refuse, before the run folder exists, a network that halves the images more often than their size allows."""
    height, width = image_size
    if height % (1 << depth) or width % (1 << depth):
        raise ValueError(f"depth: {depth} stride-2 levels need images whose sides are divisible by 2**{depth} = "
                         f"{1 << depth}; the training images are {height}x{width} pixels")


def _note_changed_settings(stored: dict, config: TrainConfig, last: Path) -> None:
    for key in RESUMED_SETTINGS:
        if key not in stored:  # a checkpoint older than the setting
            continue
        old, new = stored[key], getattr(config, key)
        if old != new:
            print(f"note: resuming {last} with {key} {new} (checkpoint: {old}); the run goes on with the new "
                  f"value (set {key} = {old} again, e.g. --{key.replace('_', '-')} {old}, to continue it unchanged)")


def _restore_handlers(previous: dict) -> None:
    for sig, handler in previous.items():
        signal.signal(sig, handler)


def _from_worker(error: Exception) -> Exception:
    """A DataLoader worker's error carries the worker's whole traceback in its message; keep only the
    worker's own message (from its ``ValueError: ...`` line to the end) so the command line prints
    it without the traceback. A ``KeyError`` becomes a ``LookupError`` (``KeyError`` would quote its
    text a second time)."""
    text = error.args[0] if error.args and isinstance(error.args[0], str) else str(error)  # KeyError quotes str()
    if "in DataLoader worker process" not in text:
        return error
    lines = text.rstrip().splitlines()
    prefix = f"{type(error).__name__}: "
    start = max((i for i, line in enumerate(lines) if line.startswith(prefix)), default=None)
    message = "\n".join(lines[start:])[len(prefix):] if start is not None else lines[-1]
    kind = LookupError if isinstance(error, KeyError) else type(error)
    try:
        return kind(message)
    except Exception:  # an exception type with other constructor arguments
        return RuntimeError(message)


def _ignore_stop_signals(_worker_id: int) -> None:
    """DataLoader workers leave SIGINT/SIGTERM to the training process, which stops cleanly."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)


def _float_outputs(out: UNetOutput) -> UNetOutput:
    return UNetOutput(*(t.float() for t in out))


def _restore(last: Path, what: str, load) -> None:
    """Run ``load`` (a ``load_state_dict``), turning its error into one naming the checkpoint."""
    try:
        load()
    except (RuntimeError, ValueError, KeyError, TypeError, IndexError) as error:
        reason = " ".join(str(error).split())  # torch's message lists one mismatch a line
        raise ValueError(f"{last}: corrupt checkpoint: loading its {what} failed ({reason}); use another --out "
                         "to start afresh") from None


def _initialise_from(net: NormalLandmarkUNet, ema: NormalLandmarkUNet, config: TrainConfig) -> None:
    """Load ``config.init`` (a weight file) into the network and its moving average."""
    from facenormals.nn import load_weights

    start = load_weights(config.init)
    weights = start.state_dict()
    if start.channels != net.channels or start.num_landmarks != net.num_landmarks:
        raise ValueError(f"init: {config.init} holds a network with channels {start.channels} and "
                         f"{start.num_landmarks} landmarks; the run has channels {net.channels} and "
                         f"{net.num_landmarks} landmarks (--base-channels, --depth)")
    net.load_state_dict(weights)
    ema.load_state_dict(weights)


def train(config: TrainConfig, dataset: Dataset | None = None, holdout: Dataset | None = None,
          progress: bool = True) -> TrainSummary:
    """Train (or resume training) a :class:`~facenormals.nn.NormalLandmarkUNet`.

    If ``config.out/last.pt`` exists the run resumes from it (model, moving average, optimiser,
    step and data position); its architecture must match ``config``. A checkpoint is written every
    ``checkpoint_every`` steps, at the end, after ``max_minutes`` and on SIGINT/SIGTERM. Rank 0
    writes ``log.csv`` (losses, learning rate, throughput) and ``eval.csv`` (held-out metrics of
    the moving-average weights).

    Args:
        config: the run.
        dataset: training items (default: ``SyntheticHeadDataset(config.data)``); items need
            ``image``, ``normals``, ``foreground``, ``landmarks`` and ``landmark_visible``.
        holdout: held-out items (default: ``config.holdout`` when set).
        progress: show a progress bar on rank 0.

    Returns:
        A :class:`TrainSummary`.

    Raises:
        FolderInUseError: (a ``ValueError``) when another process trains into ``config.out``: two runs
            on one folder had interleaved, dropped and duplicated their log rows.
    """
    with contextlib.ExitStack() as locks:
        return _train(config, dataset, holdout, progress, locks)


def _train(config: TrainConfig, dataset: Dataset | None, holdout: Dataset | None, progress: bool,
           locks: contextlib.ExitStack) -> TrainSummary:
    """:func:`train`, holding the run folder's lock in ``locks`` from the moment the folder exists."""
    ctx = init_distributed(config.device)
    if config.threads is not None and ctx.device.type == "cpu":
        torch.set_num_threads(config.threads)
    out = Path(config.out)
    last = out / "last.pt"
    autocast_dtype = resolve_precision(config.precision, ctx.device)
    if dataset is None:
        dataset = _open_dataset(config.data, config, with_maps=False)
    if holdout is dataset:
        raise ValueError("holdout: the training dataset itself; held-out scores of training samples flatter the network")
    if config.holdout and holdout is None:  # every rank: a refusal on rank 0 alone would hang the others
        _check_holdout_is_not_training_data(dataset, config.holdout)
    if holdout is None and config.holdout and ctx.is_main:
        holdout = _open_dataset(config.holdout, config, with_maps=False)
    image_size = _image_size(dataset)  # also stored, so that exported weights say what crops they expect
    _check_depth_fits_the_images(image_size, config.depth)
    if config.init is not None and not last.exists() and not Path(config.init).is_file():
        what = "a folder, not a weight file" if Path(config.init).is_dir() else "no such weight file"
        raise FileNotFoundError(f"init: {config.init}: {what}")

    torch.manual_seed(config.seed)
    net = NormalLandmarkUNet(base_channels=config.base_channels, depth=config.depth).to(ctx.device)
    ema = copy.deepcopy(net).eval().requires_grad_(False)
    if config.init is not None and not last.exists():
        _initialise_from(net, ema, config)
    if ctx.is_main:  # only now: a run refused for its data or --init leaves no empty folder
        out.mkdir(parents=True, exist_ok=True)
        locks.enter_context(hold_locks(out / LOCK, [0], f"out {out}"))  # rank 0 writes the folder's files
    optimizer = torch.optim.AdamW(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    step, samples_seen = 0, 0
    if ctx.is_main:  # checkpoint-sized temporaries of runs killed while saving
        for stale in out.glob(f".last.pt.*{PART}*"):
            stale.unlink(missing_ok=True)
    if last.exists():
        state = load_checkpoint(last, map_location=ctx.device)
        for key in ARCHITECTURE_SETTINGS:
            if state["config"][key] != getattr(config, key):
                raise ValueError(f"config.{key}: {getattr(config, key)} differs from the checkpoint's "
                                 f"{state['config'][key]} in {last}; use another --out to start afresh")
        if state["world_size"] != ctx.world_size or state["config"]["batch_size"] != config.batch_size:
            print(f"note: resuming with world size {ctx.world_size} x batch {config.batch_size} "
                  f"(checkpoint: {state['world_size']} x {state['config']['batch_size']}); the data order differs from here on")
        if ctx.is_main:
            for key, what in (("data", "the training data"), ("seed", "the data order and augmentation")):
                old, new = state["config"].get(key), getattr(config, key)
                same = (Path(str(old)).resolve() == Path(str(new)).resolve()) if key == "data" else old == new
                if not same:
                    print(f"note: resuming {last} with --{key} {new} (checkpoint: {old}); {what} differ from here on")
            stored_size = state.get("dataset_size")  # absent in checkpoints before session 14
            if stored_size is not None and int(stored_size) != len(dataset):
                print(f"note: resuming {last} with {len(dataset)} training samples (checkpoint: {stored_size}); "
                      "the epoch's sample order differs from here on (samples may repeat before the epoch ends)")
            if int(state["step"]) >= config.steps:
                print(f"note: {last} is at step {state['step']}, at or beyond --steps {config.steps}: nothing to train")
        if state["num_landmarks"] != net.num_landmarks:
            raise ValueError(f"{last}: a checkpoint of a network with {state['num_landmarks']} landmarks; the run "
                             f"trains {net.num_landmarks}; use another --out to start afresh")
        _restore(last, "model weights ('model')", lambda: net.load_state_dict(state["model"]))
        _restore(last, "averaged (EMA) weights ('ema')", lambda: ema.load_state_dict(state["ema"]))
        _restore(last, "optimiser state ('optimizer')", lambda: optimizer.load_state_dict(state["optimizer"]))
        for group in optimizer.param_groups:  # the optimiser state restores the old setting; the config wins
            group["weight_decay"] = config.weight_decay
        step, samples_seen = int(state["step"]), int(state["samples_seen"])
        if ctx.is_main:
            _note_changed_settings(state["config"], config, last)
            if config.init is not None:
                print(f"note: --init {config.init} is ignored: {last} exists and the run resumes from it "
                      "(another --out starts a new run from those weights)")
    if ctx.is_main:  # rows logged after the checkpoint (all of them when there is none) are repeated now
        for name, fields in (("log.csv", _LOG_FIELDS), ("eval.csv", _EVAL_FIELDS)):
            _truncate_csv(out / name, step, fields)
        if config.batch_size * ctx.world_size > len(dataset):
            print(f"note: a batch of {config.batch_size} x {ctx.world_size} process(es) is larger than the "
                  f"{len(dataset)} training samples: every batch repeats samples")
        if config.warmup_steps >= config.steps and step < config.steps:
            print(f"note: --warmup-steps {config.warmup_steps} >= --steps {config.steps}: the learning rate rises "
                  "for the whole run and never decays")
    model = net
    if ctx.distributed:
        model = torch.nn.parallel.DistributedDataParallel(
            net, device_ids=[ctx.device.index] if ctx.device.type == "cuda" else None)

    per_rank_seen = samples_seen // ctx.world_size
    sampler = _EpochSampler(len(dataset), config.seed, ctx.rank, ctx.world_size, start=per_rank_seen)
    loader = DataLoader(dataset, batch_size=config.batch_size, sampler=sampler, num_workers=config.workers,
                        pin_memory=ctx.device.type == "cuda", drop_last=True,
                        persistent_workers=config.workers > 0, worker_init_fn=_ignore_stop_signals)
    augment = PhotoAugmentation().to(ctx.device)

    saved_step = step if last.exists() else None  # the step of the checkpoint a failed run can resume from

    def checkpoint() -> None:
        nonlocal saved_step
        saved_step = step  # every rank knows what rank 0 wrote
        if ctx.is_main:
            save_checkpoint(last, {
                "format": "facenormals-train", "config": config.to_dict(), "step": step,
                "samples_seen": samples_seen, "world_size": ctx.world_size, "num_landmarks": net.num_landmarks,
                "dataset_size": len(dataset), "image_size": list(image_size),
                "model": net.state_dict(), "ema": ema.state_dict(), "optimizer": optimizer.state_dict(),
            })

    def resume_advice() -> str:
        if saved_step is None:
            return "lower --lr"
        return f"lower --lr, or resume from the last checkpoint {last} (step {saved_step})"

    def evaluate(max_samples: int | None) -> NetworkMetrics | None:
        if holdout is None or not ctx.is_main:
            return None
        metrics = evaluate_network(ema, holdout, batch_size=config.batch_size, max_samples=max_samples, mirror=False)
        _append_csv(out / "eval.csv", _EVAL_FIELDS, {"step": step, "samples_seen": samples_seen, **metrics.as_dict()})
        return metrics

    stop_signal: list[int] = []
    previous = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            previous[sig] = signal.signal(sig, lambda s, f: stop_signal.append(s))
        except ValueError:  # not the main thread
            pass

    bar = None
    if progress and ctx.is_main:
        from tqdm.auto import tqdm

        bar = tqdm(total=config.steps, initial=step, desc="train", unit="step", dynamic_ncols=True)
    start = time.perf_counter()
    window_start, window_images = start, 0
    stopped_by = "steps"
    metrics: NetworkMetrics | None = None
    running: dict[str, float] = {}
    window_steps = 0  # steps summed in ``running`` (fewer than log_every in the first window of a resumed run)
    already_finished = step >= config.steps  # a rerun of a finished run writes nothing

    def log_window() -> None:
        """Append a row of the losses averaged over the steps since the last one (on every rank)."""
        nonlocal running, window_start, window_images, window_steps
        now = time.perf_counter()
        if ctx.distributed:  # the losses of the whole global batch, not rank 0's share
            keys = sorted(running)
            sums = torch.tensor([running[k] for k in keys], dtype=torch.float64, device=ctx.device)
            torch.distributed.all_reduce(sums)
            running = dict(zip(keys, (sums / ctx.world_size).tolist()))
        row = {k: v / window_steps for k, v in running.items()}
        row.update(step=step, epoch=samples_seen / len(dataset), samples_seen=samples_seen,
                   lr=config.learning_rate(step - 1), images_per_s=window_images / max(now - window_start, 1e-9),
                   elapsed_s=now - start)
        running, window_start, window_images, window_steps = {}, now, 0, 0
        if ctx.is_main:
            _append_csv(out / "log.csv", _LOG_FIELDS, row)
            if bar is not None:
                bar.set_postfix(loss=f"{row['loss']:.4f}", img_s=f"{row['images_per_s']:.1f}")
    batches = None
    try:
        batches = iter(loader)
        while step < config.steps:
            try:
                batch = next(batches)
            except Exception as error:
                raise _from_worker(error) from None
            torch.manual_seed(_derived_seed(config.seed, step, ctx.world_size, ctx.rank))  # resumable augmentation
            images = augment(batch["image"].to(ctx.device, non_blocking=True))
            normals = batch["normals"].to(ctx.device, non_blocking=True)
            foreground = batch["foreground"].to(ctx.device, non_blocking=True)
            points = batch["landmarks"].to(ctx.device, non_blocking=True)
            maps = landmark_maps(points, batch["landmark_visible"].to(ctx.device), images.shape[-2:], config.sigma)
            lr = config.learning_rate(step)
            for group in optimizer.param_groups:
                group["lr"] = lr
            with torch.autocast(ctx.device.type, dtype=autocast_dtype or torch.bfloat16,
                                enabled=autocast_dtype is not None):
                prediction = model(images)
            # L_N over the global batch's foreground, not each rank's (docs of the loss)
            foreground_pixels = _foreground_per_rank(foreground, ctx.world_size) if ctx.distributed else None
            loss, terms = normal_landmark_loss(_float_outputs(prediction), normals, maps, foreground,
                                               config.landmark_weight, config.foreground_weight,
                                               config.landmark_peak_weight, foreground_pixels)
            # Stop or fail on every rank together (a rank left alone would wait in the next all-reduce).
            timed_out = config.max_minutes is not None and time.perf_counter() - start > 60.0 * config.max_minutes
            flags = torch.tensor([bool(stop_signal), timed_out, not bool(torch.isfinite(loss.detach()))],
                                 dtype=torch.int32, device=ctx.device)
            if ctx.distributed:
                torch.distributed.all_reduce(flags, op=torch.distributed.ReduceOp.MAX)
            if flags[2]:
                raise FloatingPointError(f"step {step}: the loss is not finite on some rank ({float(loss.detach())} "
                                         f"here); {resume_advice()}")
            if flags[0] or flags[1]:
                stopped_by = "signal" if flags[0] else "max_minutes"
                if window_steps:  # the steps since the last row, which a resume does not repeat
                    log_window()
                break
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            # A finite loss can still have an overflowing gradient: stepping would put NaN in the
            # weights and the next checkpoint. DDP averaged the gradients, so every rank agrees.
            gradient_norm = torch.nn.utils.clip_grad_norm_(net.parameters(), float("inf"))
            if not bool(torch.isfinite(gradient_norm)):
                raise FloatingPointError(f"step {step}: the gradient is not finite (the loss was {float(loss.detach()):.6g}); "
                                         f"the weights were not updated; {resume_advice()}")
            optimizer.step()
            with torch.no_grad():
                decay = min(config.ema_decay, (1.0 + step) / (10.0 + step))
                for e, p in zip(ema.parameters(), net.parameters()):
                    e.lerp_(p, 1.0 - decay)
                for e, b in zip(ema.buffers(), net.buffers()):
                    e.copy_(b)
            step += 1
            samples_seen += config.batch_size * ctx.world_size
            window_images += config.batch_size * ctx.world_size
            window_steps += 1
            for key, value in (("loss", loss), *terms.items()):
                running[key] = running.get(key, 0.0) + float(value.detach())
            if step % config.log_every == 0 or step == config.steps:
                log_window()
            if bar is not None:
                bar.update(1)
            if step % config.eval_every == 0 and step < config.steps:  # before the checkpoint: a run killed
                metrics = evaluate(config.eval_samples)                # in between evaluates again on resume
                if metrics is not None and bar is not None:
                    bar.write(f"step {step}: {metrics}")
            if step % config.checkpoint_every == 0:
                checkpoint()
        if not already_finished:
            checkpoint()
        _restore_handlers(previous)  # Ctrl-C during the final evaluation interrupts it
        previous = {}
        if stop_signal:
            stopped_by = "signal"
        elif step >= config.steps and (not already_finished or _last_logged_step(out / "eval.csv") != step):
            metrics = evaluate(None)  # (again, for a finished run killed during its final evaluation)
    finally:
        # Workers ignore SIGINT/SIGTERM (the training process stops cleanly), so they are told to exit
        # here: left to the interpreter's exit, which terminates them with SIGTERM, an error raised
        # out of this loop would hang the process forever.
        shutdown = getattr(batches, "_shutdown_workers", None)
        if shutdown is not None:
            shutdown()
        if bar is not None:
            bar.close()
        _restore_handlers(previous)
        if ctx.distributed and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()
    return TrainSummary(step=step, samples_seen=samples_seen, finished=step >= config.steps,
                        stopped_by=stopped_by, seconds=time.perf_counter() - start, metrics=metrics,
                        checkpoint=last)
