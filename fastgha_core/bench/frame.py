"""``fastgha bench frame``: the per-frame path of one stream, and what re-running reconstruction would cost.

Per frame the server runs ``model.animate`` (deformation MLP, first layer cached on the avatar),
``render`` (CPU rasterizer), ``server.imaging.frame_to_uint8`` + ``encode_jpeg`` and
``server.protocol.pack_frame``. Each stage is timed on its own (median after warm-up), then the
real ``server.frames.FrameRenderer.render`` + ``pack_frame`` runs back to back for a number of
frames with changing expressions: ``fps = frames / elapsed`` (one stream, end to end).

Scenes: avatars reconstructed by the model from 1, 2, 4 and 6 views (``--frame-views``; the
number of Gaussians follows), rendered at 256² and 512² from the server's default camera.

Design comparison: a model conditioned on the expression inside the reconstruction network
(Avat3r-style) has to re-run reconstruction for every frame; its per-frame cost is
``reconstruct + render + encode``. ``per_frame_vs_rerun_ratio`` is that over ours (4 views, 256²).

The stages and the end-to-end loop run the MLP the way the server does (``--frame-precision`` and
``--frame-compile``, default ``auto`` like ``FASTGHA_MLP_PRECISION`` / ``FASTGHA_COMPILE``).

Optimisations measured side by side: bf16 autocast in the MLP (``animate(bf16=True)``: time, and
PSNR of the frame against fp32) and pruning transparent Gaussians (opacity below a threshold:
render time and PSNR against the unpruned render). With a shipped sample subject, both are also
scored against ground truth on its held-out frames (novel views and expressions): the PSNR of
fp32, bf16 and each pruning threshold, and their change from fp32 (``heldout``).
"""

from __future__ import annotations

import logging
import math
import time

import torch

from ._common import bench_avatar, bench_model, load_average, non_negative_int, positive_int, time_fn

log = logging.getLogger(__name__)

DEFAULT_VIEWS = (1, 2, 4, 6)
DEFAULT_RESOLUTIONS = (256, 512)
PRUNE_THRESHOLDS = (0.02, 0.05, 0.1)


def add_arguments(parser) -> None:
    parser.add_argument("--frame-model", default="tiny", help="model preset or folder (default tiny)")
    parser.add_argument("--frame-views", default=None, help="comma-separated input view counts, i.e. avatar sizes (default 1,2,4,6)")
    parser.add_argument("--frame-resolutions", default=None, help="comma-separated square output sizes (default 256,512)")
    parser.add_argument("--frame-frames", type=positive_int, default=None, help="frames in the end-to-end loop (default 60, --quick 10)")
    parser.add_argument("--frame-jpeg-quality", type=int, default=85, help="JPEG quality (default 85, the server default)")
    parser.add_argument("--frame-precision", choices=("auto", "fp32", "bf16"), default="auto",
                        help="deformation MLP precision, as FASTGHA_MLP_PRECISION (auto: timed fp32 vs bf16, as the server does at start-up)")
    parser.add_argument("--frame-compile", choices=("auto", "on", "off"), default="auto",
                        help="torch.compile the MLP, as FASTGHA_COMPILE (auto: when a C++ compiler is found)")
    parser.add_argument("--frame-heldout", type=non_negative_int, default=None, help="held-out sample frames scored against ground truth (default 16, --quick 4; 0 = skip)")


def _ints(text, default):
    from .recon import _ints as parse

    return parse(text, default, "frame option")


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    """PSNR in dB of two images in [0, 1] (inf when identical)."""
    mse = float(((a.float() - b.float()) ** 2).mean())
    return math.inf if mse == 0 else 10.0 * math.log10(1.0 / mse)


def _expressions(model, n: int, seed: int = 1) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    space = model.expression_space
    return [space.neutral() + 0.3 * torch.rand(space.dim, generator=g) for _ in range(n)]


def _with_live_deformation(model):
    """The model itself when trained; an untrained one has a zero output layer (identity deformation),
    which would make bf16 and timing checks trivial, so a copy gets small random output weights."""
    import copy

    if bool(model.deform.out.weight.abs().sum() > 0):
        return model, False
    m = copy.deepcopy(model)
    with torch.no_grad():
        gen = torch.Generator().manual_seed(0)
        m.deform.out.weight.copy_(0.01 * torch.randn(m.deform.out.weight.shape, generator=gen))
    return m, True


