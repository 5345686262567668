"""The ``facenormals`` command line."""

from __future__ import annotations

import argparse
import math
import os
import sys
import textwrap
from pathlib import Path
from typing import Sequence

__all__ = ["main"]


def _cmd_demo(args: argparse.Namespace) -> int:
    import torch

    from facenormals.demo import run_demo
    from facenormals.models import load_model

    torch.set_num_threads(max(1, torch.get_num_threads()))
    _check_writable(args.out, "--out", folder=True)
    model = load_model(args.model)
    if model.name == "builtin" and args.model == "auto":
        print("ICT-FaceKit not found: using the built-in procedural head (`facenormals models fetch ict` gets it)")
    report = run_demo(model, seed=args.seed, out_dir=args.out)
    print()
    print("face region, after similarity alignment   point-to-plane RMSE   correspondence RMSE")
    print(f"  mean head (baseline)                      {report.mean_head_rmse_mm:8.3f} mm          "
          f"{report.mean_head_correspondence_mm:8.3f} mm")
    print(f"  fitted head                               {report.fitted_rmse_mm:8.3f} mm          "
          f"{report.fitted_correspondence_mm:8.3f} mm")
    print(f"landmark error {report.landmark_error_px:.2f} px, yaw error {report.yaw_error_deg:.2f} deg, "
          f"fit {report.fit_seconds * 1e3:.0f} ms, total {report.seconds:.1f} s")
    if report.mesh_path is not None:
        print(f"wrote {report.mesh_path} and {report.overlay_path}")
    return 0


def _describe(model) -> list[str]:
    std = model.shape_std
    # a model without shape components (a rigid template) has no sigma range
    sigma = f" (sigma {float(std.min()):.3g} .. {float(std.max()):.3g})" if std.numel() else ""
    lines = [
        f"name          {model.name}",
        f"vertices      {model.num_vertices}",
        f"triangles     {model.faces.shape[0]}",
        f"shape         {model.num_shape} components{sigma}",
        f"expressions   {model.num_expressions}",
        f"landmarks     {len(model.landmark_names)}",
        f"face region   {int(model.face_region.sum())} vertices",
    ]
    for key in ("source", "license", "file"):
        if key in model.metadata:
            lines.append(f"{key:<13} {model.metadata[key]}")
    return lines


def _cmd_models(args: argparse.Namespace) -> int:
    from facenormals.models import find_ict_archive, load_model
    from facenormals.models.registry import cache_dir

    if args.action == "list":
        archive = find_ict_archive()
        rows = [("builtin", "built into the package (procedural head)")]
        rows.append(("ict", str(archive) if archive else "not installed: run `facenormals models fetch ict`"))
        for name, where in rows:
            line = f"{name:<9} {where}"
            if name == "builtin" or archive is not None:
                model = load_model(name)
                line += (f"\n          {model.num_vertices} vertices, {model.num_shape} shape components, "
                         f"{model.num_expressions} expressions, {len(model.landmark_names)} landmarks; "
                         f"{model.metadata.get('source', '')}")
            print(line)
        print(f"cache: {cache_dir()}  (a model file also loads with --model PATH: facenormals .npz, LYHM or BFM "
              "2009 .mat, BFM 2017/2019 .h5, FLAME .pkl)")
        return 0
    if args.action == "show":
        model = load_model(args.name)
        print("\n".join(_describe(model)))
        print("landmarks:")
        for name, index in model.landmarks.items():
            print(f"  {name:<20} vertex {index}")
        return 0
    if args.action == "fetch":
        from facenormals.models.fetch import fetch_ict

        if args.name != "ict":
            raise ValueError(f"name: only 'ict' can be fetched, got {args.name!r}")
        path = fetch_ict(source=args.source, force=args.force)
        print(f"ICT-FaceKit is ready: {path}")
        return 0
    raise ValueError(f"unknown action {args.action!r}")


