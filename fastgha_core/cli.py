"""The ``fastgha`` console script.

Each subcommand is one module in ``fastgha_core/commands/`` that defines::

    NAME = "reconstruct"            # the subcommand
    HELP = "one line for --help"
    def add_arguments(parser): ...  # argparse options
    def run(args) -> int: ...       # heavy imports go inside run()

A module may also set ``QUIET_NATIVE_LOGS = True`` when it runs MediaPipe: its C++ start-up lines are
then dropped from stderr (``commands/_stderr.py``; ``-v`` keeps them).

Modules are discovered, so adding a command touches no other file. A ``CLIError`` (or a
``ValueError``/``OSError`` from the library: a missing file, a full disk, a path that is not a
folder) prints one clear line and exits 2; ``-v`` adds the traceback. Commands check their output
paths before their work (``commands/_paths.py``).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys

from . import __version__, commands

__all__ = ["main", "console_main", "CLIError", "build_parser", "check_device"]


class CLIError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


def check_device(spec: str, what: str = "--device") -> str:
    """``spec`` when torch can use it here; ``CLIError`` saying what is available otherwise (a
    start-up traceback from deep inside torch was what a user got for ``--device cuda`` on a
    CPU-only install)."""
    import torch

    try:
        dev = torch.device(spec)
    except (RuntimeError, ValueError):
        raise CLIError(f"{what} {spec!r} is not a torch device; expected cpu, cuda or cuda:N") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            why = "this torch has no CUDA support" if torch.version.cuda is None else "no CUDA device is visible"
            raise CLIError(f"{what} {spec!r}: {why} (torch {torch.__version__}); use cpu (README: CUDA users)")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise CLIError(f"{what} {spec!r}: only {torch.cuda.device_count()} CUDA device(s) here (cuda:0..)")
    elif dev.type != "cpu":
        raise CLIError(f"{what} {spec!r}: expected cpu, cuda or cuda:N")
    return spec


def _command_modules():
    mods = []
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{commands.__name__}.{info.name}")
        if hasattr(mod, "NAME") and hasattr(mod, "run"):
            mods.append(mod)
    return mods


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fastgha",
        description="FastGHA: few-shot 3D Gaussian head avatars, reconstructed once and animated in real time.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--version", action="version", version=f"fastgha {__version__}", help="print the version and exit (`fastgha version --all`: also its dependencies)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _command_modules():
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.HELP)
        if hasattr(mod, "add_arguments"):
            mod.add_arguments(p)
        p.set_defaults(_run=mod.run, _quiet_native=bool(getattr(mod, "QUIET_NATIVE_LOGS", False)))
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "_run", None):
        parser.print_help()
        return 0
    from .commands._stderr import native_stderr_filtered

    try:
        # commands that run MediaPipe (QUIET_NATIVE_LOGS) drop its C++ start-up lines from stderr, unless -v
        with native_stderr_filtered(args._quiet_native and not args.verbose):
            rc = args._run(args)
    except (CLIError, ValueError, OSError) as e:
        if args.verbose:
            logging.getLogger("fastgha").exception("the error's traceback")
        print(f"fastgha {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"fastgha {args.command}: interrupted", file=sys.stderr)
        return INTERRUPTED
    return int(rc or 0)


INTERRUPTED = 130  # the shell's status for a command ended by SIGINT (128 + 2)


def console_main() -> None:
    """The ``fastgha`` console script: ``main()``, then exit with its status.

    After Ctrl-C the process ends at once (``os._exit``), once the command's ``finally`` blocks
    have closed its files and the streams are flushed, instead of waiting in interpreter shutdown on
    threads that were mid-work when the interrupt came. The segmentation faults users saw on Ctrl-C
    in ``fastgha train`` had another cause, scipy's KD-tree threads working on freed buffers (fixed in
    ``model.prior.nearest_neighbours``); this exit keeps a thread of that kind from ending an
    interrupted command any other way than with status 130."""
    import os

    rc = main()
    if rc == INTERRUPTED:
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(rc)
    sys.exit(rc)


if __name__ == "__main__":  # pragma: no cover
    # `python -m fastgha_core.cli`: run the imported module's main, so that the CLIError the commands
    # raise (fastgha_core.cli.CLIError) is the class caught there, not a copy in __main__
    from fastgha_core.cli import console_main as _console_main

    _console_main()
