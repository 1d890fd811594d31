"""Gaussians dataclass, 3DGS PLY files and avatar files."""

from __future__ import annotations

import math
import struct
import warnings

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement
from torch.testing import assert_close

from fastgha_core.cli import main as cli_main
from fastgha_core.constants import AVATAR_FORMAT_VERSION
from fastgha_core.gaussians import Gaussians
from fastgha_core.io import load_avatar_file, load_ply, save_avatar_file, save_ply

SH_C0 = 0.28209479177387814


def random_gaussians(n=64, f=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g)
    return Gaussians(
        means=torch.randn(n, 3, generator=g) * 0.1,
        quats=q / q.norm(dim=-1, keepdim=True),
        scales=torch.rand(n, 3, generator=g) * 0.01 + 1e-4,
        opacities=torch.rand(n, generator=g).clamp(0.001, 0.999),
        colors=torch.rand(n, 3, generator=g),
        features=torch.randn(n, f, generator=g) if f else None,
    )


# ---------------------------------------------------------------- dataclass
def test_shape_checks_and_ops():
    g = random_gaussians(10, 4)
    with pytest.raises(ValueError, match=r"Gaussians.colors must have shape \[10, 3\] for N=10, got \[10, 4\]"):
        Gaussians(g.means, g.quats, g.scales, g.opacities, torch.zeros(10, 4))
    with pytest.raises(ValueError, match=r"features must have shape \[N=10, F\], got \[9, 4\]"):
        g.replace(features=torch.zeros(9, 4))
    both = Gaussians.concat([g, g[:3]])
    assert len(both) == 13 and both.num_features == 4
    kept = g.prune(0.5)
    assert (kept.opacities >= 0.5).all() and len(kept) == int((g.opacities >= 0.5).sum())
    assert g.to(dtype=torch.float64).means.dtype == torch.float64
    with pytest.raises(ValueError, match="either all items have features or none do"):
        Gaussians.concat([g, g.replace(features=None)])


# ---------------------------------------------------------------- PLY
def test_ply_layout_by_hand(tmp_path):
    # One Gaussian with hand-computed file values.
    g = Gaussians(
        means=torch.tensor([[1.0, 2.0, 3.0]]),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
        scales=torch.tensor([[1.0, math.e, 0.5]]),
        opacities=torch.tensor([0.5]),
        colors=torch.tensor([[0.5, 0.5 + SH_C0, 0.5 - 2 * SH_C0]]),
    )
    path = tmp_path / "one.ply"
    save_ply(path, g, axes="fastgha")  # our world axes as they are
    v = PlyData.read(str(path))["vertex"]
    names = list(v.data.dtype.names)
    assert names == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                     "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]  # fmt: skip
    row = {k: float(v[k][0]) for k in names}
    assert (row["x"], row["y"], row["z"]) == (1.0, 2.0, 3.0)
    assert (row["nx"], row["ny"], row["nz"]) == (0.0, 0.0, 0.0)
    assert row["f_dc_0"] == pytest.approx(0.0, abs=1e-6)
    assert row["f_dc_1"] == pytest.approx(1.0, abs=1e-6)
    assert row["f_dc_2"] == pytest.approx(-2.0, abs=1e-6)
    assert row["opacity"] == pytest.approx(0.0, abs=1e-7)  # logit(0.5)
    assert row["scale_0"] == pytest.approx(0.0, abs=1e-7)
    assert row["scale_1"] == pytest.approx(1.0, abs=1e-6)  # log(e)
    assert row["scale_2"] == pytest.approx(math.log(0.5), abs=1e-6)
    assert [row[f"rot_{i}"] for i in range(4)] == [1.0, 0.0, 0.0, 0.0]
    assert all(v[k].dtype == np.float32 for k in names)


def test_ply_round_trip_exact_within_float32(tmp_path):
    g = random_gaussians(200, f=8, seed=1)
    # include the extremes of the opacity range
    g = g.replace(opacities=torch.cat([torch.tensor([0.0, 1.0]), g.opacities[2:]]))
    path = tmp_path / "avatar.ply"
    save_ply(path, g)
    h = load_ply(path)
    assert h.features is None and h.dtype == torch.float32
    assert_close(h.means, g.means, rtol=0, atol=0)
    assert_close(h.colors, g.colors, rtol=0, atol=2e-7)
    assert_close(h.opacities, g.opacities, rtol=0, atol=2e-7)
    # log-scales near -9 are stored in float32 (half an ulp = 4.8e-7), so exp() inherits that relative error
    assert_close(h.scales, g.scales, rtol=1e-6, atol=0)
    assert_close(h.quats, g.quats, rtol=0, atol=2e-7)


