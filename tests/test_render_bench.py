"""``fastgha bench``: dispatcher and the render target on a tiny configuration."""

from __future__ import annotations

import json

from fastgha_core.bench.render import head_scene
from fastgha_core.cli import main


def test_bench_render_writes_json(tmp_path, capsys):
    out = tmp_path / "b.json"
    rc = main(["bench", "render", "--quick", "--render-sizes", "1500", "--render-resolutions", "48",
               "--render-repeats", "1", "--json", str(out)])
    assert rc == 0
    data = json.loads(out.read_text())
    row = data["render"]["rows"][0]
    assert row["n"] == 1500 and row["resolution"] == 48
    for backend in ("cpu", "torch_tiles", "reference"):
        for mode in ("forward", "forward_backward"):
            assert row[f"{backend}_{mode}_ms"] > 0
    assert "summary" in data and isinstance(data["summary"], dict)
    assert "render benchmark" in capsys.readouterr().out


def test_bench_unknown_or_missing_target_is_a_clear_error(capsys):
    import fastgha_core.bench as bench_pkg
    import pkgutil

    present = {m.name for m in pkgutil.iter_modules(bench_pkg.__path__)}
    missing = [t for t in ("recon", "frame", "mlp") if t not in present]
    if missing:
        assert main(["bench", missing[0]]) == 2
        assert "not available" in capsys.readouterr().err


def test_head_scene_is_head_sized():
    g = head_scene(4000)
    assert len(g) == 4000
    ext = g.means.abs().amax(0)
    assert 0.07 < float(ext[0]) < 0.1 and 0.1 < float(ext[1]) < 0.13
    g.validate_values()
