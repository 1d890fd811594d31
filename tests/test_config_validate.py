"""``FastGHAConfig.validate``: the numeric fields of ``GaussianHeadConfig`` / ``DeformConfig`` and the
string options are range-checked, with a ``ValueError`` naming the field and the allowed range; the
shipped configs and presets pass; a model folder with a wrong value fails to load with that message,
in the library, the CLI and ``fastgha serve``."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from fastgha_core.config import PRESETS, FastGHAConfig, GaussianHeadConfig, DeformConfig, get_preset

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "fastgha_core" / "assets" / "models"

# (section, field, a wrong value, what the message must say about the allowed range)
BAD = [
    ("gaussians", "view_blend_expr_mm", -8.0, ">= 0"),
    ("gaussians", "view_blend_tau_deg", -20.0, "in [0, 360]"),
    ("gaussians", "view_blend_tau_deg", 400.0, "in [0, 360]"),
    ("gaussians", "view_blend_tau_deg", float("nan"), "in [0, 360]"),
    ("gaussians", "mirror_min_yaw_deg", -1.0, "in [0, 180]"),
    ("gaussians", "mirror_blend_offset_deg", -40.0, ">= 0"),
    ("gaussians", "mirror_midline_m", -0.01, ">= 0"),
    ("gaussians", "mirror_drop_seen_deg", -5.0, "in [0, 90]"),
    ("gaussians", "mirror_drop_seen_deg", 95.0, "in [0, 90]"),
    ("gaussians", "depth_range", 0.0, "> 0"),
    ("gaussians", "min_scale_px", 0.0, "> 0"),
    ("gaussians", "max_scale_px", 0.1, ">= 0.25"),  # below min_scale_px
    ("gaussians", "prune_opacity", 1.0, "in [0, 1)"),
    ("gaussians", "prune_opacity", -0.1, "in [0, 1)"),
    ("gaussians", "coverage_target", 1.5, "in [0, 1]"),
    ("gaussians", "edge_margin_px", -3.0, ">= 0"),
    ("gaussians", "depth_parity_sigma", -1.0, ">= 0"),
    ("gaussians", "head_on_colour_tol", -0.25, "in [0, 1]"),
    ("gaussians", "head_on_gain_deg", -15.0, "in [0, 180]"),
    ("gaussians", "head_on_tau_scale", 0.0, "> 0"),
    ("gaussians", "grazing_stretch", -1.0, ">= 0"),
    ("gaussians", "stereo_depth_mm", -2.0, ">= 0"),
    ("gaussians", "grazing_edge_px", -1, ">= 0"),
    ("gaussians", "grazing_edge_px", 2.5, "an integer"),
    ("gaussians", "grazing_min_ratio", -1.0, ">= 0"),
    ("gaussians", "grazing_keep_features_mm", -1.0, ">= 0"),
    ("gaussians", "feature_dim", -1, ">= 0"),
    ("gaussians", "flow_register_clip_px", 0.0, "> 0"),
    ("gaussians", "edge_mode", "color", "one of ['colour', 'fade']"),
    ("gaussians", "neck_cylinder", "on", "one of"),
    ("gaussians", "off_head_hull", "enter", "one of"),
    ("gaussians", "off_head_draw", "unde", "one of"),
    ("gaussians", "off_head_smooth", -0.1, "in [0, 1]"),
    ("gaussians", "off_head_smooth_axis", "horizontal", "one of ['vertical', 'both']"),
    ("gaussians", "off_head_smooth_hold", 1.5, "in [0, 1]"),
    ("gaussians", "off_head_extrude_m", -0.05, "in [0, 0.3]"),
    ("gaussians", "off_head_extrude_m", 0.5, "in [0, 0.3]"),
    ("deform", "hidden_size", 0, ">= 1"),
    ("deform", "num_layers", 0, ">= 1"),
    ("deform", "pe_freqs", -1, ">= 0"),
    ("deform", "pe_scale", 0.0, "> 0"),
    ("deform", "negative_slope", -0.01, "in [0, 1)"),
    ("deform", "prior_fade", (-0.006, 0.025), "prior_fade[0]"),
    ("deform", "prior_fade", (0.025, 0.006), "prior_fade[1] must be a number >= 0.025"),
    ("deform", "prior_fade", (0.006,), "two distances"),
    ("deform", "anchor_residual", "false", "true or false"),  # a truthy string used to turn it on
    ("gaussians", "flow_register", 1, "true or false"),
]


@pytest.mark.parametrize("section,name,value,rng", BAD, ids=[f"{s}.{n}={v!r}" for s, n, v, _ in BAD])
@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_a_wrong_value_names_the_field_and_its_range(preset, section, name, value, rng):
    cfg = get_preset(preset)
    setattr(getattr(cfg, section), name, value)
    with pytest.raises(ValueError) as err:
        cfg.validate()
    msg = str(err.value)
    assert msg.startswith(f"{section}.{name}"), msg
    assert rng in msg, msg
    # and the same value through from_dict (what a model folder's config.json goes through)
    d = get_preset(preset).to_dict()
    d[section][name] = list(value) if isinstance(value, tuple) else value
    with pytest.raises(ValueError, match=rf"^{section}\.{name}"):
        FastGHAConfig.from_dict(d)


# the legitimate edges: 0 = off where the comment says so, and the ends of each closed range
GOOD = [
    ("gaussians", "view_blend_tau_deg", 0.0),
    ("gaussians", "view_blend_tau_deg", 360.0),
    ("gaussians", "view_blend_expr_mm", 0.0),
    ("gaussians", "view_blend_expr_mm", 8.0),
    ("gaussians", "mirror_blend_offset_deg", 0.0),
    ("gaussians", "mirror_min_yaw_deg", 0.0),
    ("gaussians", "mirror_drop_seen_deg", 90.0),
    ("gaussians", "prune_opacity", 0.0),
    ("gaussians", "coverage_target", 0.0),
    ("gaussians", "coverage_target", 1.0),
    ("gaussians", "edge_margin_px", 0.0),
    ("gaussians", "head_on_colour_tol", 0.0),
    ("gaussians", "grazing_edge_px", 0),
    ("gaussians", "max_scale_px", 0.25),  # = min_scale_px: one fixed scale
    ("gaussians", "neck_cylinder", "below_ring"),
    ("gaussians", "off_head_hull", "middle"),
    ("gaussians", "off_head_draw", "headon_sharp"),
    ("gaussians", "edge_mode", "fade"),
    ("deform", "pe_freqs", 0),
    ("deform", "negative_slope", 0.0),
    ("deform", "prior_fade", (0.0, 0.0)),
    ("deform", "prior_fade", [0.006, 0.025]),
    ("deform", "anchor_residual", False),
    ("gaussians", "flow_register", True),
]


@pytest.mark.parametrize("section,name,value", GOOD, ids=[f"{s}.{n}={v!r}" for s, n, v in GOOD])
def test_legitimate_values_pass(section, name, value):
    cfg = get_preset("tiny")
    setattr(getattr(cfg, section), name, value)
    cfg.validate()


def test_shipped_configs_presets_and_defaults_validate():
    for name in sorted(PRESETS):
        get_preset(name).validate()
    FastGHAConfig(gaussians=GaussianHeadConfig(), deform=DeformConfig()).validate()
    shipped = sorted(MODELS.glob("*/config.json"))
    assert shipped, f"no shipped model configs under {MODELS}"
    for path in shipped:
        FastGHAConfig.from_dict(json.loads(path.read_text()))


def test_the_string_options_match_the_modes_their_users_accept():
    from fastgha_core import config
    from fastgha_core.commands import MAX_VIEW_BLEND_TAU_DEG
    from fastgha_core.model.surface import OFF_HEAD_DRAW_MODES, OFF_HEAD_SMOOTH_AXES

    assert config.OFF_HEAD_DRAW_MODES == OFF_HEAD_DRAW_MODES
    assert config.OFF_HEAD_SMOOTH_AXES == OFF_HEAD_SMOOTH_AXES
    assert config.MAX_VIEW_BLEND_TAU_DEG == MAX_VIEW_BLEND_TAU_DEG


# ---------------------------------------------------------------- a model folder with a wrong value
@pytest.fixture
def bad_model_folder(tmp_path):
    """The shipped tiny model copied with ``gaussians.view_blend_expr_mm = -8`` (the weights linked)."""
    folder = tmp_path / "bad-model"
    folder.mkdir()
    cfg = json.loads((MODELS / "tiny" / "config.json").read_text())
    cfg["gaussians"]["view_blend_expr_mm"] = -8.0
    (folder / "config.json").write_text(json.dumps(cfg, indent=2))
    try:
        os.symlink(MODELS / "tiny" / "model.safetensors", folder / "model.safetensors")
    except OSError:
        shutil.copy(MODELS / "tiny" / "model.safetensors", folder / "model.safetensors")
    return folder


def test_load_model_names_the_file_and_the_field(bad_model_folder):
    from fastgha_core import load_model

    with pytest.raises(ValueError) as err:
        load_model(str(bad_model_folder))
    msg = str(err.value)
    assert str(bad_model_folder / "config.json") in msg
    assert "gaussians.view_blend_expr_mm must be a number >= 0" in msg and "got -8.0" in msg


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}


def _one_line_error(proc) -> str:
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert "Traceback" not in proc.stderr, proc.stderr
    return proc.stderr


def test_cli_command_surfaces_the_field(bad_model_folder, tmp_path):
    """``fastgha eval --model FOLDER`` loads the model first: one line naming the field, exit 2."""
    proc = subprocess.run(
        [sys.executable, "-m", "fastgha_core.cli", "eval", "--model", str(bad_model_folder), "--subjects", "1", "--no-faces"],
        capture_output=True, text=True, env=_env(), cwd=tmp_path, timeout=300,
    )
    err = _one_line_error(proc)
    assert "gaussians.view_blend_expr_mm must be a number >= 0" in err, err


@pytest.mark.parametrize("via", ["flag", "env"])
def test_serve_refuses_the_folder_before_starting(bad_model_folder, tmp_path, via):
    """``fastgha serve --model FOLDER`` (or ``FASTGHA_MODEL=FOLDER``) exits at once with the field,
    instead of a start-up traceback after the port is bound."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cmd = [sys.executable, "-m", "fastgha_core.cli", "serve", "--host", "127.0.0.1", "--port", str(port),
           "--data-dir", str(tmp_path / "data"), "--no-warmup"]
    env = _env()
    if via == "flag":
        cmd += ["--model", str(bad_model_folder)]
    else:
        env["FASTGHA_MODEL"] = str(bad_model_folder)
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
    err = _one_line_error(proc)
    assert ("--model" if via == "flag" else "FASTGHA_MODEL") in err, err
    assert "gaussians.view_blend_expr_mm must be a number >= 0" in err, err


