"""``fastgha bench recon|frame|mlp --quick``: they run and write the documented JSON keys.

No timing assertions (the machine is shared); sizes are cut down so the file stays quick.
"""

from __future__ import annotations

import json
import math

import pytest

from fastgha_core.cli import main

SUMMARY_KEYS = {"recon_s_4views", "fps_256", "fps_512", "per_frame_vs_rerun_ratio", "mlp_fraction_of_matmul", "bytes_per_avatar"}


def _bench(tmp_path, target: str, *options: str) -> dict:
    out = tmp_path / f"{target}.json"
    assert main(["bench", target, "--quick", "--json", str(out), *options]) == 0
    return json.loads(out.read_text())


def _positive(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and x > 0


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bench")
    return {
        "recon": _bench(tmp, "recon", "--recon-views", "1,4", "--recon-avatars", "1,2"),
        "frame": _bench(tmp, "frame", "--frame-views", "4", "--frame-resolutions", "256,512", "--frame-frames", "3", "--frame-compile", "off"),
        "mlp": _bench(tmp, "mlp", "--mlp-gaussians", "4096", "--mlp-batch", "2", "--mlp-compile", "off"),
    }


def test_summary_has_the_documented_keys(results):
    summary = {}
    for res in results.values():
        summary.update(res["summary"])
    assert SUMMARY_KEYS <= set(summary)
    for key in SUMMARY_KEYS:
        assert _positive(summary[key]), (key, summary[key])


def test_recon_rows_and_memory(results):
    r = results["recon"]["recon"]
    rows = {row["views"]: row for row in r["rows"]}
    assert set(rows) == {1, 4}
    # at most one reconstructed Gaussian per input pixel (the shipped model prunes background pixels');
    # the avatar's total adds the prior's appended Gaussians (shells, mouth interior, lids)
    side = results["recon"]["recon"].get("input_size", 128)
    rec = {v: row["reconstructed"] for v, row in rows.items()}
    assert 0 < rec[1] <= side * side and rec[1] < rec[4] <= 4 * side * side
    assert all(row["gaussians"] >= row["reconstructed"] for row in rows.values())
    mem = r["memory"]
    assert mem["per_avatar"]["bytes"] == mem["per_avatar"]["gaussian_bytes"] + mem["per_avatar"]["deform_cache_bytes"]
    probe = mem["process"]
    assert "error" not in probe, probe
    assert [row["avatars"] for row in probe["rows"]] == [1, 2]
    assert all(row["peak_rss_mib"] >= 0.98 * row["rss_mib"] > 0 for row in probe["rows"])  # KiB vs pages: rounding


def test_frame_breakdown_and_design_comparison(results):
    f = results["frame"]["frame"]
    assert {row["resolution"] for row in f["rows"]} == {256, 512}
    for row in f["rows"]:
        for stage in ("deform", "render", "quantize", "jpeg", "message"):
            assert _positive(row[f"{stage}_ms"]), stage
        assert row["jpeg_bytes"] > 0 and _positive(row["e2e_fps"])
    comp = f["design_comparison"]
    assert comp["rerun_frame_ms_256"] > comp["ours_frame_ms_256"]
    assert comp["ratio_256"] == pytest.approx(comp["rerun_frame_ms_256"] / comp["ours_frame_ms_256"])
    assert f["bf16"]["psnr_bf16_vs_fp32_db"] > 20
    assert f["prune"][0]["min_opacity"] == 0.0 and math.isinf(f["prune"][0]["psnr_vs_unpruned_db"])


def test_render_breakdown_names_every_kernel(results):
    rows = results["frame"]["frame"]["render_breakdown"]
    assert [r["resolution"] for r in rows] == [[256, 256], [512, 512]]
    for r in rows:
        for stage in ("project", "pack", "sort", "gather", "bin", "composite", "finish"):
            assert _positive(r[f"{stage}_ms"]), stage
        assert r["sum_ms"] == pytest.approx(sum(v for k, v in r.items() if k.endswith("_ms") and k != "sum_ms"))
        assert 0 < r["composited_splats"] <= r["gaussians"] and r["composited_splats"] <= r["intersections"]
    assert rows[1]["intersections"] > rows[0]["intersections"]  # larger splats in pixels: more tiles each


def test_bf16_and_pruning_against_ground_truth_on_held_out_frames(results):
    # the shipped model on a shipped held-out subject: bf16 may cost at most 0.1 dB (issue 10's budget)
    h = results["frame"]["frame"]["heldout"]
    assert h is not None and h["frames"] == 4
    assert h["psnr_db"]["fp32"] > 15, h  # a trained model, not a blob
    assert h["psnr_change_db"]["bf16"] > -0.1, h
    assert h["psnr_change_db"]["bf16"] == pytest.approx(h["psnr_db"]["bf16"] - h["psnr_db"]["fp32"])
    assert h["gaussians"]["prune_0.02"] < h["gaussians"]["fp32"]  # some Gaussians are nearly transparent
    assert math.isfinite(h["psnr_change_db"]["prune_0.02"])


def test_mlp_configurations_and_matmul_reference(results):
    m = results["mlp"]["mlp"]
    names = {row["config"] for row in m["rows"]}
    assert {"fp32_plain", "fp32_split", "bf16_split", "fp32_split_batch2"} <= names
    assert _positive(m["matmul_gflops"]["fp32"]) and _positive(m["matmul_gflops"]["bf16"])
    for row in m["rows"]:
        assert row["fraction_of_matmul"] == pytest.approx(row["gflops"] / m["matmul_gflops"][row["precision"]])
    plain = next(r for r in m["rows"] if r["config"] == "fp32_plain")
    split = next(r for r in m["rows"] if r["config"] == "fp32_split")
    assert split["gflop"] < plain["gflop"]  # the split skips the first layer's big matmul


def test_mlp_flop_count_by_hand():
    from fastgha_core.bench.mlp import mlp_flops
    from fastgha_core.config import DeformConfig
    from fastgha_core.model.deform import DeformationMLP

    d = DeformationMLP(8, 5, DeformConfig(hidden_size=16, num_layers=3, pe_freqs=2))  # input 8 + 15 + 5 = 28
    assert mlp_flops(d, 10, split=False) == 2 * 10 * (28 * 16 + 2 * 16 * 16 + 6 * 16)
    assert mlp_flops(d, 10, split=True) == 2 * (10 * (2 * 16 * 16 + 6 * 16) + 5 * 16) + 10 * 16
