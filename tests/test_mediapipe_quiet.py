"""MediaPipe's C++ start-up lines stay off stderr where the library itself builds its graphs
(``tracking/faces.py`` ``QuietGraph``, ``commands/_stderr.py`` ``mediapipe_start_up_quiet``): the
server tracks photos through it, outside any command's filter. Our own log lines still arrive."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from fastgha_core.commands._stderr import is_noise

ROOT = Path(__file__).resolve().parents[1]


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}


def _mediapipe_installed() -> bool:
    try:
        import mediapipe  # noqa: F401

        return True
    except ImportError:
        return False


def test_overlapping_blocks_in_two_threads_share_one_filter_and_restore_stderr():
    """Thread A enters, B enters, A leaves while B is inside, B leaves: the noise written by either
    while a block is open is dropped, the other lines arrive, and fd 2 is the real stderr again at
    the end (a second independent redirect would have left it pointing at a dead pipe)."""
    script = textwrap.dedent(
        """
        import os, sys, threading
        from fastgha_core.commands._stderr import mediapipe_start_up_quiet
        noise = b"INFO: Created TensorFlow Lite XNNPACK delegate for CPU.\\n"
        before = os.fstat(2)
        a_in, b_in, a_out = threading.Event(), threading.Event(), threading.Event()

        def a():
            with mediapipe_start_up_quiet():
                a_in.set(); b_in.wait()
                os.write(2, noise); os.write(2, b"from A\\n")
            a_out.set()

        def b():
            a_in.wait()
            with mediapipe_start_up_quiet():
                b_in.set(); a_out.wait()
                os.write(2, noise); os.write(2, b"from B\\n")

        ta, tb = threading.Thread(target=a), threading.Thread(target=b)
        ta.start(); tb.start(); ta.join(); tb.join()
        after = os.fstat(2)
        assert (before.st_dev, before.st_ino) == (after.st_dev, after.st_ino), "fd 2 not restored"
        os.write(2, noise)  # no block open: passes
        os.write(2, b"end\\n")
        """
    )
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, env=_env(), timeout=120)
    assert r.returncode == 0, r.stderr.decode()
    lines = r.stderr.decode().splitlines()
    assert sorted(lines[:2]) == ["from A", "from B"], lines
    assert lines[2:] == ["INFO: Created TensorFlow Lite XNNPACK delegate for CPU.", "end"], lines


_TRACK = textwrap.dedent(
    """
    import logging, sys
    import numpy as np, skimage.data
    logging.basicConfig(level=getattr(logging, sys.argv[1]), format="%(levelname)s %(name)s: %(message)s")
    from fastgha_core.tracking.faces import MeshDetector
    from fastgha_core.tracking.silhouette import person_mask
    img = np.ascontiguousarray(skimage.data.astronaut())
    det = MeshDetector()
    box, lm = det.detect_one(img, "astronaut")
    det.detect_one(img, "astronaut")
    mask = person_mask(img)
    logging.getLogger("fastgha_core.test").info("our own line: %d landmarks, mask mean %.2f", len(lm), float(mask.mean()))
    print("a print to stderr", file=sys.stderr)
    """
)


@pytest.mark.skipif(not _mediapipe_installed(), reason="needs mediapipe (the 'faces' extra)")
def test_face_mesh_and_segmentation_start_quietly_and_our_lines_stay():
    """Face Mesh (detector and landmark model) and selfie segmentation, built and run on a portrait
    outside any command: no start-up line reaches stderr, our log line and a print do. At DEBUG
    the same run shows them (so the check above could fail, and ``-v`` still has them)."""
    quiet = subprocess.run([sys.executable, "-c", _TRACK, "INFO"], capture_output=True, env=_env(), timeout=300)
    assert quiet.returncode == 0, quiet.stderr.decode()
    lines = quiet.stderr.decode().splitlines()
    assert not [ln for ln in lines if is_noise(ln.encode())], lines
    assert not [ln for ln in lines if ln.startswith("W0000")], lines
    assert any("our own line" in ln for ln in lines) and "a print to stderr" in lines, lines

    loud = subprocess.run([sys.executable, "-c", _TRACK, "DEBUG"], capture_output=True, env=_env(), timeout=300)
    assert loud.returncode == 0, loud.stderr.decode()
    assert [ln for ln in loud.stderr.decode().splitlines() if is_noise(ln.encode())], loud.stderr.decode()


def test_a_child_process_outliving_the_block_writes_to_stderr_not_to_a_reused_descriptor(tmp_path):
    """A child started inside the block inherits fd 2 (the pipe) and writes after the block has ended:
    its line reaches the real stderr through the reader, which owns the pipe and the saved stderr
    until the pipe ends; a file opened after the block (which used to get one of their reused numbers)
    receives nothing."""
    script = textwrap.dedent(
        f"""
        import os, subprocess, sys, threading
        from fastgha_core.commands import _stderr
        _stderr.DRAIN_TIMEOUT_S = 0.05  # do not wait for the child's pipe to end
        go = os.pipe()
        with _stderr.native_stderr_filtered():
            p = subprocess.Popen(["sh", "-c", "read x; echo CHILD-LATE-LINE >&2"], stdin=go[0])
        files = [open({str(tmp_path)!r} + f"/f{{i}}", "wb") for i in range(4)]
        os.write(go[1], b"go\\n"); p.wait()
        for t in threading.enumerate():
            if t.name == "fastgha-stderr-filter":
                t.join()
        for f in files:
            f.close()
        os.write(2, b"end\\n")
        """
    )
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, env=_env(), timeout=120)
    assert r.returncode == 0, r.stderr.decode()
    assert r.stderr.decode().splitlines() == ["CHILD-LATE-LINE", "end"], r.stderr.decode()
    assert [(tmp_path / f"f{i}").read_bytes() for i in range(4)] == [b""] * 4