def heldout_quality(model, frames: int, thresholds=PRUNE_THRESHOLDS) -> dict | None:
    """PSNR against ground truth on a shipped sample's held-out frames: fp32, bf16 and pruned.

    The first sample subject is reconstructed from its 4 photos; ``frames`` frames of its expression
    sequence are rendered from its orbit cameras (novel views and expressions) at the ground truth's
    resolution. None when no sample is shipped."""
    from ..constants import BACKGROUND_RGB
    from ..data.samples import list_samples, load_sample
    from ..render import render

    if frames <= 0 or not list_samples():
        return None
    sample = load_sample()
    images, cams = model.prepare(sample.request_images, sample.request_cameras, sample.request_masks)
    with torch.inference_mode():
        avatar = model.reconstruct(images, cams)
    t_max = min(len(sample.expressions), sample.orbit_cameras.K.shape[0], len(sample.gt_frames))
    idx = torch.linspace(0, t_max - 1, min(frames, t_max)).round().long().tolist()
    variants = {"fp32": (False, 0.0), "bf16": (True, 0.0), **{f"prune_{t:g}": (False, t) for t in thresholds}}
    scores: dict[str, list[float]] = {k: [] for k in variants}
    counts: dict[str, int] = {}
    with torch.inference_mode():
        for t in idx:
            cam = sample.orbit_cameras[t : t + 1]
            gt = sample.gt_frames[t]  # [3, H, W]
            for name, (bf16, thr) in variants.items():
                g = model.animate(avatar, sample.expressions[t], bf16=bf16)
                if thr > 0:
                    g = g.prune(thr)
                counts[name] = len(g)
                rgb = render(g, cam, background=BACKGROUND_RGB).rgb[0]  # [3, H, W]
                scores[name].append(psnr(rgb, gt))
    mean = {k: sum(v) / len(v) for k, v in scores.items()}
    return {
        "sample": sample.name,
        "frames": len(idx),
        "resolution": [int(sample.gt_frames.shape[-1]), int(sample.gt_frames.shape[-2])],
        "psnr_db": mean,
        "psnr_change_db": {k: mean[k] - mean["fp32"] for k in mean if k != "fp32"},
        "gaussians": counts,
    }


def render_breakdown(gaussians, cam, repeats: int) -> dict:
    """Where the CPU render of one frame goes, kernel by kernel, on the path ``render`` takes for
    served frames: ``project_cpu``, then ``rasterize_fast``'s own stage clock (pack, depth sort,
    gather, tile binning, compositing), then the torch ops that finish the image. Medians over
    ``repeats`` renders in ms; ``intersections`` = (tile, splat) pairs composited."""
    import statistics

    import numba

    from ..constants import BACKGROUND_RGB
    from ..render import _background, _finish
    from ..render.cpu_backend import num_threads, project_cpu, rasterize_fast

    g, c = gaussians, cam.flatten()
    w, h = c.width, c.height
    bg = _background(BACKGROUND_RGB, 1, torch.float32, torch.device("cpu"))
    prev = numba.get_num_threads()
    numba.set_num_threads(num_threads())
    runs: list[dict] = []
    try:
        with torch.inference_mode():
            for _ in range(repeats + 1):  # the first is a warm-up
                st: dict[str, float] = {}
                t0 = time.perf_counter()
                proj, rects = project_cpu(g.means, g.quats, g.scales, c.K, c.w2c, w, h)
                values = torch.cat([g.colors.expand(1, -1, 3), proj.depths[..., None]], dim=-1)  # [1, N, 4]
                st["project"] = time.perf_counter() - t0
                acc, alpha = rasterize_fast(proj, g.opacities, values, w, h, rects, stages=st)
                t1 = time.perf_counter()
                _finish(acc, alpha, bg)
                st["finish"] = time.perf_counter() - t1
                runs.append(st)
    finally:
        numba.set_num_threads(prev)
    runs = runs[1:]
    names = ("project", "pack", "sort", "gather", "bin", "composite", "finish")
    out = {f"{k}_ms": 1e3 * statistics.median(r[k] for r in runs) for k in names}
    out["sum_ms"] = sum(out.values())
    out.update({"gaussians": len(g), "composited_splats": int(runs[0]["composited_splats"]),
                "intersections": int(runs[0]["intersections"]), "resolution": [w, h]})
    return out


