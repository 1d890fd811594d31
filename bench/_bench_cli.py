"""The command-line plumbing the bench scripts share: their parsers' common options, ``--json``
output and ``--threads``.

A script imports it after putting its own folder on ``sys.path`` (``python bench/x.py`` has it
there already; tests load the scripts by file path, which does not)::

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _bench_cli import parser, write_json

Nothing here imports torch or the project: a script's ``--help`` stays instant.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def parser(doc: str) -> argparse.ArgumentParser:
    """An ``ArgumentParser`` described by the first line of the script's docstring ``doc``."""
    return argparse.ArgumentParser(description=doc.splitlines()[0])


def training_subjects_args(doc: str, argv: list[str] | None) -> argparse.Namespace:
    """``--subjects N`` (training seeds 0..N-1, default 30) and ``--json PATH``, parsed from ``argv``:
    the whole command line of the scripts that measure the synthetic training subjects' colours."""
    ap = parser(doc)
    ap.add_argument("--subjects", type=int, default=30, help="training subjects (seeds 0..N-1)")
    ap.add_argument("--json", default=None, help="also write the figures here")
    return ap.parse_args(argv)


def frame_parser(doc: str, rounds: int) -> argparse.ArgumentParser:
    """The expression-prior frame benchmarks' first options: ``--model`` (default tiny) and
    ``--rounds`` (default ``rounds``); the script adds its own after them."""
    ap = parser(doc)
    ap.add_argument("--model", default="tiny")
    ap.add_argument("--rounds", type=int, default=rounds)
    return ap


def add_threads_and_clock(ap: argparse.ArgumentParser) -> None:
    """``--threads N`` (0: leave the defaults) and ``--clock wall|cpu`` (default wall)."""
    ap.add_argument("--threads", type=int, default=0, help="torch and rasterizer threads (0: leave the defaults)")
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                    help="cpu: this thread's CPU time (with --threads 1 every stage runs on it; steadier on a loaded machine)")  # fmt: skip


def set_threads(n: int) -> None:
    """Run torch and the CPU rasterizer on ``n`` threads (0: leave the defaults). Call after numba and
    torch are imported."""
    if not n:
        return
    import os

    import numba
    import torch

    os.environ["FASTGHA_NUMBA_THREADS"] = str(n)
    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))  # the rasterizer restores it after each render
    torch.set_num_threads(n)  # after numba: starting numba's OpenMP pool resets torch's count


def write_json(path: str | Path | None, report, indent: int = 2) -> None:
    """Write ``report`` as JSON to ``path`` (its folder created) when a path was given (``--json``)."""
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps(report, indent=indent))
