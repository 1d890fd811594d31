"""The command-line plumbing the bench scripts share: their parsers' common options, ``--json``
output, ``--threads`` and ``--isa``.

A script imports it after putting its own folder on ``sys.path`` (``python bench/x.py`` has it
there already; tests load the scripts by file path, which does not)::

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _bench_cli import parser, write_json

Nothing here imports torch or the project: a script's ``--help`` stays instant.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

ISA_ENV = "FASTGHA_BENCH_ISA"  # set in the re-run process by run_as_isa
# 64-bit x86 with AVX2 and FMA, no AVX-512 (LLVM's name for x86-64 microarchitecture level 3)
AVX2_CPU = "x86-64-v3"


def parser(doc: str) -> argparse.ArgumentParser:
    """An ``ArgumentParser`` described by the first paragraph of the script's docstring ``doc`` (argparse rewraps it)."""
    return argparse.ArgumentParser(description=doc.split("\n\n")[0])


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


def add_isa(ap: argparse.ArgumentParser) -> None:
    """``--isa host|avx2`` (default host): see ``run_as_isa``."""
    ap.add_argument("--isa", choices=("host", "avx2"), default="host",
                    help="avx2: compile and dispatch as an AVX2-only machine would (no AVX-512), on this one")  # fmt: skip


def avx2_env() -> dict[str, str] | None:
    """The environment that builds and dispatches for AVX2 only on this machine (``run_as_isa``), or
    ``None`` when this CPU has no AVX2: numba compiles for ``x86-64-v3`` with every AVX-512 feature
    off (``NUMBA_CPU_NAME`` / ``NUMBA_CPU_FEATURES``; numba caches such code apart from the host's),
    and torch, MKL and oneDNN dispatch their AVX2 kernels (``ATEN_CPU_CAPABILITY``,
    ``MKL_ENABLE_INSTRUCTIONS``, ``ONEDNN_MAX_CPU_ISA``)."""
    import llvmlite.binding as ll

    feats = ll.get_host_cpu_features()
    if not feats.get("avx2"):
        return None
    off = ("avx512", "avx10", "amx", "evex512")
    flags = ",".join(("-" if k.startswith(off) or not v else "+") + k for k, v in sorted(feats.items()))
    return {"NUMBA_CPU_NAME": AVX2_CPU, "NUMBA_CPU_FEATURES": flags, "ATEN_CPU_CAPABILITY": "avx2",
            "MKL_ENABLE_INSTRUCTIONS": "AVX2", "ONEDNN_MAX_CPU_ISA": "AVX2"}  # fmt: skip


def run_as_isa(isa: str, script: str | Path, argv: list[str] | None) -> None:
    """Re-run ``script`` with ``argv`` (``None``: this process's arguments) in a fresh process whose
    vector code is limited to ``isa``, and exit with its status; return at once for ``host`` or when
    this process already is that re-run.

    ``avx2``: the environment of ``avx2_env``. It measures what the code does with AVX2's sixteen
    256-bit registers on this core, not an AVX2 machine's clock or caches.

    Raises:
        SystemExit: this CPU has no AVX2.
    """
    if isa == "host" or os.environ.get(ISA_ENV) == isa:
        return
    import subprocess

    overrides = avx2_env()
    if overrides is None:
        raise SystemExit("--isa avx2: this CPU has no AVX2")
    env = {**os.environ, **overrides, ISA_ENV: isa}
    args = sys.argv[1:] if argv is None else list(argv)
    raise SystemExit(subprocess.call([sys.executable, str(script), *args], env=env))