def _cmd_evaluate(args: argparse.Namespace) -> int:
    import json

    from facenormals.eval import evaluate_reconstruction, landmark_correspondences, shares_vertex_order
    from facenormals.mesh import load_mesh
    from facenormals.models import load_model

    if args.json is not None:
        _check_writable(args.json, "--json", inputs=(args.prediction, args.reference, args.prediction_landmarks,
                                                     args.model))  # a model file too, not the names ict/builtin
    pred_v, pred_f = load_mesh(args.prediction)
    ref_v, ref_f = load_mesh(args.reference)
    model = load_model(args.model)
    # the reference's landmarks are the model's: a model without those of the rough alignment is named
    landmark_correspondences(model.landmarks, model.landmarks, source_name=f"--model {args.model}",
                             target_name=f"--model {args.model}")
    if ref_v.shape[0] != model.num_vertices or not shares_vertex_order(model.faces, ref_f):  # a crop of it passes
        what = (f"has {ref_v.shape[0]} vertices but model {model.name!r} has {model.num_vertices}"
                if ref_v.shape[0] != model.num_vertices else
                f"has the vertex count of model {model.name!r} but not its vertex order (its triangles join other vertices)")
        raise ValueError(
            f"{args.reference}: {what}; the reference must share the model's topology (its face region and landmarks "
            "are used); pass --model"
        )
    if args.prediction_landmarks:
        try:
            with open(args.prediction_landmarks) as handle:
                pred_landmarks = dict(json.load(handle))
            wrong = {k: v for k, v in pred_landmarks.items() if type(v) is not int}  # 1.7 or true are no index
            if wrong:
                raise ValueError(f"non-integer vertex indices {wrong}")
        except (OSError, ValueError, TypeError, AttributeError) as error:
            raise ValueError(f"{args.prediction_landmarks}: expected a JSON object of landmark name -> vertex index "
                             f"({type(error).__name__}: {error})") from None
        outside = {name: index for name, index in pred_landmarks.items() if not 0 <= index < pred_v.shape[0]}
        if outside:
            raise ValueError(f"{args.prediction_landmarks}: expected vertex indices in [0, {pred_v.shape[0]}) of "
                             f"{args.prediction}, got {outside}")
    elif pred_v.shape[0] == model.num_vertices and shares_vertex_order(model.faces, pred_f):
        pred_landmarks = model.landmarks
    else:
        what = (f"has {pred_v.shape[0]} vertices, not the model's {model.num_vertices}" if pred_v.shape[0] !=
                model.num_vertices else "has the model's vertex count but not its vertex order (its triangles join other "
                "vertices)")
        raise ValueError(
            f"{args.prediction}: {what}; pass --prediction-landmarks JSON (landmark name -> vertex index) "
            "for the rough alignment"
        )
    try:
        report = evaluate_reconstruction(pred_v.double(), pred_f, ref_v.double(), ref_f, model.face_region,
                                         correspondences=(pred_landmarks, model.landmarks))
    except ValueError as error:  # e.g. a degenerate mesh: say which files
        files = f"{args.prediction} (landmarks {args.prediction_landmarks})" if args.prediction_landmarks else args.prediction
        raise ValueError(f"{files} against {args.reference}: {error}") from None
    print(report)  # with its warnings, if any
    if args.json is not None:
        from facenormals.core import atomic_write

        Path(args.json).parent.mkdir(parents=True, exist_ok=True)  # the check above removed the folders it made
        with atomic_write(args.json) as part:
            part.write_text(json.dumps(_json_safe(report.as_dict()), indent=2, allow_nan=False))
        print(f"wrote {args.json}")
    return 0