def stage_times(model, avatar, cam, quality: int, repeats: int, bf16: bool = False) -> dict:
    """Median ms of each per-frame stage."""
    from server.imaging import encode_jpeg, frame_to_uint8
    from server.protocol import pack_frame

    from ..constants import BACKGROUND_RGB
    from ..render import render

    expr = _expressions(model, 1)[0]
    with torch.inference_mode():
        g = model.animate(avatar, expr)
        out = render(g, cam, background=BACKGROUND_RGB)
    frame = frame_to_uint8(out.rgb[0])
    jpeg = encode_jpeg(frame, quality)
    header = {"seq": 1, "render_ms": 1.0, "deform_ms": 1.0, "raster_ms": 1.0, "encode_ms": 1.0, "total_ms": 1.0,
              "width": cam.width, "height": cam.height, "dropped": 0}

    def deform():
        with torch.inference_mode():
            model.animate(avatar, expr, bf16=bf16)

    def raster():
        with torch.inference_mode():
            render(g, cam, background=BACKGROUND_RGB)

    t = {
        "deform": time_fn(deform, repeats),
        "render": time_fn(raster, repeats),
        "quantize": time_fn(lambda: frame_to_uint8(out.rgb[0]), repeats),
        "jpeg": time_fn(lambda: encode_jpeg(frame, quality), repeats),
        "message": time_fn(lambda: pack_frame(header, jpeg), repeats),
    }
    res = {f"{k}_ms": v.wall_ms for k, v in t.items()}
    res.update({f"{k}_cpu_ms": v.cpu_ms for k, v in t.items()})
    res["sum_ms"] = sum(v.wall_ms for v in t.values())
    res["jpeg_bytes"] = len(jpeg)
    return res


