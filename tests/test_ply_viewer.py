"""Our PLY in the viewer people use: SuperSplat's HTML viewer, made by ``@playcanvas/splat-transform``
(pinned in ``tests/viewer/package.json``; ``npm ci --prefix tests/viewer`` installs it), rendered in
headless Chromium (Debian's ``/usr/bin/chromium``, driven by playwright).

A synthetic marker head (skin ellipsoid, the subject's left eye blue, right eye green, a red mouth)
is exported with the defaults of ``fastgha export`` and screenshotted: the eyes must be above the
mouth (upright), the blue eye on image right (a camera in front of the face sees the subject's left
on image right: not mirrored) and the head must fill a fair share of the frame (not a speck).
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from fastgha_core.gaussians import Gaussians
from fastgha_core.io import load_ply, save_avatar_file

ROOT = Path(__file__).resolve().parent.parent
SPLAT_TRANSFORM = ROOT / "tests" / "viewer" / "node_modules" / ".bin" / "splat-transform"
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"


def _skip_reason() -> str | None:
    if shutil.which("node") is None:
        return "needs node (apt install nodejs) for @playcanvas/splat-transform"
    if not SPLAT_TRANSFORM.exists():
        return "needs `npm ci --prefix tests/viewer` (@playcanvas/splat-transform)"
    if not Path(CHROMIUM).exists():
        return "needs Debian's chromium (/usr/bin/chromium)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "needs playwright (dev extra)"
    return None


pytestmark = pytest.mark.skipif(_skip_reason() is not None, reason=_skip_reason() or "")

SKIN = (0.85, 0.65, 0.5)
MARKERS = {"left_eye": ((0.035, 0.03, 0.08), (0.0, 0.0, 1.0)), "right_eye": ((-0.035, 0.03, 0.08), (0.0, 1.0, 0.0)),
           "mouth": ((0.0, -0.05, 0.075), (1.0, 0.0, 0.0))}  # fmt: skip


def marker_head(stray: bool = True) -> Gaussians:
    """A head in our world axes (+x subject's left, +y up, +z out of the face), 0.2 m tall."""
    g = torch.Generator().manual_seed(0)
    n = 3000
    d = torch.randn(n, 3, generator=g)
    d = d / d.norm(dim=-1, keepdim=True)
    means = [d * torch.tensor([0.075, 0.1, 0.08])]
    colors = [torch.tensor(SKIN).expand(n, 3)]
    scales = [torch.full((n, 3), 0.006)]
    for centre, col in MARKERS.values():
        m = 150
        means.append(torch.tensor(centre) + 0.006 * torch.randn(m, 3, generator=g))
        colors.append(torch.tensor(col).expand(m, 3))
        scales.append(torch.full((m, 3), 0.004))
    if stray:  # stray Gaussians far away: without outlier removal they blow up the bounding box
        means.append(torch.tensor([[3.0, -2.0, 1.5], [-40.0, 5.0, 2.0]]))
        colors.append(torch.tensor([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0]]))
        scales.append(torch.full((2, 3), 0.01))
    means_t = torch.cat(means)
    N = len(means_t)
    return Gaussians(
        means=means_t,
        quats=torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(N, 4).clone(),
        scales=torch.cat(scales),
        opacities=torch.full((N,), 0.95),
        colors=torch.cat(colors).clone(),
    )


def _screenshot(html: Path, out: Path) -> np.ndarray:
    from PIL import Image
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=CHROMIUM,
            args=["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"],
        )
        try:
            page = browser.new_page(viewport={"width": 480, "height": 480})
            page.goto(html.as_uri() + "?noui&noanim")
            page.wait_for_timeout(1500)
            prev = None
            for _ in range(20):  # until the splat has loaded and two frames agree
                page.wait_for_timeout(750)
                page.screenshot(path=str(out))
                img = np.asarray(Image.open(out).convert("RGB")).astype(np.int16)
                if prev is not None and img.max() > 0 and np.abs(img - prev).mean() < 0.5:
                    break
                prev = img
        finally:
            browser.close()
    return img


