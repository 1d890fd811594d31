"""MediaPipe's C++ start-up lines are dropped from the stderr of the commands that run it
(``fastgha_core/commands/_stderr.py``); everything else on stderr still arrives."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from extras import needs_faces

ROOT = Path(__file__).resolve().parents[1]
NOISE_LINES = [
    "INFO: Created TensorFlow Lite XNNPACK delegate for CPU.",
    "WARNING: All log messages before absl::InitializeLog() is called are written to STDERR",
    "W0000 00:00:1796068287.472275    4094 inference_feedback_manager.cc:114] Feedback manager requires a model with a "
    "single signature inference. Disabling support for feedback tensors.",
    "W0000 00:00:1796068287.487334    4093 landmark_projection_calculator.cc:186] Using NORM_RECT without IMAGE_DIMENSIONS "
    "is only supported for the square ROI. Provide IMAGE_DIMENSIONS or use PROJECTION_MATRIX.",
]


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}


def test_the_filter_drops_exactly_the_known_lines_and_passes_the_rest_through():
    """Written to fd 2 as C++ does (os.write, bypassing sys.stderr) and through sys.stderr, in
    pieces: the four known lines go, other lines (a real warning from the same C++ logger included),
    a tqdm-style ``\\r`` update without a newline and a last line without one arrive in order."""
    script = textwrap.dedent(
        f"""
        import os, sys
        from fastgha_core.commands._stderr import native_stderr_filtered
        noise = {NOISE_LINES!r}
        with native_stderr_filtered():
            os.write(2, b"before\\n")
            for line in noise:
                half = len(line) // 2
                os.write(2, line[:half].encode()); os.write(2, line[half:].encode() + b"\\n")
            os.write(2, b"W0000 00:00:1.0  1 other_calculator.cc:1] a real warning\\n")
            print("python line", file=sys.stderr)
            os.write(2, b"\\rrefining:  40%|####")
            os.write(2, b"\\rrefining: 100%|##########\\n")
            os.write(2, b"last without newline")
        print("after", file=sys.stderr)
        with native_stderr_filtered(enabled=False):
            os.write(2, (noise[0] + "\\n").encode())
        """
    )
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, env=_env(), timeout=120)
    assert r.returncode == 0, r.stderr.decode()
    assert r.stderr.decode() == (
        "before\n"
        "W0000 00:00:1.0  1 other_calculator.cc:1] a real warning\n"
        "python line\n"
        "\rrefining:  40%|####\rrefining: 100%|##########\n"
        "last without newline"
        "after\n" + NOISE_LINES[0] + "\n"
    )


@needs_faces
def test_fastgha_track_prints_no_mediapipe_chatter(tmp_path):
    """`fastgha track` on the README's example portrait used to print MediaPipe's XNNPACK / absl /
    W0000 lines between its own; its own lines and the result stay."""
    skimage_data = pytest.importorskip("skimage.data", reason="needs scikit-image (dev extra) for the portrait")
    from PIL import Image

    photo = tmp_path / "astronaut.png"
    Image.fromarray(skimage_data.astronaut()).save(photo)
    cmd = [sys.executable, "-m", "fastgha_core.cli", "track", "--images", str(photo), "--out", str(tmp_path / "req")]
    r = subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "tracked 1 photo(s)" in r.stderr and "landmark RMS" in r.stderr
    for marker in ("XNNPACK", "absl::InitializeLog", "inference_feedback_manager", "landmark_projection_calculator"):
        assert marker not in r.stderr, r.stderr
    assert (tmp_path / "req" / "head.json").is_file()
