"""What the demo's test-time refinement changes on the shipped samples: orbit PSNR, dlib CSIM and AKD, frame time.

For every shipped sample (``fastgha_core/assets/samples``): the feed-forward avatar of its 4 photos
and the same avatar refined as ``fastgha demo`` refines it (``--steps``, default 60, the preset
``refine_config_for`` picks, the photos' own expressions from ``request/info.json``), each drawn
along the sample's orbit at its expressions and scored against the ground truth: PSNR, and dlib's
CSIM (cosine similarity of the 128-d face descriptors) and AKD (mean distance of the 68 landmarks,
pixels) over the frames where dlib finds the ground truth's face (``train.faces.FaceMetrics``, as
``fastgha eval`` scores them; needs the ``faces`` extra, else those columns are empty). Then the
two avatars' frames (``animate`` + ``render`` in inference mode, as the server draws them) are
timed interleaved, ``--rounds`` passes over the orbit, alternating which goes first: median ms and
the ratio refined / feed-forward.

``--expressions`` picks the photos' expressions the refinement animates the avatar to: ``info``
(the sample's own, as ``fastgha demo`` refines), ``fitted`` (fitted through the photos' cameras by
``server.tracking.PhotoTracker.fit_known_cameras``, as the server refines photos posted with
cameras; needs the ``faces`` extra) or ``none``.

    python bench/demo_refinement.py --json out/demo_refinement.json
    python bench/demo_refinement.py --expressions fitted     # the server's path for photos with cameras
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/: _bench_cli (tests load this file by path)

from _bench_cli import parser, write_json


def main(argv=None) -> int:
    ap = parser(__doc__)
    ap.add_argument("--model", default="tiny")
    ap.add_argument("--steps", type=int, default=60, help="refinement steps (the demo's default)")
    ap.add_argument("--rounds", type=int, default=3, help="timed passes over the first sample's orbit")
    ap.add_argument("--expressions", choices=("info", "fitted", "none"), default="info",
                    help="the photos' expressions the refinement uses: the sample's own (the demo's), fitted through the cameras (the server's), none")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)

    import fastgha_core  # noqa: F401  (its OpenMP defaults before torch, as the server does)
    import numpy as np
    import torch

    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.data.samples import list_samples, load_sample
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.refine import refine_avatar, refine_config_for
    from fastgha_core.render import render
    from fastgha_core.train.faces import load_face_metrics
    from fastgha_core.train.metrics import psnr

    model = load_model(args.model)
    faces = load_face_metrics()
    bg = torch.tensor(BACKGROUND_RGB)

    def frame(avatar, s, t):
        return render(model.animate(avatar, s.expressions[t], camera=s.orbit_cameras[t : t + 1]), s.orbit_cameras[t : t + 1], background=bg).rgb[0].clamp(0, 1)

    rows, timing = [], None
    for name in list_samples():
        s = load_sample(name)
        images, cams = model.prepare(s.request_images, s.request_cameras, s.request_masks)
        plain = model.reconstruct(images, cams)
        t_fit = time.perf_counter()
        expressions, fit_error = photo_expressions(s, args.expressions)
        fit_s = time.perf_counter() - t_fit if fit_error is not None else None
        refined = refine_avatar(model, plain, s.request_images, s.request_cameras, s.request_masks,
                                config=refine_config_for(plain, args.steps), expressions=expressions).avatar  # fmt: skip
        row = {"sample": name, "expressions": args.expressions, "fitted_expression_mae": fit_error, "fit_s": fit_s}
        with torch.inference_mode():
            for key, av in (("feed_forward", plain), ("refined", refined)):
                ps, cs, ak = [], [], []
                for t in range(len(s.expressions)):
                    rgb = frame(av, s, t)
                    ps.append(float(psnr(rgb[None], s.gt_frames[t][None])))
                    c, a = faces.compare(rgb, s.gt_frames[t]) if faces is not None else (None, None)
                    if c is not None:
                        cs.append(c)
                        ak.append(a)
                row[key] = {"psnr": float(np.mean(ps)), "csim": float(np.mean(cs)) if cs else None, "akd_px": float(np.mean(ak)) if ak else None, "face_frames": len(cs)}
            if timing is None:  # frame time, the two avatars interleaved over the first sample's orbit
                ms = {"feed_forward": [], "refined": []}
                for av in (plain, refined):
                    frame(av, s, 0)  # warm-up
                for r in range(args.rounds):
                    for t in range(len(s.expressions)):
                        pair = (("feed_forward", plain), ("refined", refined))
                        for key, av in pair if (t + r) % 2 == 0 else pair[::-1]:
                            t0 = time.perf_counter()
                            frame(av, s, t)
                            ms[key].append(1e3 * (time.perf_counter() - t0))
                med = {k: statistics.median(v) for k, v in ms.items()}
                timing = {"sample": name, "frames_each": len(ms["refined"]), "median_ms": med, "ratio_refined": med["refined"] / med["feed_forward"]}
        rows.append(row)
        f, r_ = row["feed_forward"], row["refined"]
        fmt = lambda x, spec: "n/a" if x is None else format(x, spec)  # noqa: E731
        fit = "" if fit_error is None else f"   (fitted expressions in {fit_s:.1f} s: mean |error| {fit_error:.3f})"
        print(f"{name}: PSNR {f['psnr']:.2f} -> {r_['psnr']:.2f} dB   CSIM {fmt(f['csim'], '.3f')} -> {fmt(r_['csim'], '.3f')}   "
              f"AKD {fmt(f['akd_px'], '.2f')} -> {fmt(r_['akd_px'], '.2f')} px ({r_['face_frames']} frames with a face){fit}", flush=True)  # fmt: skip
    if timing is not None:
        m = timing["median_ms"]
        print(f"frame time ({timing['sample']}, {timing['frames_each']} interleaved frames each): feed-forward {m['feed_forward']:.1f} ms, "
              f"refined {m['refined']:.1f} ms, ratio {timing['ratio_refined']:.3f}")  # fmt: skip
    write_json(args.json, {"steps": args.steps, "expressions": args.expressions, "samples": rows, "timing": timing})
    return 0


def photo_expressions(s, how: str):
    """``(expressions [V, E] or None, mean absolute error of fitted ones against the sample's own or None)``
    for ``--expressions`` ``how`` on sample ``s`` (``data.samples.Sample``).

    Raises:
        SystemExit: ``fitted`` without the ``faces`` extra, or when no photo shows a face.
    """
    if how == "info":
        return s.request_expressions, None
    if how == "none":
        return None, None
    from server.tracking import PhotoTracker

    images = list(s.request_images.unbind(0))
    surface = PhotoTracker().fit_known_cameras(images, [s.request_cameras[i : i + 1] for i in range(len(images))],
                                               masks=list(s.request_masks.unbind(0)))  # fmt: skip
    if surface is None:
        raise SystemExit("--expressions fitted: no head fitted through the cameras (is the faces extra installed?)")
    import torch

    fitted = torch.from_numpy(surface.expressions).float()
    return fitted, float((fitted - s.request_expressions.float()).abs().mean())


if __name__ == "__main__":
    raise SystemExit(main())
