"""``tandemscan train-deepmerge`` and ``tandemscan register``: DeepMerge training and pairwise registration.

``add_commands(subparsers)`` adds both sub-commands to the main CLI. Bad input (a missing cloud, an unreadable
transform or weights file) raises :class:`~tandemscan.daemon.cli.command.UsageError`: one error line, exit status
2; a registration that fails its verification is one line and exit status 3 (docs/registration.md).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from tandemscan.config import load_config
from tandemscan.daemon.cli.command import UsageError, console


def cmd_train_deepmerge(args: argparse.Namespace) -> int:
    """Train DeepMerge weights on generated data (CPU; see docs/deepmerge.md)."""
    import torch
    from tandemscan.pipeline.deepmerge.train import TrainSettings, train

    if args.threads:
        torch.set_num_threads(args.threads)
    if args.log:
        handler = logging.FileHandler(args.log, encoding="utf-8")
        handler.setFormatter(logging.Formatter("%(asctime)s %(message)s"))
        train_log = logging.getLogger("tandemscan.pipeline.deepmerge.train")
        train_log.addHandler(handler)
        train_log.setLevel(logging.INFO)
    settings = TrainSettings(seed=args.seed, steps=args.steps, max_minutes=args.max_minutes,
                             train_pairs=args.train_pairs, val_pairs=args.val_pairs, batch_size=args.batch_size,
                             checkpoint_every=args.checkpoint_every)
    with Progress(TextColumn("{task.description:<32}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                  TimeElapsedColumn(), console=console) as bar:
        task = bar.add_task("making data, then training", total=settings.steps)
        _, summary = train(settings, Path(args.out),
                           lambda step, loss: bar.update(task, completed=step, description=f"loss {loss:.4f}"))
    Console().print_json(json.dumps(summary))
    return 0


def cmd_register(args: argparse.Namespace) -> int:
    """Register SOURCE onto TARGET; print the 4x4 that maps SOURCE into TARGET, the fit and the stage that
    won. A result that fails its verification (no inliers, infinite RMS, worse than the start) prints one
    line saying why and exits with status 3; the network (PyTorch) is loaded only if a stage needs it."""
    import numpy as np
    from tandemscan.pipeline.io.cloud_io import CloudIOError, read_ply
    from tandemscan.pipeline.registration.pairs import LazyNetwork, PairCriteria, RegistrationFailed, register_clouds

    config = load_config(args.config)
    try:
        source, _ = read_ply(Path(args.source))
        target, _ = read_ply(Path(args.target))
        init = np.loadtxt(args.init).reshape(4, 4) if args.init else None
        criteria = PairCriteria.from_section(config.correction, **({"method": args.method} if args.method else {}))
        res = register_clouds(source, target, criteria, init, args.delta_mm, LazyNetwork(config.deepmerge))
    except RegistrationFailed as e:
        console.print(f"registration failed: {e}", highlight=False, markup=False, soft_wrap=True)
        return 3
    except (CloudIOError, OSError, ValueError) as e:
        raise UsageError(str(e)) from e
    text = "\n".join(" ".join(f"{v:.9g}" for v in row) for row in res.transformation)
    if args.out:
        Path(args.out).write_text(text + "\n", encoding="utf-8")
    out = Console()
    out.print(text, highlight=False)
    gate = f", refined at {res.gate_mm:.3f} mm" if res.gate_mm is not None else ""
    out.print(f"fitness {res.fit.fitness:.4f}  point-to-plane RMS {res.fit.rmse_mm:.4f} mm  ({args.method}: "
              f"stage {res.stage} won of {', '.join(res.stages_run)}{gate})", highlight=False)
    return 0


def add_commands(sub) -> None:
    """Add ``train-deepmerge`` and ``register`` to an argparse sub-parser collection."""
    p = sub.add_parser("train-deepmerge", help="train DeepMerge weights on generated data (CPU)")
    p.add_argument("--out", type=Path, default=Path("deepmerge.pt"), help="weights file to write")
    p.add_argument("--steps", type=int, default=6000, help="at most this many steps (the time budget may end it first)")
    p.add_argument("--max-minutes", type=float, default=110.0, help="stop after this long (data included)")
    p.add_argument("--train-pairs", type=int, default=800)
    p.add_argument("--checkpoint-every", type=int, default=100, help="steps between checkpoints and validations")
    p.add_argument("--val-pairs", type=int, default=60)
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    p.add_argument("--log", type=Path, help="append the loss and validation log to this file")
    p.set_defaults(func=cmd_train_deepmerge)

    p = sub.add_parser("register", help="register two clouds (PLY/PCD/XYZ, mm)")
    p.add_argument("source", type=Path)
    p.add_argument("target", type=Path)
    p.add_argument("--init", type=Path, help="text file with the initial 4x4 (source into target)")
    p.add_argument("--method", choices=["auto", "icp", "fpfh+icp", "deepmerge", "deepmerge+icp"], default="auto",
                   help="auto: fine stage and FPFH + RANSAC, the network where they disagree; best verified fit")
    p.add_argument("--delta-mm", type=float, default=5.0, help="overlap threshold after --init, mm")
    p.add_argument("--config", type=Path, help="cell configuration TOML ([correction] and [deepmerge] settings)")
    p.add_argument("--out", type=Path, help="also write the 4x4 to this file")
    p.set_defaults(func=cmd_register)