def _write_degree3_ply(path, n, seed):
    rng = np.random.default_rng(seed)
    props = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
    props += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    arr = np.zeros(n, dtype=[(p, "f4") for p in props])
    vals = {}
    for p in props:
        arr[p] = vals[p] = rng.normal(size=n).astype(np.float32)
    arr["f_dc_0"] = vals["f_dc_0"] = np.array([0.0, 10.0, -10.0][:n], dtype=np.float32)  # colour 0.5 / clamp 1 / clamp 0
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(path))
    return vals


def test_read_degree3_ply_from_other_tool(tmp_path):
    path = tmp_path / "gs3.ply"
    vals = _write_degree3_ply(path, 3, seed=2)
    with pytest.warns(UserWarning, match="SH degree 3; dropping the 45 higher-order"):
        g = load_ply(path, axes="fastgha")  # the values as stored
    assert len(g) == 3
    assert_close(g.means, torch.from_numpy(np.stack([vals["x"], vals["y"], vals["z"]], 1)))
    with pytest.warns(UserWarning):  # a file without our axes comment is a standard (COLMAP, y-down) file
        std = load_ply(path)
    assert_close(std.means, g.means * torch.tensor([-1.0, -1.0, 1.0]))
    # colour = 0.5 + C0 * f_dc, clamped to [0, 1]
    assert_close(g.colors[:, 0], torch.tensor([0.5, 1.0, 0.0]))
    assert_close(g.colors[:, 1], torch.from_numpy(np.clip(0.5 + SH_C0 * vals["f_dc_1"].astype(np.float64), 0, 1)).float())
    assert_close(g.opacities, torch.from_numpy(1.0 / (1.0 + np.exp(-vals["opacity"].astype(np.float64)))).float())
    assert_close(g.scales[:, 2], torch.from_numpy(np.exp(vals["scale_2"].astype(np.float64))).float())
    q = np.stack([vals[f"rot_{i}"] for i in range(4)], 1).astype(np.float64)
    assert_close(g.quats, torch.from_numpy(q / np.linalg.norm(q, axis=1, keepdims=True)).float())


