"""Reconstruction time on the tracked head surface against the network's depth (issue 17), interleaved.

Tracks the first 4 photos of a real set (``$FASTGHA_REALSETS`` or ``../shared/realsets``; not part of
the repository, so the script says so and exits 0 when it is absent), then times
``model.reconstruct(..., expressions=tracked)`` with and without ``surface=HeadSurface.from_tracking``,
alternating, and prints the medians (the first round is a warm-up).

    python bench/surface_recon_ab.py --set phone-5 --rounds 8
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="tiny")
    ap.add_argument("--set", default="phone-5", help="real set (folder name)")
    ap.add_argument("--rounds", type=int, default=8)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    import fastgha_core  # noqa: F401  (OpenMP defaults before torch)
    import torch

    from fastgha_core.model.fastgha import load_model
    from fastgha_core.model.surface import HeadSurface
    from fastgha_core.refine.realsets import _load_photos, realsets_root
    from fastgha_core.tracking import track_photos
    from fastgha_core.tracking.pipeline import TrackConfig

    folder = realsets_root() / args.set
    if not folder.is_dir():
        print(f"no real photo set at {folder}: skipped")
        return 0
    model = load_model(args.model)
    photos, names = _load_photos(folder)
    tr = track_photos(photos[:4], TrackConfig(size=256), names=names[:4])
    crops = torch.from_numpy(tr.crops).permute(0, 3, 1, 2).float() / 255.0
    x, c = model.prepare(crops, tr.cameras, torch.from_numpy(tr.masks)[:, None])
    expr = torch.from_numpy(tr.expressions)
    surface = HeadSurface.from_tracking(tr)
    times: dict[str, list[float]] = {"network depth": [], "tracked surface": []}
    for r in range(args.rounds + 1):
        order = [("network depth", None), ("tracked surface", surface)]
        for name, s in order if r % 2 == 0 else order[::-1]:
            t0 = time.perf_counter()
            model.reconstruct(x, c, expressions=expr, surface=s)
            if r:  # round 0 warms up
                times[name].append(time.perf_counter() - t0)
    print(f"reconstruct {len(names[:4])} views of {args.set}: " + ", ".join(f"{k} {statistics.median(v):.3f} s" for k, v in times.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