def end_to_end(model, avatar, cam, quality: int, frames: int, bf16: bool = False) -> dict:
    """The server's ``FrameRenderer.render`` + ``pack_frame`` back to back: frames per second."""
    from server.frames import FrameRenderer
    from server.protocol import pack_frame

    renderer = FrameRenderer(model, "cpu", bf16=bf16)
    exprs = _expressions(model, frames + 2, seed=2)
    for e in exprs[:2]:  # warm-up
        renderer.render(avatar, e, cam, quality)
    c0, t0 = time.process_time(), time.perf_counter()
    per = []
    for i, e in enumerate(exprs[2:]):
        s = time.perf_counter()
        fr = renderer.render(avatar, e, cam, quality)
        pack_frame({"seq": i, "render_ms": fr.render_ms, "encode_ms": fr.encode_ms, "width": fr.width, "height": fr.height}, fr.jpeg)
        per.append(1e3 * (time.perf_counter() - s))
    wall = time.perf_counter() - t0
    per.sort()
    return {"frames": frames, "fps": frames / wall, "median_frame_ms": per[len(per) // 2],
            "p90_frame_ms": per[min(len(per) - 1, int(0.9 * len(per)))], "cpu_s_per_frame": (time.process_time() - c0) / frames}


def bf16_check(model, avatar, cam, repeats: int) -> dict:
    """fp32 vs bf16-autocast deformation: time and PSNR of the rendered frame."""
    from ..constants import BACKGROUND_RGB
    from ..render import render

    expr = _expressions(model, 1, seed=3)[0]
    out = {}
    frames = {}
    for name, bf16 in (("fp32", False), ("bf16", True)):
        def f(bf16=bf16):
            with torch.inference_mode():
                return model.animate(avatar, expr, bf16=bf16)

        out[f"deform_{name}_ms"] = time_fn(f, repeats).wall_ms
        with torch.inference_mode():
            frames[name] = render(f(), cam, background=BACKGROUND_RGB).rgb
    out["psnr_bf16_vs_fp32_db"] = psnr(frames["bf16"], frames["fp32"])
    return out


def prune_check(model, avatar, cam, repeats: int, thresholds=PRUNE_THRESHOLDS) -> list[dict]:
    """Render time and PSNR against the unpruned frame after dropping Gaussians below an opacity."""
    from ..constants import BACKGROUND_RGB
    from ..render import render

    expr = _expressions(model, 1, seed=4)[0]
    with torch.inference_mode():
        g = model.animate(avatar, expr)
        ref = render(g, cam, background=BACKGROUND_RGB).rgb
    rows = []
    for thr in (0.0, *thresholds):
        gp = g.prune(thr) if thr > 0 else g

        def f(gp=gp):
            with torch.inference_mode():
                return render(gp, cam, background=BACKGROUND_RGB).rgb

        t = time_fn(f, repeats)
        rows.append({"min_opacity": thr, "gaussians": len(gp), "render_ms": t.wall_ms, "psnr_vs_unpruned_db": psnr(f(), ref)})
    return rows


def served_mlp(model, precision: str = "auto", compile_opt: str = "auto") -> dict:
    """Set the model's MLP up as the server would: precision as configured or, for ``auto``, chosen by
    ``fastgha_core.perf.measure_mlp_precision`` (the server's start-up micro-benchmark); compiled per
    ``Settings.resolved_compile``."""
    from server.settings import Settings

    from ..perf import PrecisionChoice, measure_mlp_precision

    s = Settings(mlp_precision=precision, compile=compile_opt)
    choice = measure_mlp_precision(model) if precision == "auto" else PrecisionChoice(precision, "configured")
    bf16 = choice.bf16
    out = {"precision": choice.precision, "choice": choice.to_dict(), "compiled": False, "compile_s": None, "compile_error": None}
    if s.resolved_compile("cpu"):
        try:
            out["compile_s"] = model.compile_deformation(bf16=bf16)
            out["compiled"] = True
        except Exception as e:  # inductor needs a C++ toolchain; report and measure eagerly
            out["compile_error"] = f"{type(e).__name__}: {str(e).splitlines()[0][:200] if str(e) else ''}"
            log.warning("torch.compile failed, measuring the eager MLP: %s", out["compile_error"])
    return out


def run(args) -> dict:
    from server.frames import FrameRenderer

    quick = bool(getattr(args, "quick", False))
    name = getattr(args, "frame_model", "tiny") or "tiny"
    views = _ints(getattr(args, "frame_views", None), (4,) if quick else DEFAULT_VIEWS)
    resolutions = _ints(getattr(args, "frame_resolutions", None), (256,) if quick else DEFAULT_RESOLUTIONS)
    frames = getattr(args, "frame_frames", None) or (10 if quick else 60)
    quality = int(getattr(args, "frame_jpeg_quality", 85) or 85)
    repeats = 3 if quick else 15
    heldout_frames = getattr(args, "frame_heldout", None)
    heldout_frames = (4 if quick else 16) if heldout_frames is None else int(heldout_frames)
    model = bench_model(name)
    base_cam = FrameRenderer(model, "cpu").default_camera
    load0 = load_average()
    mlp = served_mlp(model, getattr(args, "frame_precision", "auto") or "auto", getattr(args, "frame_compile", "auto") or "auto")
    bf16 = mlp["precision"] == "bf16"
    print(f"frame benchmark: model {model.config.name!r}, torch threads {torch.get_num_threads()}, "
          f"stage medians of {repeats}, end-to-end over {frames} frames; MLP {mlp['precision']}"
          f"{', compiled in %.1f s' % mlp['compile_s'] if mlp['compiled'] else ', eager'}")
    print(f"{'views':>5} {'N':>7} {'res':>5} | {'deform':>7} {'render':>7} {'quant':>6} {'jpeg':>6} {'msg':>6} | {'fps':>6} {'frame ms':>9}")
    rows = []
    avatars = {}
    for v in views:
        avatars[v] = bench_avatar(model, v)
        for res in resolutions:
            cam = base_cam.resize(res, res)
            st = stage_times(model, avatars[v], cam, quality, repeats, bf16)
            e2e = end_to_end(model, avatars[v], cam, quality, frames, bf16)
            row = {"views": v, "gaussians": len(avatars[v]), "resolution": res, **st, **{f"e2e_{k}": x for k, x in e2e.items()}}
            rows.append(row)
            print(f"{v:>5} {len(avatars[v]):>7} {res:>5} | {st['deform_ms']:>7.1f} {st['render_ms']:>7.1f} {st['quantize_ms']:>6.2f} "
                  f"{st['jpeg_ms']:>6.2f} {st['message_ms']:>6.3f} | {e2e['fps']:>6.1f} {e2e['median_frame_ms']:>9.1f}", flush=True)

    # design comparison: re-running reconstruction per frame (4 views) vs our per-frame path
    from ._common import input_views

    images, cams = input_views(model, 4)

    def recon():
        with torch.inference_mode():
            model.reconstruct(images, cams)

    recon_ms = time_fn(recon, 1 if quick else 3).wall_ms
    comparison = {"reconstruct_4views_ms": recon_ms}
    for row in rows:
        if row["views"] == 4:
            ours = 1e3 / row["e2e_fps"]
            rerun = recon_ms + ours  # reconstruct + the same render/encode per frame
            comparison[f"ours_frame_ms_{row['resolution']}"] = ours
            comparison[f"rerun_frame_ms_{row['resolution']}"] = rerun
            comparison[f"ratio_{row['resolution']}"] = rerun / ours
    print("design comparison (4 views): " + ", ".join(f"{k} {v:.1f}" for k, v in comparison.items()))

    # optimisation checks on the 4-view avatar (or the largest measured) at the first resolution
    v_opt = 4 if 4 in avatars else max(avatars)
    cam = base_cam.resize(resolutions[0], resolutions[0])
    live, perturbed = _with_live_deformation(model)
    if perturbed:
        live.animate(avatars[v_opt], model.expression_space.neutral())  # cache for the copy
    bf16 = bf16_check(live, avatars[v_opt], cam, repeats)
    bf16["untrained_model_output_layer_randomised"] = perturbed
    prune = prune_check(model, avatars[v_opt], cam, repeats, PRUNE_THRESHOLDS[:1] if quick else PRUNE_THRESHOLDS)
    print(f"bf16 deform: {bf16['deform_bf16_ms']:.1f} ms vs fp32 {bf16['deform_fp32_ms']:.1f} ms, PSNR {bf16['psnr_bf16_vs_fp32_db']:.1f} dB")
    for p in prune:
        print(f"prune opacity < {p['min_opacity']}: {p['gaussians']} Gaussians, render {p['render_ms']:.1f} ms, PSNR {p['psnr_vs_unpruned_db']:.1f} dB")
    breakdown = []
    with torch.inference_mode():
        g_opt = model.animate(avatars[v_opt], _expressions(model, 1)[0], bf16=bf16)
    for res in resolutions:
        b = render_breakdown(g_opt, base_cam.resize(res, res), repeats)
        breakdown.append(b)
        print(f"render at {res}²: " + ", ".join(f"{k[:-3]} {v:.2f}" for k, v in b.items() if k.endswith("_ms"))
              + f" ms; {b['intersections']} tile intersections")
    heldout = heldout_quality(model, heldout_frames, PRUNE_THRESHOLDS[:1] if quick else PRUNE_THRESHOLDS)
    if heldout is not None:
        print(f"held-out {heldout['sample']} ({heldout['frames']} frames vs ground truth): "
              + ", ".join(f"{k} {v:.2f} dB ({heldout['gaussians'][k]} G)" for k, v in heldout["psnr_db"].items()))

    def fps_at(res):
        r = next((r for r in rows if r["views"] == 4 and r["resolution"] == res), None)
        return r["e2e_fps"] if r else None

    summary = {"fps_256": fps_at(256), "fps_512": fps_at(512), "per_frame_vs_rerun_ratio": comparison.get("ratio_256")}
    return {
        "model": model.config.name,
        "jpeg_quality": quality,
        "rows": rows,
        "design_comparison": comparison,
        "bf16": bf16,
        "prune": prune,
        "heldout": heldout,
        "render_breakdown": breakdown,
        "mlp": mlp,
        "load_average_start": load0,
        "load_average_end": load_average(),
        "summary": summary,
    }
