"""Output paths checked before a command does its work.

A command that writes ``--out a/b.safetensors`` where ``a`` is an existing *file* used to do all its
work (load the model, track, refine) and then die in ``mkdir`` with a ``FileExistsError`` traceback.
These checks run first and raise ``CLIError`` (one line, exit status 2) naming the option:

- ``output_file(path, "--out")``: ``path`` is a file to write; it must not be an existing folder, and
  its parent must be an existing folder or a path that ``mkdir(parents=True)`` can create;
- ``output_dir(path, "--out")``: ``path`` is a folder to write into; it must not be an existing file,
  and the same holds for its parents.

Neither creates anything: a command that fails later leaves no empty folders behind.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["output_file", "output_dir"]


def _check_folder(folder: Path, option: str, given: Path) -> None:
    """``CLIError`` unless ``folder`` is an existing writable folder or can be created as one;
    ``given`` is the user's path, for the message."""
    from ..cli import CLIError

    probe = folder
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    if not probe.is_dir():
        raise CLIError(f"{option} {given}: {probe} is a file, not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise CLIError(f"{option} {given}: {probe} is not writable")


def output_file(path: str | os.PathLike, option: str) -> Path:
    """``path`` as a ``Path`` when a file can be written there (parents created later by the command).

    Raises:
        CLIError: ``path`` is an existing folder, or a parent is a file or not writable.
    """
    from ..cli import CLIError

    p = Path(path)
    if p.is_dir():
        raise CLIError(f"{option} {p} is a folder; expected a file path")
    _check_folder(p.parent, option, p)
    return p


def output_dir(path: str | os.PathLike, option: str) -> Path:
    """``path`` as a ``Path`` when it is, or can be created as, a writable folder.

    Raises:
        CLIError: ``path`` or one of its parents is an existing file, or the nearest existing one is
            not writable.
    """
    p = Path(path)
    _check_folder(p, option, p)
    return p
