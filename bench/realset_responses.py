"""Expression responses of avatars built from the real photo sets (issue 16), frontal 512² renders.

For every set in ``../shared/realsets/`` (or ``$FASTGHA_REALSETS``): track the photos
(``fastgha_core.tracking.track_photos``: crops, cameras, masks, each photo's expression), reconstruct
an avatar on the tracked head surface as the server does (``--no-surface``: on the network's depth;
the tracked expressions are undone when the model has the expression prior), render it
from the server's default frontal camera at 512² with the neutral expression, ``jawOpen`` = 1,
``eyeBlink_L`` = ``eyeBlink_R`` = 1 and ``mouthSmile_L`` = ``mouthSmile_R`` = 1, and measure dlib's
68 landmarks (the ``faces`` extra) as in ``fastgha_core/train/responses.py``:

- ``jawOpen``: inner-lip gap change in interocular distances (target >= 0.25);
- ``eyeBlink``: eye aspect ratio over the neutral's (target <= 0.6);
- ``mouthSmile``: mouth width over the neutral's (target >= 1.10).

There is no ground truth for these people. The sets are non-commercial material: this script never
writes pictures of them unless ``--pictures DIR`` is given (for a local look; never commit them).
Photos the tracker cannot use (it names them: profiles, today) are left out of their set and
listed under ``dropped``; a set where none tracks is reported with the error. Exits 0 when the folder is absent.

    python bench/realset_responses.py --model tiny --json out/realsets.json

``--sizes 448,512,576`` also measures each response at those render sides and their mean: dlib's
reading of one render moves by a few hundredths of an interocular distance with the render size
(and with the server's JPEG rounding), as much as the margin of a reading near its target.

``--server URL`` builds each avatar through a running server instead (``fastgha serve``): the photos
are posted alone, without cameras, the server tracks and reconstructs them with its own settings,
and the four frames are streamed back over the WebSocket at the same camera (JPEG quality 100)::

    fastgha serve --port 8765 &
    python bench/realset_responses.py --model tiny --server http://127.0.0.1:8765
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/: _bench_cli (tests load this file by path)

from _bench_cli import write_json

REPO = Path(__file__).resolve().parents[1]
EXPRESSIONS = {
    "neutral": {},
    "jawOpen": {"jawOpen": 1.0},
    "eyeBlink": {"eyeBlink_L": 1.0, "eyeBlink_R": 1.0},
    "mouthSmile": {"mouthSmile_L": 1.0, "mouthSmile_R": 1.0},
}
TARGETS = {"jawOpen": ("lip_gap_change", ">=", 0.25), "eyeBlink": ("ear_ratio", "<=", 0.6), "mouthSmile": ("width_ratio", ">=", 1.10)}


def realsets_root() -> Path:
    env = os.environ.get("FASTGHA_REALSETS")
    return Path(env) if env else (REPO / ".." / "shared" / "realsets").resolve()


def run_set(model, folder: Path, size: int, det, pictures: Path | None, drop_untracked: bool = True, surface: bool = True, sizes: tuple[int, ...] = ()) -> dict:
    import torch
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.images import read_image  # the project's one decoder (EXIF orientation applied)
    from fastgha_core.model.surface import HeadSurface
    from fastgha_core.render import render
    from fastgha_core.tracking import track_photos
    from fastgha_core.train.responses import _u8

    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    images = [read_image(p, max_pixels=64_000_000).rgb for p in paths]
    dropped = []
    while True:  # photos the tracker cannot use (it names them) are left out, and reported
        try:
            tr = track_photos(images, names=[p.name for p in paths])
            break
        except ValueError as e:
            bad = [i for i, p in enumerate(paths) if p.name in str(e)]
            if not drop_untracked or not bad or len(paths) <= 1:
                raise
            dropped.append(f"{paths[bad[0]].name}: {e}")
            del paths[bad[0]], images[bad[0]]
    crops = torch.from_numpy(tr.crops).permute(0, 3, 1, 2).float() / 255.0
    masks = torch.from_numpy(tr.masks)[:, None]
    x, c = model.prepare(crops, tr.cameras, masks)
    expr = torch.from_numpy(tr.expressions) if tr.expressions.shape[1] == model.config.expression_dim else None
    with torch.inference_mode():
        avatar = model.reconstruct(x, c, expressions=expr, surface=HeadSurface.from_tracking(tr) if surface else None)
    space = model.expression_space

    def frames_at(sz: int) -> dict:
        cam = frontal_camera(model, sz)
        frames = {}
        for name, w in EXPRESSIONS.items():
            with torch.inference_mode():
                g = model.animate(avatar, space.parse(w), camera=cam)  # as the server draws it (view blending, model/viewblend.py)
                frames[name] = _u8(render(g, cam, background=BACKGROUND_RGB).rgb[0].float().clamp(0, 1))
        return frames

    out: dict = {"photos": [p.name for p in paths], "dropped": dropped, "gaussians": len(avatar)}
    out.update(measure_frames(frames_at(size), det, folder.name, pictures))
    if sizes:
        out["by_size"] = by_size({sz: measure_frames(frames_at(sz), det, folder.name, None)["responses"] for sz in sizes})
    return out


def by_size(res: dict) -> dict:
    """``{size: responses}`` -> the same plus ``"mean"``: each response averaged over the sizes where dlib
    measured it (dlib's reading of one render moves by a few hundredths with the render size)."""
    out = {str(k): v for k, v in res.items()}
    keys = sorted({k for r in res.values() for k in r})
    out["mean"] = {k: float(np.mean([r[k] for r in res.values() if k in r])) for k in keys}
    return out


def frontal_camera(model, size: int):
    """The server's default frontal camera at ``size`` x ``size`` (what the browser demo opens with)."""
    from server.frames import FrameRenderer

    return FrameRenderer(model, "cpu").default_camera.resize(size, size)


def run_set_server(url: str, api_key: str | None, model, folder: Path, size: int, det, pictures: Path | None, sizes: tuple[int, ...] = ()) -> dict:
    """The same responses for an avatar built by a running server from the photos alone.

    The photos are posted without cameras (the server tracks them, as for a user's upload), and the
    four expressions are streamed over the WebSocket at the local frontal camera (JPEG quality 100).
    A photo the server's tracker cannot use fails the set with the server's error (which names it).
    """
    from client_demo.client import FastGHAClient

    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    client = FastGHAClient(url, api_key=api_key, timeout=600.0)
    avatar = client.create_avatar(paths)

    def frames_at(sz: int) -> dict:
        cam = frontal_camera(model, sz)
        camera = {"K": cam.K.tolist(), "w2c": cam.w2c.tolist(), "width": sz, "height": sz}
        requests = [{"expression": w, "camera": camera} for w in EXPRESSIONS.values()]
        got = client.stream_sync(avatar, requests, options={"jpeg_quality": 100, "max_size": sz})
        frames = {name: f.image() for name, f in zip(EXPRESSIONS, got)}
        for name, img in frames.items():
            if img.shape[:2] != (sz, sz):
                raise RuntimeError(f"the server sent a {img.shape[1]}x{img.shape[0]} frame for {name}, expected {sz}x{sz}")
        return frames

    try:
        out: dict = {"photos": [p.name for p in paths], "dropped": [], "gaussians": avatar.num_gaussians, "via": url}
        out.update(measure_frames(frames_at(size), det, folder.name, pictures))
        if sizes:
            out["by_size"] = by_size({sz: measure_frames(frames_at(sz), det, folder.name, None)["responses"] for sz in sizes})
    finally:
        client.delete(avatar)
    return out


def measure_frames(frames: dict, det, set_name: str, pictures: Path | None) -> dict:
    """dlib's measures of the ``EXPRESSIONS`` frames (uint8 ``[H, W, 3]`` each), the responses and the targets met."""
    from fastgha_core.train.responses import landmark_measures

    out: dict = {"measures": {}, "detected": {}}
    fallback = None  # the neutral render's face box, for frames where dlib finds no face
    for name in EXPRESSIONS:
        u8 = frames[name]
        if pictures is not None:
            from PIL import Image

            pictures.mkdir(parents=True, exist_ok=True)
            Image.fromarray(u8).save(pictures / f"{set_name}_{name}.png")
        box = det.box(u8)
        out["detected"][name] = box is not None
        lm, _ = det.landmarks(u8, fallback)
        if name == "neutral":
            fallback = box
        out["measures"][name] = landmark_measures(lm) if lm is not None else None
    m = out["measures"]
    res = {}
    if m["neutral"] is not None:
        n = m["neutral"]
        if m["jawOpen"]:
            res["lip_gap_change"] = m["jawOpen"]["lip_gap"] - n["lip_gap"]
        if m["eyeBlink"]:
            res["ear_ratio"] = m["eyeBlink"]["ear"] / max(n["ear"], 1e-6)
        if m["mouthSmile"]:
            res["width_ratio"] = m["mouthSmile"]["mouth_width"] / max(n["mouth_width"], 1e-6)
    out["responses"] = res
    out["targets_met"] = {
        e: (None if key not in res else (res[key] >= thr if op == ">=" else res[key] <= thr)) for e, (key, op, thr) in TARGETS.items()
    }
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="tiny")
    ap.add_argument("--size", type=int, default=512, help="render side (default 512)")
    ap.add_argument("--sizes", default=None, help="also measure at these render sides (comma-separated, e.g. 448,512,576) and their mean: dlib's jitter")
    ap.add_argument("--json", default=None, help="write the results here")
    ap.add_argument("--pictures", default=None, help="write the renders here (local look only; never commit pictures of these people)")
    ap.add_argument("--sets", default=None, help="comma-separated set names (default: all)")
    ap.add_argument("--no-surface", action="store_true", help="use the network's depth, not the tracked head surface (the server's default)")
    ap.add_argument("--keep-untracked", action="store_true", help="fail a set when one photo does not track (default: leave that photo out and report it)")
    ap.add_argument("--server", default=None, metavar="URL", help="build each avatar through this running server from the photos alone (no cameras) and measure its streamed frames")
    ap.add_argument("--api-key", default=os.environ.get("FASTGHA_API_KEY"), help="the server's API key (default: $FASTGHA_API_KEY)")
    args = ap.parse_args(argv)
    sizes = tuple(int(x) for x in args.sizes.split(",")) if args.sizes else ()
    root = realsets_root()
    if not root.is_dir():
        print(f"no real photo sets at {root}: skipped")
        return 0
    sys.path.insert(0, str(REPO))
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.train.responses import LandmarkDetector

    model = load_model(args.model)
    det = LandmarkDetector()
    sets = sorted(p for p in root.iterdir() if p.is_dir())
    if args.sets:
        want = set(args.sets.split(","))
        sets = [s for s in sets if s.name in want]
    report = {"model": args.model, "size": args.size, "server": args.server, "prior": bool(model.config.deform.prior), "sets": {}}
    for s in sets:
        try:
            pictures = Path(args.pictures) if args.pictures else None
            if args.server:
                report["sets"][s.name] = run_set_server(args.server, args.api_key, model, s, args.size, det, pictures, sizes)
            else:
                report["sets"][s.name] = run_set(model, s, args.size, det, pictures, not args.keep_untracked, not args.no_surface, sizes)
        except Exception as e:  # tracking failures name the photo; report and go on
            report["sets"][s.name] = {"error": f"{type(e).__name__}: {e}"}
        r = report["sets"][s.name]
        print(s.name, json.dumps(r.get("responses", r.get("error"))), json.dumps(r.get("targets_met", {})), "dropped:", r.get("dropped"))
        if "by_size" in r:
            print("  by size:", json.dumps({k: {q: round(x, 3) for q, x in v.items()} for k, v in r["by_size"].items()}))
    write_json(args.json, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