def test_training_config_from_a_folder_names_the_file_and_the_field(bad_model_folder):
    """``fastgha train --model FOLDER`` reads the config with ``model_config_from_spec``."""
    from fastgha_core.train.builders import model_config_from_spec

    with pytest.raises(ValueError, match=r"config\.json: gaussians\.view_blend_expr_mm must be a number >= 0"):
        model_config_from_spec(str(bad_model_folder))


def test_expression_dim_must_match_its_space():
    """A config with ``expression_space`` flame120 and ``expression_dim`` 53 validated, and the model
    failed at its first sample ("expression must have shape [B=1, E=53], got [1, 120]")."""
    from fastgha_core.config import FastGHAConfig, get_preset

    d = get_preset("tiny").to_dict()
    with pytest.raises(ValueError, match=r"expression_dim must be 120, the length of expression_space 'flame120''s codes, got 53"):
        FastGHAConfig.from_dict({**d, "expression_space": "flame120", "expression_dim": 53})
    with pytest.raises(ValueError, match=r"unknown expression space 'arkit'"):
        FastGHAConfig.from_dict({**d, "expression_space": "arkit"})
    assert FastGHAConfig.from_dict({**d, "expression_space": "flame120", "expression_dim": 120}).expression_dim == 120


def test_a_dataset_in_another_expression_space_is_refused_before_training(tmp_path):
    from types import SimpleNamespace

    from fastgha_core.train.builders import check_expression_space

    seqs = [SimpleNamespace(expression_space="ict53"), SimpleNamespace(expression_space="flame120")]
    with pytest.raises(ValueError, match=r"data: the sequences' expression space flame120 is not the model's 'ict53'"):
        check_expression_space(seqs, "ict53", "data")
    check_expression_space(seqs[:1], "ict53", "data")  # the same space passes
