"""Cost of the mirrored virtual views (``model/mirror.py``, issue 17): Gaussians, reconstruction time and served-frame time, side by side.

One real photo set (``../shared/realsets`` or ``$FASTGHA_REALSETS``; skipped cleanly when absent)
is tracked once; its avatar from all photos is reconstructed on the tracked head surface with
mirroring off and on (each ``--rebuilds`` times, interleaved; median seconds), then the server's
``FrameRenderer.render`` (animate + view blending + render + JPEG, 256²) draws both avatars
interleaved frame by frame with the same expressions, at cameras sweeping -60..60 degrees of yaw.
Medians; timings on a shared machine are noisy: compare the ratio of one run.

    python bench/mirror_frame.py --set phone-5 --frames 60
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="tiny", help="preset name or model folder (default: tiny)")
    ap.add_argument("--set", default="phone-5", help="real photo set to build the avatar from (default: phone-5)")
    ap.add_argument("--frames", type=int, default=60, help="timed frames per setting (default 60; 2 more warm up)")
    ap.add_argument("--rebuilds", type=int, default=3, help="reconstructions per setting for the timing (default 3)")
    ap.add_argument("--min-yaw", type=float, default=None, help="mirror_min_yaw_deg of the 'on' avatar (default: the config's)")
    ap.add_argument("--drop-seen", type=float, default=None, help="mirror_drop_seen_deg of the 'on' avatar (default: the config's)")
    args = ap.parse_args(argv)
    if args.frames < 1 or args.rebuilds < 1:
        ap.error(f"expected --frames >= 1 and --rebuilds >= 1, got {args.frames} and {args.rebuilds}")
    sys.path.insert(0, str(REPO))
    import fastgha_core  # noqa: F401
    import torch

    from fastgha_core.cameras import Cameras
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.model.surface import HeadSurface
    from fastgha_core.refine.realsets import _load_photos, list_sets, realsets_root
    from fastgha_core.tracking import track_photos
    from fastgha_core.tracking.pipeline import TrackConfig
    from server.frames import FrameRenderer

    every = list_sets(realsets_root())
    sets = [s for s in every if s.name == args.set]
    if not every:  # the real sets are not on this machine: skip cleanly
        print(f"no real photo sets under {realsets_root()} (set FASTGHA_REALSETS): nothing to measure")
        return 0
    if not sets:  # a set name that is not there (a typo) is an error, not a silent skip
        print(f"mirror_frame.py: --set {args.set!r} is not a real photo set under {realsets_root()}; expected one of: "
              f"{', '.join(s.name for s in every)}", file=sys.stderr)  # fmt: skip
        return 2
    model = load_model(args.model)
    gc = model.config.gaussians
    if args.min_yaw is not None:
        gc.mirror_min_yaw_deg = args.min_yaw
    if args.drop_seen is not None:
        gc.mirror_drop_seen_deg = args.drop_seen
    photos, names = _load_photos(sets[0])
    tr = track_photos(photos, TrackConfig(size=256), names=names)
    crops = torch.from_numpy(tr.crops).permute(0, 3, 1, 2).float() / 255.0
    masks = torch.from_numpy(tr.masks)[:, None].float()
    bg = torch.tensor(BACKGROUND_RGB).view(1, 3, 1, 1)
    v = min(len(names), model.config.max_views)
    imgs, cams = model.prepare((crops * masks + bg * (1 - masks))[:v], tr.cameras[:v])
    head = HeadSurface.from_tracking(tr).subset(list(range(v)))
    expr = torch.from_numpy(tr.expressions).float()[:v]
    avatars, rec = {}, {False: [], True: []}
    for _ in range(args.rebuilds):
        for on in (False, True):
            gc.mirror_views = on
            t0 = time.perf_counter()
            avatars[on] = model.reconstruct(imgs, cams, expressions=expr, surface=head)
            rec[on].append(time.perf_counter() - t0)
    renderer = FrameRenderer(model, "cpu")
    gen = torch.Generator().manual_seed(2)
    n = args.frames + 2
    exprs = [0.3 * torch.rand(model.config.expression_dim, generator=gen) for _ in range(n)]
    frames = {False: [], True: []}
    for i, e in enumerate(exprs):
        yaw = math.radians(-60.0 + 120.0 * i / max(1, n - 1))
        cam = Cameras.look_at((math.sin(yaw), 0.05, math.cos(yaw)), fov_deg=20.0, width=256, height=256)
        for on in (False, True):
            t0 = time.perf_counter()
            renderer.render(avatars[on], e, cam, 85)
            if i >= 2:
                frames[on].append(1e3 * (time.perf_counter() - t0))
    vb = avatars[True].view_blend
    out = {
        "set": args.set,
        "views": v,
        "mirrored_views": 0 if vb is None else int(vb.directions.shape[0]) - v,
        "gaussians_off": len(avatars[False].gaussians),
        "gaussians_on": len(avatars[True].gaussians),
        "reconstruct_s_off": statistics.median(rec[False]),
        "reconstruct_s_on": statistics.median(rec[True]),
        "frame_ms_off": statistics.median(frames[False]),
        "frame_ms_on": statistics.median(frames[True]),
        "frame_ratio_on_off": statistics.median(frames[True]) / statistics.median(frames[False]),
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