def _json_safe(value):
    """NaN and infinities as ``null``: ``json.dumps`` would write ``NaN`` tokens, which are not JSON."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


#: write_dataset's and SynthConfig's parameters as `facenormals synth` options, for its errors.
_SYNTH_OPTIONS = {"count": "--count", "workers": "--workers", "seed": "--seed", "shard_size": "--shard-size",
                  "out_dir": "--out", "config.background_folders": "--backgrounds", "rank": "--rank",
                  "world_size": "--world-size", "identity_scale": "--identity-scale"}


def _cmd_synth(args: argparse.Namespace) -> int:
    from facenormals.data import SynthConfig, write_dataset

    _check_writable(args.out, "--out", folder=True)
    try:
        config = SynthConfig(identity_scale=args.identity_scale, background_folders=tuple(args.backgrounds))
        summary = write_dataset(args.out, args.count, workers=args.workers, seed=args.seed, model_spec=args.model,
                                shard_size=args.shard_size, progress=not args.quiet, rank=args.rank,
                                world_size=args.world_size, config=config)
    except ValueError as error:  # the library names its parameters; name the command's options instead
        name, _, rest = str(error).partition(": ")
        if name in _SYNTH_OPTIONS:
            raise ValueError(f"{_SYNTH_OPTIONS[name]}: {rest}") from None
        raise
    print(f"{summary.root}: wrote {summary.shards_written} shard(s) ({summary.samples} samples, "
          f"{summary.samples_per_second:.1f}/s), {summary.shards_skipped} already complete")
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    from facenormals.core.check import environment_integer
    from facenormals.training import TrainConfig, export_weights, train

    _check_writable(args.out, "--out", folder=True)
    fields = TrainConfig.__dataclass_fields__
    values = {name: getattr(args, name) for name in fields if getattr(args, name, None) is not None}
    last = Path(args.out) / "last.pt"
    if last.is_file():  # a resume keeps the checkpoint's training settings unless the command gives them
        from facenormals.training import load_checkpoint
        from facenormals.training.config import ARCHITECTURE_SETTINGS, RESUMED_SETTINGS

        stored = load_checkpoint(last)["config"]
        values.update({key: stored[key] for key in (*ARCHITECTURE_SETTINGS, *RESUMED_SETTINGS)
                       if key not in values and key in stored})
    try:
        config = TrainConfig(**values)
    except ValueError as error:  # the config names its fields; name the command's options where they came from
        name, _, rest = str(error).partition(": ")
        if name in fields and getattr(args, name, None) is not None:
            raise ValueError(f"--{name.replace('_', '-')}: {rest}") from None
        raise
    if args.export is not None:
        _check_export_path(args.export, Path(config.out), config.init)
    try:
        summary = train(config, progress=not args.quiet)
    except ValueError as error:  # e.g. "config.base_channels: 8 differs from the checkpoint's 16": the option
        name, _, rest = str(error).partition(": ")
        if name.startswith("config.") and name[len("config."):] in fields:
            raise ValueError(f"--{name[len('config.'):].replace('_', '-')}: {rest}") from None
        raise
    if environment_integer("RANK", 0) != 0:  # under torchrun only rank 0 reports and exports
        return 130 if summary.stopped_by == "signal" else 0
    print(f"{summary.checkpoint}: step {summary.step}/{config.steps}, {summary.samples_seen} samples seen "
          f"(stopped by {summary.stopped_by}, {summary.seconds / 60:.1f} min)")
    if summary.metrics is not None:
        print(f"held out: {summary.metrics}")
    if summary.stopped_by == "signal":  # a half-trained network must not pass for a finished one
        print("interrupted: rerun the same command to resume" + (" (and export)" if args.export else ""),
              file=sys.stderr)
        return 130
    if args.export is not None:
        from torch.utils.data import Subset

        from facenormals.data import SyntheticHeadDataset

        data = SyntheticHeadDataset(config.data, with_landmark_maps=False)
        tail = Subset(data, range(max(0, len(data) - 1000), len(data)))  # threshold from training samples
        path = export_weights(summary.checkpoint, args.export, calibration_data=tail)
        print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB)")
    return 0


def _check_writable(path: str | Path, option: str, folder: bool = False, inputs: Sequence[str | None] = ()) -> None:
    """Refuse, before any work, an output ``path`` that cannot be written or would destroy something: an
    empty name (an unset variable: the output would land in the current folder), a folder (a file when
    ``folder``), a path under a file, one of the command's ``inputs``, or a folder where no file can be
    created (tried by creating one, and the missing folders leading to it, then removing them again;
    under a launcher, ``WORLD_SIZE`` > 1, the folders stay: the ranks run this check at once, and a
    rank removing the folder it made pulled it from under another's probe, or its first shard)."""
    from facenormals.core.check import check_file_name, environment_integer
    from facenormals.core.files import temporary_beside

    if not folder:
        path = check_file_name(path, option)  # a name, no folder, under no file
    else:
        if str(path) == "":
            raise ValueError(f"{option}: expected a folder name, got an empty string")
        path = Path(path)
        if path.exists() and not path.is_dir():
            raise ValueError(f"{option}: {path} exists and is not a folder")
        blocking = next((p for p in path.parents if p.exists() and not p.is_dir()), None)
        if blocking is not None:
            raise ValueError(f"{option}: {path} cannot be written: {blocking} is a file, not a folder")
    for name in inputs:
        if name is not None and Path(name).resolve() == path.resolve():
            raise ValueError(f"{option}: {path} is also an input of this command; writing it would destroy the input")
    where = path if folder else path.parent
    missing = [p for p in (where, *where.parents) if not p.exists()]
    world, rank = environment_integer("WORLD_SIZE", 1), environment_integer("RANK", 0)
    if world > 1 and 0 <= rank < world:  # (a launch of no rank 0 is refused later, leaving nothing)
        missing = []  # left for the other ranks, which may be using them already
    try:
        where.mkdir(parents=True, exist_ok=True)
        temporary_beside(where / "probe").unlink()
    except OSError as error:
        raise ValueError(f"{option}: {path} cannot be written ({error.strerror or error})") from None
    finally:
        for folder_made in missing:  # deepest first: a failed command leaves no empty folders behind
            try:
                folder_made.rmdir()
            except OSError:
                break


def _check_export_path(export: str, out: Path, init: str | None = None) -> None:
    """Refuse, before training, an --export path that cannot be written or would destroy a file."""
    from facenormals.nn import load_weights

    _check_writable(export, "--export")
    path = Path(export)
    if init is not None and path.resolve() == Path(init).resolve():
        raise ValueError(f"--export: {path} holds the --init weights this run starts from; writing over them would "
                         "lose them, choose another file")
    if path.resolve() == (out / "last.pt").resolve():
        raise ValueError(f"--export: {path} is the run's checkpoint; writing the weights over it would lose the "
                         "training state, choose another file")
    if path.exists():
        try:
            load_weights(path)
        except ValueError:
            raise ValueError(f"--export: {path} exists and is not a facenormals weight file; refusing to overwrite "
                             "it (remove it or choose another name)") from None


def _parse_box(text: str) -> tuple[float, float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 4:
        raise argparse.ArgumentTypeError(f"expected X,Y,W,H in pixels, got {text!r}")
    return values  # type: ignore[return-value]


def _cmd_reconstruct(args: argparse.Namespace) -> int:
    from facenormals.reconstruct import reconstruct_photos

    _check_writable(args.out, "-o/--out", folder=True)  # before the photos are read and fitted
    boxes = list(args.box or [])
    if boxes and len(boxes) != len(args.images):
        raise ValueError(f"--box: give one per image ({len(args.images)}) or none, got {len(boxes)}")
    rec = reconstruct_photos(args.images, args.out, model=args.model, weights=args.weights, device=args.device,
                             boxes=boxes or None)
    t = rec.timings
    print(f"done in {t['total']:.2f} s (network {t['network'] * 1e3:.0f} ms, fit {t['fit'] * 1e3:.0f} ms, "
          f"loading {t['load']:.2f} s)")
    return 0


class _OptionsKeptWhole(argparse.HelpFormatter):
    """Help text wrapped between words only: argparse's default breaks "--weight-decay" at its hyphens."""

    def _split_lines(self, text: str, width: int) -> list[str]:
        return textwrap.wrap(" ".join(text.split()), width, break_on_hyphens=False)

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        return textwrap.fill(" ".join(text.split()), width, initial_indent=indent, subsequent_indent=indent,
                             break_on_hyphens=False)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="facenormals", description="Reconstruct 3D heads from photos with predicted normals and landmarks.",
        epilog="Errors print one line and exit 1 (set FACENORMALS_TRACEBACK=1 for the traceback); a mistyped "
               "command line prints its usage and exits 2; Ctrl-C exits 130.")
    from facenormals import __version__

    parser.add_argument("--version", action="version", version=f"facenormals {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="recover a random synthetic head from its normal map and landmarks")
    demo.add_argument("--model", default="auto", help="ict, builtin, auto (default) or a model file (.npz, .mat, .h5, "
                      ".pkl)")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--out", default="out/demo", help="output folder for demo_fit.ply and demo_overlay.png")
    demo.set_defaults(func=_cmd_demo)

    models = sub.add_parser("models", help="list, show or fetch morphable models")
    actions = models.add_subparsers(dest="action", required=True)
    actions.add_parser("list", help="the models available here")
    show = actions.add_parser("show", help="vertices, components, landmarks and source of a model")
    show.add_argument("name", help="ict, builtin or a model file (.npz, .mat, .h5, .pkl)")
    fetch = actions.add_parser("fetch", help="download and convert a model into the cache")
    fetch.add_argument("name", choices=["ict"])
    fetch.add_argument("--from", dest="source", default=None, help="convert a local copy (folder or zip) instead")
    fetch.add_argument("--force", action="store_true", help="rebuild even if cached")
    models.set_defaults(func=_cmd_models)

    evaluate = sub.add_parser("evaluate", help="score a predicted head mesh against a reference, in mm")
    evaluate.add_argument("prediction", help="predicted mesh (.ply, .obj, ...)")
    evaluate.add_argument("reference", help="reference mesh in the topology of --model")
    evaluate.add_argument("--model", default="auto", help="model giving the reference's face region and landmarks")
    evaluate.add_argument("--prediction-landmarks", default=None,
                          help="JSON name -> vertex index for a prediction in another topology")
    evaluate.add_argument("--json", default=None, help="also write the report as JSON")
    evaluate.set_defaults(func=_cmd_evaluate)

    synth = sub.add_parser("synth", help="render synthetic training data (images, normal maps, landmarks) into shards")
    synth.add_argument("--count", type=int, required=True, help="number of samples")
    synth.add_argument("--out", required=True, help="output folder; finished shards are skipped on a rerun")
    synth.add_argument("--workers", type=int, default=1)
    synth.add_argument("--seed", type=int, default=0)
    synth.add_argument("--model", default="auto", help="ict, builtin, auto or a model path")
    synth.add_argument("--shard-size", type=int, default=1000)
    synth.add_argument("--identity-scale", type=float, default=1.0, help="scale of the identity coefficients' spread")
    synth.add_argument("--backgrounds", action="append", default=[], metavar="DIR", help="folders of background photos")
    synth.add_argument("--rank", type=int, default=None, help="this process's rank (default: $RANK)")
    synth.add_argument("--world-size", type=int, default=None, help="number of ranks (default: $WORLD_SIZE)")
    synth.add_argument("--quiet", action="store_true", help="no progress bar")
    synth.set_defaults(func=_cmd_synth)

    rec = sub.add_parser("reconstruct", help="reconstruct a 3D head from one or more photos of a person",
                         description="Detect and crop the face, predict normals and landmarks, pre-align and fit "
                                     "the morphable model (several photos: one shared shape, a pose per photo). "
                                     "Writes head.ply, head.obj, params.json and per photo an overlay and N/Z pictures.")
    rec.add_argument("images", nargs="+", metavar="IMAGE", help="photos (any size, colour or grey; EXIF orientation honoured)")
    rec.add_argument("-o", "--out", required=True, metavar="OUT_DIR", help="output folder")
    rec.add_argument("--model", default="auto", help="ict, builtin, auto (ICT if installed, default) or a model path")
    rec.add_argument("--weights", default=None, help="network weights (default: the shipped ones)")
    rec.add_argument("--device", default="cpu", help="cpu (default) or cuda")
    rec.add_argument("--box", action="append", type=_parse_box, metavar="X,Y,W,H",
                     help="face box per image, in image order, instead of detecting it (e.g. for profile views); "
                          "write a box with a negative X as --box=-20,30,150,150")
    rec.set_defaults(func=_cmd_reconstruct)

    from facenormals.training.config import ARCHITECTURE_SETTINGS, RESUMED_SETTINGS, TrainConfig

    resumed = ["--" + key.replace("_", "-") for key in (*ARCHITECTURE_SETTINGS, *RESUMED_SETTINGS)]
    train = sub.add_parser("train", formatter_class=_OptionsKeptWhole, help="train the normal + landmark network on synthetic data (resumes from OUT/last.pt)",
                           description="Single process: `facenormals train ...`; several GPUs or machines: "
                                       "`torchrun --nproc-per-node N -m facenormals.cli train ...` (DDP). A run "
                                       "that resumes OUT/last.pt takes the network's shape and the optimisation "
                                       f"and loss settings ({', '.join(resumed)}) from the checkpoint unless the "
                                       "command gives them; the other options apply as given. The defaults below "
                                       "are those of a new run.")
    train.add_argument("--data", required=True, help="training dataset folder (facenormals synth)")
    train.add_argument("--out", required=True, help="run folder: last.pt, log.csv, eval.csv")
    train.add_argument("--holdout", default=None, help="held-out dataset folder scored during training")
    train_defaults = TrainConfig.__dataclass_fields__
    for name, kind, text in (
        ("steps", int, "optimiser steps of the whole run"), ("batch-size", int, "images per step and process"),
        ("lr", float, "peak AdamW learning rate"), ("warmup-steps", int, None),
        ("min-lr-ratio", float, "the cosine's floor, as a fraction of --lr"), ("weight-decay", float, None),
        ("ema-decay", float, "decay of the exported weight average"),
        ("landmark-weight", float, "weight of L_Z"), ("landmark-peak-weight", float, "extra weight under the Gaussians"),
        ("foreground-weight", float, None),
        ("sigma", float, "landmark Gaussian sigma in pixels"), ("workers", int, "DataLoader workers per process"),
        ("precision", str, "auto, bf16 or fp32"), ("threads", int, "CPU threads"), ("seed", int, None),
        ("log-every", int, None), ("checkpoint-every", int, None), ("eval-every", int, None),
        ("eval-samples", int, None), ("max-minutes", float, "stop with a checkpoint after this wall time"),
        ("base-channels", int, None), ("depth", int, None),
    ):
        default = train_defaults[name.replace("-", "_")].default
        shown = f"default {default}" if default is not None else {"threads": "default: torch's",
                                                                   "max-minutes": "default: no limit"}[name]
        train.add_argument(f"--{name}", type=kind, default=None,  # None: a resume keeps the checkpoint's value
                           help=f"{text}; {shown}" if text else shown)
    train.add_argument("--device", default=None, help="auto (default), cpu, cuda or cuda:N")
    train.add_argument("--init", default=None, metavar="WEIGHTS",
                       help="start a new run from these weights (fine-tuning); ignored when OUT/last.pt exists")
    train.add_argument("--export", default=None, metavar="WEIGHTS", help="also export the averaged weights (fp16)")
    train.add_argument("--quiet", action="store_true", help="no progress bar")
    train.set_defaults(func=_cmd_train)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    name = "facenormals"  # then "facenormals COMMAND", for the messages
    try:  # building the parser imports torch (seconds): Ctrl-C then gets the same one line
        args = build_parser().parse_args(argv)
        name = f"facenormals {args.command}"
        return int(args.func(args))
    except KeyboardInterrupt:
        print(f"{name}: interrupted (files already written are kept; rerun to resume where that applies)",
              file=sys.stderr)
        return 130
    except BrokenPipeError as error:
        if _stdout_is_broken():  # its reader went away (`facenormals models show X | head`): exit quietly
            return 141  # 128 + SIGPIPE, as a shell reports a command killed by it
        if os.environ.get("FACENORMALS_TRACEBACK", "") not in ("", "0"):
            raise
        print(f"{name}: error: {error}", file=sys.stderr)
        return 1
    except (ValueError, OSError, RuntimeError, ArithmeticError) as error:
        if os.environ.get("FACENORMALS_TRACEBACK", "") not in ("", "0"):
            raise
        print(f"{name}: error: {error}", file=sys.stderr)
        return 1


def _stdout_is_broken() -> bool:
    """Whether stdout is a pipe whose reader has gone (poll reports an error on its write end,
    without writing); if so, stdout is pointed at /dev/null so that the interpreter's final flush
    raises no second error. Without poll (Windows) a broken pipe is taken to be stdout's."""
    import select

    try:
        descriptor = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # not a file (a StringIO): the broken pipe is another
        return False
    try:
        poller = select.poll()
        poller.register(descriptor, select.POLLOUT)
        events = dict(poller.poll(0)).get(descriptor, 0)
        broken = bool(events & (select.POLLERR | select.POLLHUP))
    except (AttributeError, OSError):
        broken = True
    if broken:
        os.dup2(os.open(os.devnull, os.O_WRONLY), descriptor)
    return broken


if __name__ == "__main__":
    raise SystemExit(main())
