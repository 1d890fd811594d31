"""``python -m fastgha_core.tracking.meshmap``: ``--pose`` rebuilds the pose table; ``--yaw``, the
name of the yaw-only table it replaced, still does so but is hidden from ``--help`` and warns."""

from __future__ import annotations

import numpy as np
import pytest

from fastgha_core.tracking import meshmap


@pytest.fixture
def fake_build(monkeypatch, tmp_path):
    """``build_pose_table`` replaced by a small table (the real one renders for ~30 s), written to tmp."""
    calls = []

    def build():
        calls.append(1)
        return {"yaw": np.array([0.0]), "pitch": np.array([0.0]), "vertex": np.zeros((1, 1, 2), dtype=np.int64)}

    monkeypatch.setattr(meshmap, "build_pose_table", build)
    monkeypatch.setattr(meshmap, "POSE_ASSET", tmp_path / "pose.npz")
    return calls, tmp_path / "pose.npz"


@pytest.mark.parametrize("flag,warns", [("--pose", False), ("--yaw", True)])
def test_pose_and_its_old_name_rebuild_the_pose_table(fake_build, capsys, flag, warns):
    calls, out = fake_build
    assert meshmap.main([flag]) == 0
    assert calls == [1] and out.is_file()
    err = capsys.readouterr().err
    assert ("--yaw is deprecated" in err and "use --pose" in err) == warns, err


def test_help_lists_pose_not_yaw(capsys):
    with pytest.raises(SystemExit):
        meshmap.main(["--help"])
    out = capsys.readouterr().out
    assert "--pose" in out and "--yaw" not in out
