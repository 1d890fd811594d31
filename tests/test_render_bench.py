"""``fastgha bench``: dispatcher and the render target on a tiny configuration."""

from __future__ import annotations

import json

from fastgha_core.bench.render import head_scene
from fastgha_core.cli import main


def test_bench_render_writes_json(tmp_path, capsys):
    out = tmp_path / "b.json"
    rc = main(["bench", "render", "--quick", "--render-sizes", "1500", "--render-resolutions", "48",
               "--render-repeats", "1", "--render-budget", "600", "--json", str(out)])  # every baseline runs
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


def test_quick_plan_is_a_small_smoke_run():
    import argparse

    from fastgha_core.bench import render as rb

    quick = rb.plan(argparse.Namespace(quick=True, render_sizes=None, render_resolutions=None, render_repeats=None, render_budget=None))
    full = rb.plan(argparse.Namespace(quick=False, render_sizes=None, render_resolutions=None, render_repeats=None, render_budget=None))
    assert max(quick["sizes"]) <= 65_536 and quick["resolutions"] == (256,) and quick["repeats"] <= 3
    assert quick["budget"] <= 2.0 < full["budget"]  # slow baselines only when one repeat is predicted short
    assert len(quick["sizes"]) * len(quick["resolutions"]) < len(full["sizes"]) * len(full["resolutions"])
    explicit = rb.plan(argparse.Namespace(quick=True, render_sizes="500", render_resolutions="32", render_repeats=1, render_budget=9.0))
    assert explicit == {"sizes": (500,), "resolutions": (32,), "repeats": 1, "budget": 9.0}


def test_rows_are_printed_as_entries_finish(monkeypatch):
    """Output appears cell by cell: every timed entry's value is written before the next entry starts."""
    import io
    import sys

    from fastgha_core.bench import render as rb

    events: list[tuple[str, str]] = []

    class Recorder(io.StringIO):
        def write(self, s):
            events.append(("out", s))
            return super().write(s)

    real = rb._median_time

    def timed(fn, repeats):
        events.append(("measure", ""))
        return real(fn, repeats)

    monkeypatch.setattr(rb, "_median_time", timed)
    monkeypatch.setattr(sys, "stdout", Recorder())
    assert main(["bench", "render", "--quick", "--render-sizes", "800,1200", "--render-resolutions", "32",
                 "--render-repeats", "1", "--render-budget", "0"]) == 0  # budget 0: only the cpu backend is timed
    kinds = [k for k, s in events if k == "measure" or s.strip()]
    measures = [i for i, k in enumerate(kinds) if k == "measure"]
    assert len(measures) == 4  # 2 sizes x (forward, forward+backward) on the cpu backend
    for a, b in zip(measures, measures[1:]):
        assert "out" in kinds[a + 1 : b], "an entry's value was not printed before the next entry started"
    text = "".join(s for k, s in events if k == "out")
    rows = [line for line in text.splitlines() if line.strip().startswith(("800 ", "1200 "))]
    assert len(rows) == 2 and all(line.count("skipped") == 4 for line in rows)


def test_reference_prediction_scales_by_the_splats_the_full_image_sees(monkeypatch):
    """The dense reference evaluates every visible splat at every pixel, and the 64x64 calibration
    crop sees only the middle of the head: the prediction multiplies the crop's time by the pixel
    ratio *and* the visible-splat ratio (by pixels alone it predicted 5 s for an entry of 35-68 s)."""
    import fastgha_core.bench.render as R

    g = R.head_scene(3000)
    full, crop = R.bench_camera(256), R.bench_camera(256).crop(96, 96, 64, 64)
    n_full, n_crop = R._visible(g, full), R._visible(g, crop)
    assert n_full == 3000 and 0 < n_crop < n_full  # the whole head is in frame, the crop sees part of it
    ticks = iter([10.0, 11.0] * 2)  # every calibration render "takes" 1 s
    monkeypatch.setattr(R.time, "perf_counter", lambda: next(ticks))
    monkeypatch.setattr(R, "_forward", lambda g, cams, backend: (lambda: None))
    assert R._predict(g, 256, "torch_tiles", "forward") == 16.0  # pixels only
    assert R._predict(g, 256, "reference", "forward") == 16.0 * n_full / n_crop


def test_bench_count_options_refuse_zero_and_negative(capsys):
    import pytest

    for argv in (["bench", "render", "--render-repeats", "0"], ["bench", "mlp", "--mlp-gaussians", "-1"],
                 ["bench", "recon", "--recon-repeats", "0"], ["bench", "frame", "--frame-heldout", "-1"]):
        with pytest.raises(SystemExit) as e:  # argparse: usage line, exit 2, before any work
            main(argv)
        assert e.value.code == 2
        assert "expected an integer >=" in capsys.readouterr().err
