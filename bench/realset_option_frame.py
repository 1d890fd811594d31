"""Served frame time of real-photo avatars with one reconstruction option at two values, interleaved.

For each real set of ``$FASTGHA_REALSETS`` or ``../shared/realsets`` (not part of the repository: the
script says so and exits 0 when it is absent), tracks the photos as the server does (the turned photos
registered, 256²), builds the avatar of all of them (up to the model's ``max_views``) on the tracked
head surface once per value of ``GaussianHeadConfig.<option>``, then times one served frame
(``model.animate`` + ``render`` at 256², the first photo's camera, a 0.3 code on the first shape),
alternating the values, and prints each value's Gaussian count and median frame time (the first
``--warmup`` rounds are dropped) and the frame-rate ratio of the first value to the second.

    python bench/realset_option_frame.py --option off_head_extrude_m --values 0.10,0
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _value(text: str):
    """A command-line value: JSON where it parses (``0.1``, ``true``, ``"name"``), else the bare text (``forehead``)."""
    import json

    try:
        return json.loads(text)
    except ValueError:
        return text.strip()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="tiny")
    ap.add_argument("--sets", default="", help="comma-separated set names (default: every set)")
    ap.add_argument("--option", default="off_head_extrude_m", help="a GaussianHeadConfig field")
    ap.add_argument("--values", default="0.10,0", help="two comma-separated values of the option (JSON-like: 0.1, true, \"name\")")
    ap.add_argument("--rounds", type=int, default=25)
    ap.add_argument("--warmup", type=int, default=5)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    import fastgha_core  # noqa: F401  (OpenMP defaults before torch)
    import torch

    from fastgha_core.config import GaussianHeadConfig
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.model.surface import HeadSurface
    from fastgha_core.refine.realsets import _load_photos, realsets_root
    from fastgha_core.render import render
    from fastgha_core.tracking import track_photos
    from fastgha_core.tracking.pipeline import TrackConfig

    fields = {f.name for f in dataclasses.fields(GaussianHeadConfig)}
    if args.option not in fields:
        ap.error(f"--option {args.option!r} is not a GaussianHeadConfig field")
    raw = args.values.split(",")
    if len(raw) != 2:
        ap.error(f"--values needs two comma-separated values, got {args.values!r}")
    values = [_value(v) for v in raw]
    if not 0 <= args.warmup < args.rounds:
        ap.error("--warmup must be at least 0 and below --rounds")
    root = realsets_root()
    if not root.is_dir():
        print(f"no real photo sets at {root}: skipped")
        return 0
    names_ = [s for s in args.sets.split(",") if s] or sorted(p.name for p in root.iterdir() if p.is_dir())
    model = load_model(args.model)
    g_cfg = model.config.gaussians
    original = getattr(g_cfg, args.option)
    torch.set_grad_enabled(False)
    try:
        for set_name in names_:
            photos, names = _load_photos(root / set_name)
            tr = track_photos(photos, TrackConfig.with_photo_align("turned", size=256), names=names)
            keep = list(range(min(len(names), model.config.max_views)))
            crops = torch.from_numpy(tr.crops[keep]).permute(0, 3, 1, 2).float() / 255.0
            x, c = model.prepare(crops, tr.cameras[keep], torch.from_numpy(tr.masks[keep])[:, None].float())
            expr = torch.from_numpy(tr.expressions[keep]).float()
            surface = HeadSurface.from_tracking(tr).subset(keep)
            avatars = []
            for v in values:
                setattr(g_cfg, args.option, v)
                model.config.validate()
                avatars.append(model.reconstruct(x, c, expressions=expr, surface=surface))
            cam = tr.cameras[0:1]
            if (cam.width, cam.height) != (256, 256):
                cam = cam.resize(256, 256)
            code = torch.zeros(model.config.expression_dim)
            code[0] = 0.3
            times: list[list[float]] = [[], []]
            for r in range(args.rounds):
                for i in (0, 1) if r % 2 == 0 else (1, 0):
                    t0 = time.perf_counter()
                    render(model.animate(avatars[i], code, camera=cam), cam, background=BACKGROUND_RGB)
                    if r >= args.warmup:
                        times[i].append(time.perf_counter() - t0)
            m = [statistics.median(t) for t in times]
            print(
                f"{set_name}: {args.option}={values[0]!r}: {len(avatars[0].gaussians)} Gaussians, {1000 * m[0]:.1f} ms; "
                f"{args.option}={values[1]!r}: {len(avatars[1].gaussians)} Gaussians, {1000 * m[1]:.1f} ms; "
                f"frame-rate ratio {m[1] / m[0]:.3f}",
                flush=True,
            )
    finally:
        setattr(g_cfg, args.option, original)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