def _centroid(img: np.ndarray, rgb: tuple[float, float, float]) -> tuple[float, float, int]:
    target = np.array(rgb) * 255
    close = np.abs(img - target).max(axis=2) < 90
    other = [c for c in range(3) if rgb[c] == 0]
    close &= img[..., other].max(axis=2) < 110
    ys, xs = np.nonzero(close)
    return (float(xs.mean()) if len(xs) else math.nan, float(ys.mean()) if len(ys) else math.nan, int(len(xs)))


def _export(tmp_path: Path, head: Gaussians) -> tuple[Path, Path]:
    from fastgha_core.cli import main

    avatar = tmp_path / "head.safetensors"
    save_avatar_file(avatar, head, {"model_name": "test", "expression_space": "ict53"})
    ply, settings = tmp_path / "head.ply", tmp_path / "head.settings.json"
    assert main(["export", "--avatar", str(avatar), "--ply", str(ply), "--viewer-settings", str(settings)]) == 0
    return ply, settings


def test_exported_head_is_upright_unmirrored_and_framed_in_supersplat_viewer(tmp_path):
    ply, settings = _export(tmp_path, marker_head(stray=True))
    assert len(load_ply(ply)) == len(marker_head()) - 2  # the two stray Gaussians were dropped
    html = tmp_path / "head.html"
    r = subprocess.run([str(SPLAT_TRANSFORM), "-q", "-w", "-g", "cpu", str(ply), str(html), "--viewer-settings", str(settings)],
                       capture_output=True, text=True, timeout=300)  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    img = _screenshot(html, tmp_path / "head.png")
    h, w = img.shape[:2]
    lx, ly, ln = _centroid(img, MARKERS["left_eye"][1])
    rx, ry, rn = _centroid(img, MARKERS["right_eye"][1])
    mx, my, mn = _centroid(img, MARKERS["mouth"][1])
    assert min(ln, rn, mn) > 20, f"markers not found (pixels: left eye {ln}, right eye {rn}, mouth {mn})"
    assert ly < my and ry < my, f"upside down: eyes at y={ly:.0f},{ry:.0f}, mouth at y={my:.0f} (image y grows down)"
    assert lx > rx, f"mirrored: the subject's left eye at x={lx:.0f} should be right of the right eye at x={rx:.0f}"
    fg = img.max(axis=2) > 40
    ys, xs = np.nonzero(fg)
    assert (ys.max() - ys.min()) > 0.4 * h and (xs.max() - xs.min()) > 0.25 * w, "the head is a speck"


def test_compressed_ply_from_splat_transform_reads_back(tmp_path):
    head = marker_head(stray=False)
    ply, _ = _export(tmp_path, head)
    comp = tmp_path / "head.compressed.ply"
    r = subprocess.run([str(SPLAT_TRANSFORM), "-q", "-w", "-g", "cpu", str(ply), str(comp)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    back = load_ply(comp)  # SuperSplat's compressed layout; standard (colmap) axes
    assert len(back) == len(head)
    # splat-transform reorders Gaussians (Morton order): compare as point sets via nearest neighbours
    d = torch.cdist(back.means.double(), head.means.double())
    nn = d.argmin(dim=1)
    assert float(d.min(dim=1).values.max()) < 2e-3  # 11/10-bit quantisation of a ~0.2 m chunk
    assert (back.colors - head.colors[nn]).abs().max() < 0.02
    assert (back.scales / head.scales[nn]).log().abs().max() < 0.05
    assert (back.opacities - head.opacities[nn]).abs().max() < 0.01
    # identity rotations in our axes survive the 180 degree turn and back (up to sign)
    assert float((back.quats[:, 0].abs() - 1).abs().max()) < 0.01
    json.dumps(back.means[:1].tolist())
