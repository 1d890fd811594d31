"""Held-out synthetic evaluation with view blending off and on (``model/viewblend.py``, issue 17).

The same evaluation as ``python -m fastgha_core.cli eval --model tiny --subjects 4 --resolution 256
--no-faces`` (the network-depth path), once per ``--taus`` value of
``GaussianHeadConfig.view_blend_tau_deg`` (0 = off), with ``view_blend_surface_only`` off so that
these avatars (no tracked surface) carry per-view data, with mean PSNR / SSIM per value:

    python bench/view_blend_synthetic.py --taus 0,10,20,30
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="tiny", help="preset name or model folder (default: tiny)")
    ap.add_argument("--subjects", type=int, default=4, help="held-out synthetic subjects (default 4)")
    ap.add_argument("--resolution", type=int, default=256, help="render resolution in pixels (default 256)")
    ap.add_argument("--taus", default="0,20", help="comma-separated view_blend_tau_deg values in degrees, 0 = off (default 0,20)")
    ap.add_argument("--json", default=None, help="also write {tau: {psnr, ssim}} here")
    args = ap.parse_args(argv)
    try:
        taus = [float(t) for t in args.taus.split(",")]
    except ValueError:
        ap.error(f"--taus: expected comma-separated numbers of degrees (0,10,20), got {args.taus!r}")
    if any(t < 0 for t in taus):
        ap.error(f"--taus: degrees must be >= 0 (0 = off), got {args.taus!r}")
    sys.path.insert(0, str(REPO))
    import fastgha_core  # noqa: F401
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.train.builders import build_eval_sources
    from fastgha_core.train.evaluate import EvalConfig, evaluate

    model = load_model(args.model)
    model.config.gaussians.view_blend_surface_only = False  # record per-view data on the network-depth path too
    cfg = EvalConfig(resolution=args.resolution)
    res = args.resolution or int(model.config.render_size)
    sources = build_eval_sources("synthetic-heldout", args.subjects, resolution=max(res, int(model.config.input_size)), num_cameras=max(16, cfg.num_inputs + cfg.num_target_views))
    out = {}
    for tau in taus:
        model.config.gaussians.view_blend_tau_deg = tau
        rep = evaluate(model, sources, cfg)
        out[tau] = {k: rep["summary"].get(k) for k in ("psnr", "ssim")} if "summary" in rep else rep
        print(json.dumps({"tau_deg": tau, **out[tau]}), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