def test_read_degree0_ply_has_no_warning(tmp_path):
    path = tmp_path / "d0.ply"
    save_ply(path, random_gaussians(5, 0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_ply(path)


def test_ply_errors(tmp_path):
    arr = np.zeros(2, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1")])
    path = tmp_path / "points.ply"
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(path))
    with pytest.raises(ValueError, match=r"not a 3DGS Gaussian PLY, missing properties \['f_dc_0'"):
        load_ply(path)
    bad = tmp_path / "garbage.ply"
    bad.write_bytes(b"not a ply at all")
    with pytest.raises(ValueError, match="cannot parse"):
        load_ply(bad)
    with pytest.raises(FileNotFoundError):
        load_ply(tmp_path / "missing.ply")


# ---------------------------------------------------------------- avatar files
def test_avatar_file_round_trip(tmp_path):
    g = random_gaussians(50, f=32, seed=3)
    extra = {"bbox": torch.tensor([[-0.1, -0.2, -0.3], [0.1, 0.2, 0.3]]), "ids": torch.arange(5)}
    path = tmp_path / "a.safetensors"
    save_avatar_file(path, g, {"model_name": "tiny", "expression_space": "ict53", "note": "hi"}, extra)
    h, meta, ex = load_avatar_file(path)
    for name in ("means", "quats", "scales", "opacities", "colors", "features"):
        assert torch.equal(getattr(h, name), getattr(g, name)), name
    assert meta == {"model_name": "tiny", "expression_space": "ict53", "note": "hi", "format_version": str(AVATAR_FORMAT_VERSION)}
    assert set(ex) == {"bbox", "ids"} and torch.equal(ex["ids"], extra["ids"]) and torch.equal(ex["bbox"], extra["bbox"])
    plain = tmp_path / "plain.txt"
    plain.write_text("x")  # the mode any file gets under this umask (safetensors' save_file made 0600)
    assert path.stat().st_mode & 0o777 == plain.stat().st_mode & 0o777


def test_avatar_file_errors(tmp_path):
    g = random_gaussians(4, f=0)
    with pytest.raises(ValueError, match=r"must contain \['model_name', 'expression_space'\], missing \['expression_space'\]"):
        save_avatar_file(tmp_path / "x.safetensors", g, {"model_name": "tiny"})
    with pytest.raises(ValueError, match="dict of str -> str"):
        save_avatar_file(tmp_path / "x.safetensors", g, {"model_name": 3, "expression_space": "ict53"})
    # A file from a future format version.
    from safetensors.torch import save_file

    path = tmp_path / "future.safetensors"
    save_file({"gaussians.means": torch.zeros(1, 3)}, str(path), metadata={"format_version": "999"})
    with pytest.raises(ValueError, match=rf"format version '999', this FastGHA reads version {AVATAR_FORMAT_VERSION}"):
        load_avatar_file(path)
    plain = tmp_path / "plain.safetensors"
    save_file({"w": torch.zeros(2)}, str(plain))
    with pytest.raises(ValueError, match="not a FastGHA avatar file"):
        load_avatar_file(plain)
    partial = tmp_path / "partial.safetensors"
    save_file({"gaussians.means": torch.zeros(1, 3)}, str(partial), metadata={"format_version": str(AVATAR_FORMAT_VERSION)})
    with pytest.raises(ValueError, match=r"missing tensors \['gaussians.quats'"):
        load_avatar_file(partial)
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(struct.pack("<Q", 10) + b"{not json}")
    with pytest.raises(ValueError, match="cannot read as safetensors"):
        load_avatar_file(junk)
    with pytest.raises(FileNotFoundError):
        load_avatar_file(tmp_path / "none.safetensors")
    ply = tmp_path / "head.ply"  # the export given where the avatar is wanted (animate, export)
    save_ply(ply, random_gaussians(8, f=4, seed=0))
    with pytest.raises(ValueError, match=r"is a PLY point cloud; expected the \.safetensors avatar file written by `fastgha reconstruct`"):
        load_avatar_file(ply)


def test_export_command(tmp_path, capsys):
    g = random_gaussians(20, f=4, seed=4)
    src = tmp_path / "a.safetensors"
    save_avatar_file(src, g, {"model_name": "tiny", "expression_space": "ict53"})
    out = tmp_path / "out" / "a.ply"
    assert cli_main(["export", "--avatar", str(src), "--ply", str(out)]) == 0
    assert "20 Gaussians" in capsys.readouterr().out
    h = load_ply(out)
    assert_close(h.means, g.means, rtol=0, atol=0)
    assert cli_main(["export", "--avatar", str(tmp_path / "nope.safetensors"), "--ply", str(out)]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_export_counts_what_min_opacity_left_out(tmp_path, capsys):
    """``--min-opacity`` drops faint Gaussians; the summary counts them, not only the stray ones
    (it used to say "of N; 0 stray dropped" with hundreds fewer Gaussians written)."""
    g = random_gaussians(40, f=4, seed=6)
    src = tmp_path / "a.safetensors"
    save_avatar_file(src, g, {"model_name": "tiny", "expression_space": "ict53"})
    faint = int((g.opacities < 0.5).sum())
    assert 0 < faint < 40
    out = tmp_path / "a.ply"
    assert cli_main(["export", "--avatar", str(src), "--ply", str(out), "--min-opacity", "0.5", "--keep-outliers"]) == 0
    said = capsys.readouterr().out
    assert len(load_ply(out)) == 40 - faint
    assert f"{40 - faint} Gaussians (of 40; {faint} below --min-opacity 0.5, 0 stray dropped)" in said, said


def test_export_of_a_view_blended_avatar_says_the_ply_is_unweighted(tmp_path, capsys):
    """A tracked-head avatar is view-blended per frame; its PLY holds the plain opacities, and the
    export says so (a viewer shows all views' Gaussians at once). Older files say nothing."""
    import torch

    g = random_gaussians(20, f=4, seed=5)
    view = {"view.source": (torch.arange(20) % 2).to(torch.int8), "view.mask": torch.full((20,), 3, dtype=torch.uint8),
            "view.dirs": torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])}  # fmt: skip
    one = {"view.source": torch.zeros(20, dtype=torch.int8), "view.mask": torch.ones(20, dtype=torch.uint8), "view.dirs": torch.tensor([[0.0, 0.0, 1.0]])}
    save_avatar_file(tmp_path / "blended.safetensors", g, {"model_name": "tiny", "expression_space": "ict53"}, extra=view)
    save_avatar_file(tmp_path / "one.safetensors", g, {"model_name": "tiny", "expression_space": "ict53"}, extra=one)
    save_avatar_file(tmp_path / "plain.safetensors", g, {"model_name": "tiny", "expression_space": "ict53"})
    for name, noted in (("blended", True), ("one", False), ("plain", False)):
        out = tmp_path / f"{name}.ply"
        assert cli_main(["export", "--avatar", str(tmp_path / f"{name}.safetensors"), "--ply", str(out), "--keep-outliers"]) == 0
        said = capsys.readouterr().out
        assert ("unweighted opacities" in said) == noted, name
        assert ("one input view, so its frames are not view-blended" in said) == (name == "one"), said  # weights are all 1
        assert_close(load_ply(out).opacities, g.opacities, rtol=0, atol=1e-6)  # the file's own opacities, unweighted


# ---------------------------------------------------------------- PLY axes, outliers, compressed PLY
def test_ply_colmap_axes_by_hand_and_rotation_of_covariances(tmp_path):
    from fastgha_core.render.projection import quat_to_rotmat

    g = random_gaussians(50, f=0, seed=7)
    g = g.replace(means=torch.cat([torch.tensor([[0.01, 0.02, 0.03]]), g.means[1:]]),
                  quats=torch.cat([torch.tensor([[1.0, 0.0, 0.0, 0.0]]), g.quats[1:]]))  # fmt: skip
    path = tmp_path / "c.ply"
    save_ply(path, g)  # default: colmap (y down), what SuperSplat shows upright
    ply = PlyData.read(str(path))
    assert "fastgha_axes colmap" in ply.comments
    v = ply["vertex"]
    # 180 degrees about z: (x, y, z) -> (-x, -y, z); identity rotation -> q = (0, 0, 0, 1) (rotation about z by pi)
    assert [float(v[k][0]) for k in "xyz"] == pytest.approx([-0.01, -0.02, 0.03])
    assert [float(v[f"rot_{i}"][0]) for i in range(4)] == pytest.approx([0.0, 0.0, 0.0, 1.0])
    Rz = torch.diag(torch.tensor([-1.0, -1.0, 1.0]))
    q_file = torch.from_numpy(np.stack([np.asarray(v[f"rot_{i}"]) for i in range(4)], 1).astype(np.float32))
    S = torch.diag_embed(g.scales**2)
    R, Rf = quat_to_rotmat(g.quats), quat_to_rotmat(q_file)
    cov, cov_file = R @ S @ R.transpose(1, 2), Rf @ S @ Rf.transpose(1, 2)
    assert_close(cov_file, Rz @ cov @ Rz.T, rtol=1e-4, atol=1e-9)
    for axes in ("colmap", "fastgha"):  # both read back exactly (the comment says which)
        save_ply(tmp_path / f"{axes}.ply", g, axes=axes)
        h = load_ply(tmp_path / f"{axes}.ply")
        assert_close(h.means, g.means, rtol=0, atol=0)
        assert_close(h.quats, g.quats, rtol=0, atol=2e-7)
    # told otherwise, the reader reinterprets: a fastgha file read as colmap is turned by 180 degrees
    h = load_ply(tmp_path / "fastgha.ply", axes="colmap")
    assert_close(h.means, g.means @ Rz, rtol=0, atol=0)
    with pytest.raises(ValueError, match="axes must be one of"):
        save_ply(tmp_path / "x.ply", g, axes="opengl")


def test_drop_outliers_removes_strays_and_keeps_a_clean_head(tmp_path):
    from fastgha_core.io import drop_outliers

    head = random_gaussians(400, f=0, seed=3)  # means ~ N(0, 0.1^2): a head-sized cloud
    kept, n = drop_outliers(head)
    assert n == 0 and len(kept) == 400
    far = head.means[:3] * 0 + torch.tensor([[5.0, 0, 0], [0, -30.0, 0], [0.0, 0.0, 1e3]])
    big = head.scales[:1] * 0 + 2.0  # one splat 2 m wide
    g = Gaussians(
        means=torch.cat([head.means, far, torch.zeros(1, 3)]),
        quats=torch.cat([head.quats, head.quats[:4]]),
        scales=torch.cat([head.scales, head.scales[:3], big]),
        opacities=torch.cat([head.opacities, head.opacities[:4]]),
        colors=torch.cat([head.colors, head.colors[:4]]),
    )
    kept, n = drop_outliers(g)
    assert n == 4 and len(kept) == 400
    assert float(kept.means.abs().max()) < 1.0
    save_ply(tmp_path / "o.ply", g)  # the default drops them too
    h = load_ply(tmp_path / "o.ply")
    assert len(h) == 400 and float(h.means.abs().max()) < 1.0
    save_ply(tmp_path / "k.ply", g, outliers=False)
    assert len(load_ply(tmp_path / "k.ply")) == 404


def _pack(vals: np.ndarray, bits: tuple[int, ...]) -> np.ndarray:
    """Pack unit-range columns [N, k] into uint32 with the given bit widths (first column highest)."""
    out = np.zeros(len(vals), np.uint64)
    for j, b in enumerate(bits):
        q = np.round(np.clip(vals[:, j], 0, 1) * ((1 << b) - 1)).astype(np.uint64)
        out = (out << np.uint64(b)) | q
    return out.astype(np.uint32)


def test_read_supersplat_compressed_ply_hand_encoded(tmp_path):
    """SuperSplat's compressed layout, encoded here by hand: 300 Gaussians = 2 chunks of 256."""
    rng = np.random.default_rng(5)
    n = 300
    pos = rng.uniform(-0.1, 0.1, (n, 3))
    logs = rng.uniform(-6, -4, (n, 3))
    rgb = rng.uniform(0.1, 0.9, (n, 3))
    alpha = rng.uniform(0.2, 0.95, n)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    ci = np.arange(n) // 256
    chunks = []
    for c in range(2):
        s = ci == c
        lo_p, hi_p, lo_s, hi_s = pos[s].min(0), pos[s].max(0), logs[s].min(0), logs[s].max(0)
        chunks.append((*lo_p, *hi_p, *lo_s, *hi_s))
    ch = np.array(chunks)
    lo_p, hi_p, lo_s, hi_s = ch[ci, 0:3], ch[ci, 3:6], ch[ci, 6:9], ch[ci, 9:12]
    packed_pos = _pack((pos - lo_p) / (hi_p - lo_p), (11, 10, 11))
    packed_scale = _pack((logs - lo_s) / (hi_s - lo_s), (11, 10, 11))
    largest = np.abs(q).argmax(1)
    q = q * np.sign(q[np.arange(n), largest])[:, None]  # largest component positive
    rest = np.stack([np.delete(q[i], largest[i]) for i in range(n)])
    packed_rot = (largest.astype(np.uint32) << np.uint32(30)) | _pack(rest * (np.sqrt(2) * 0.5) + 0.5, (10, 10, 10))
    packed_col = _pack(np.concatenate([rgb, alpha[:, None]], 1), (8, 8, 8, 8))
    cdt = [(k, "<f4") for k in ("min_x", "min_y", "min_z", "max_x", "max_y", "max_z", "min_scale_x", "min_scale_y",
                                 "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z")]  # fmt: skip
    carr = np.array([tuple(r) for r in ch], dtype=cdt)
    varr = np.empty(n, dtype=[(k, "<u4") for k in ("packed_position", "packed_rotation", "packed_scale", "packed_color")])
    for k, val in zip(varr.dtype.names, (packed_pos, packed_rot, packed_scale, packed_col)):
        varr[k] = val
    path = tmp_path / "scene.compressed.ply"
    PlyData([PlyElement.describe(carr, "chunk"), PlyElement.describe(varr, "vertex")], byte_order="<").write(str(path))
    g = load_ply(path, axes="fastgha")  # values as stored
    span = (ch[:, 3:6] - ch[:, 0:3]).max()
    assert np.abs(g.means.numpy() - pos).max() < span / 1023 * 0.6 + 1e-6
    assert np.abs(np.log(g.scales.numpy()) - logs).max() < 2.0 / 1023 * 0.6 + 1e-5
    assert np.abs(g.colors.numpy() - rgb).max() < 0.6 / 255 + 1e-6
    assert np.abs(g.opacities.numpy() - alpha).max() < 0.6 / 255 + 1e-6
    dots = np.abs((g.quats.numpy().astype(np.float64) * q).sum(1))
    assert dots.min() > 1 - 2e-5  # same rotation (10-bit components)
    # without the chunk element the file is named, not called "not a 3DGS PLY"
    PlyData([PlyElement.describe(varr, "vertex")], byte_order="<").write(str(tmp_path / "broken.ply"))
    with pytest.raises(ValueError, match="compressed PLY needs its 'chunk' element"):
        load_ply(tmp_path / "broken.ply")


def test_viewer_settings_frame_the_head_from_the_front():
    from fastgha_core.io import viewer_settings

    head = random_gaussians(400, f=0, seed=3)
    head = head.replace(means=head.means + torch.tensor([0.0, 0.05, 0.0]))
    s = viewer_settings(head)
    cam = s["cameras"][0]["initial"]
    assert s["version"] == 2 and cam["fov"] == 35.0
    tgt, pos = np.array(cam["target"]), np.array(cam["position"])
    assert np.allclose(tgt, head.means.median(0).values.numpy(), atol=1e-4)  # viewer = our axes for colmap files
    d = pos - tgt
    assert d[0] == 0 and d[1] == 0 and 0.5 < d[2] < 3.0  # in front of the face (+z), about a metre away
    flipped = viewer_settings(head, axes="fastgha")["cameras"][0]["initial"]["target"]
    assert np.allclose(flipped, tgt * np.array([-1, -1, 1]), atol=1e-4)
