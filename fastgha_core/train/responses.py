"""Expression-response evaluation (issue 16): does a sent expression visibly move the avatar as much
as it moves the ground truth?

Per held-out synthetic subject: the avatar is reconstructed with the protocol of ``evaluate.py``
(``num_inputs`` inputs at different expressions and cameras; their known expressions are given to
``reconstruct``, which undoes them when the model has the expression prior). Then every expression
of ``RESPONSE_EXPRESSIONS`` at weight 1.0, and the neutral face, is rendered frontally and from 30
degrees of yaw (1 m, the synthetic rig's field of view), by the model and by the mesh renderer (the
ground truth), at ``resolution``.

Measurements, the same detector on truth and ours (dlib's HOG face detector + 68-point shape
predictor, the ``faces`` extra; the iBUG/Multi-PIE 68-point numbering):

- interocular distance ``iod`` = |p36 - p45| (outer eye corners);
- inner-lip gap = mean(|p61 - p67|, |p62 - p66|, |p63 - p65|) / iod;
- eye aspect ratio (Soukupová & Čech 2016) = (|p37 - p41| + |p38 - p40|) / (2 |p36 - p39|),
  averaged over both eyes (p42..p47 for the other);
- mouth width = |p48 - p54| / iod;
- landmark displacement = mean over the 68 points of |p(expr) - p(neutral)| / iod.

``response`` of an expression = ours / truth of its change from neutral: the displacement ratio for
every expression, and for the three headline ones the specific measure (jawOpen: lip-gap change;
eyeBlink: 1 - EAR ratio; mouthSmile: mouth-width ratio - 1). 1.0 is a perfect response.

Where dlib finds no face on an image, the failure is counted (per image kind) and the landmarks are
fitted inside the face box found on the truth's neutral render of the same view (so every pair is
measured; the counts say how often that happened).

Region PSNR: the mouth box (true landmarks 48-67, projected) and the eye boxes (36-47), each padded
by 30% of its size, on ours and on a static head (the avatar animated with the neutral expression).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "RESPONSE_EXPRESSIONS",
    "ResponseConfig",
    "landmark_measures",
    "response_ratio",
    "evaluate_responses",
    "responses_markdown",
]

# name -> ict53 weights (ARKit names; both sides where the issue says L+R)
RESPONSE_EXPRESSIONS: dict[str, dict[str, float]] = {
    "jawOpen": {"jawOpen": 1.0},
    "eyeBlink": {"eyeBlink_L": 1.0, "eyeBlink_R": 1.0},
    "mouthSmile": {"mouthSmile_L": 1.0, "mouthSmile_R": 1.0},
    "browInnerUp": {"browInnerUp_L": 1.0, "browInnerUp_R": 1.0},
    "mouthPucker": {"mouthPucker": 1.0},
    "mouthFunnel": {"mouthFunnel": 1.0},
    "jawLeft": {"jawLeft": 1.0},
    "eyeLookOut_L": {"eyeLookOut_L": 1.0},
}
HEADLINE = ("jawOpen", "eyeBlink", "mouthSmile")


@dataclass
class ResponseConfig:
    resolution: int = 256  # side of the renders (pixels)
    yaws: tuple[float, ...] = (0.0, 30.0)  # degrees; positive = camera towards the subject's left
    num_inputs: int = 4  # reconstruction inputs (evaluate.py protocol)
    expressions: tuple[str, ...] = tuple(RESPONSE_EXPRESSIONS)
    use_prior: bool = True  # False: the ablation without the prior's displacement
    neutralize_inputs: bool = True  # give reconstruct() the inputs' known expressions
    backend: str = "auto"
    grid_subject: int = 0  # which subject the picture grid shows
    region_pad: float = 0.3


# ---------------------------------------------------------------------------- landmark measures
def _d(lm: np.ndarray, i: int, j: int) -> float:
    return float(np.linalg.norm(lm[i] - lm[j]))


def landmark_measures(lm: np.ndarray) -> dict[str, float]:
    """Measures of one face's 68 landmarks ``[68, 2]`` (pixels): ``iod`` (pixels), ``lip_gap``,
    ``mouth_width`` (both / iod) and ``ear`` (see module doc). Raises ``ValueError`` for another shape."""
    lm = np.asarray(lm, dtype=np.float64)
    if lm.shape != (68, 2):
        raise ValueError(f"landmark_measures expects [68, 2] landmarks, got {list(lm.shape)}")
    iod = max(_d(lm, 36, 45), 1e-6)
    gap = (_d(lm, 61, 67) + _d(lm, 62, 66) + _d(lm, 63, 65)) / 3.0
    ear = []
    for a in (36, 42):
        p = lambda k: a + k  # noqa: E731
        ear.append((_d(lm, p(1), p(5)) + _d(lm, p(2), p(4))) / (2.0 * max(_d(lm, p(0), p(3)), 1e-6)))
    return {"iod": iod, "lip_gap": gap / iod, "mouth_width": _d(lm, 48, 54) / iod, "ear": float(np.mean(ear))}


def displacement(lm: np.ndarray, lm0: np.ndarray) -> float:
    """Mean landmark displacement ``|lm - lm0|`` over 68 points, in interocular distances of ``lm0``."""
    return float(np.linalg.norm(np.asarray(lm) - np.asarray(lm0), axis=1).mean() / landmark_measures(lm0)["iod"])


def change(name: str, m: dict[str, float], m0: dict[str, float], disp: float) -> float:
    """The change an expression should make, from neutral measures ``m0`` to ``m`` (see module doc)."""
    if name == "jawOpen":
        return m["lip_gap"] - m0["lip_gap"]
    if name == "eyeBlink":
        return 1.0 - m["ear"] / max(m0["ear"], 1e-6)
    if name == "mouthSmile":
        return m["mouth_width"] / max(m0["mouth_width"], 1e-6) - 1.0
    return disp


def response_ratio(ours: float, truth: float) -> float | None:
    """``ours / truth``, or None when the truth hardly changes (|truth| < 1e-3)."""
    return None if abs(truth) < 1e-3 else float(ours / truth)


class LandmarkDetector:
    """dlib HOG detector + 68-point predictor; counts failures."""

    def __init__(self):
        import dlib  # type: ignore
        import face_recognition_models as frm  # type: ignore

        self.detector = dlib.get_frontal_face_detector()
        self.predictor = dlib.shape_predictor(frm.pose_predictor_model_location())

    def box(self, img: np.ndarray):
        dets = self.detector(img, 1)
        return max(dets, key=lambda r: r.width() * r.height()) if len(dets) else None

    def landmarks(self, img: np.ndarray, fallback_box) -> tuple[np.ndarray | None, bool]:
        """``([68, 2] | None, detected)``: landmarks in the detected box, else in ``fallback_box``."""
        b = self.box(img)
        ok = b is not None
        b = b if ok else fallback_box
        if b is None:
            return None, False
        s = self.predictor(img, b)
        return np.array([[s.part(i).x, s.part(i).y] for i in range(68)], dtype=np.float64), ok


def _u8(img: Tensor) -> np.ndarray:
    from .faces import to_uint8_hwc

    return np.ascontiguousarray(to_uint8_hwc(img))


def _region_psnr(pred: Tensor, gt: Tensor, box: tuple[int, int, int, int]) -> float:
    x0, y0, x1, y1 = box
    p, g = pred[:, y0:y1, x0:x1], gt[:, y0:y1, x0:x1]
    mse = float(((p - g) ** 2).mean())
    return 10.0 * math.log10(1.0 / max(mse, 1e-10))


def _box(pts: np.ndarray, pad: float, size: int) -> tuple[int, int, int, int]:
    lo, hi = pts.min(0), pts.max(0)
    ext = np.maximum(hi - lo, 4.0) * pad
    lo, hi = np.floor(lo - ext).astype(int), np.ceil(hi + ext).astype(int)
    return max(lo[0], 0), max(lo[1], 0), min(hi[0], size), min(hi[1], size)


def _project(cams, pts: np.ndarray) -> np.ndarray:
    """World points ``[P, 3]`` -> pixels ``[P, 2]`` in the first camera of ``cams``."""
    w2c = cams.w2c.reshape(-1, 4, 4)[0].double().numpy()
    K = cams.K.reshape(-1, 3, 3)[0].double().numpy()
    pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
    uv = pc @ K.T
    return uv[:, :2] / uv[:, 2:3]


def _code(weights: dict[str, float], names: Sequence[str]) -> Tensor:
    z = torch.zeros(len(names))
    for n, w in weights.items():
        z[list(names).index(n)] = w
    return z


@torch.no_grad()
def evaluate_responses(model, sources: Sequence, config: ResponseConfig | None = None, out_dir: str | Path | None = None, grid_path: str | Path | None = None, progress: bool = True) -> dict[str, Any]:
    """Run the response evaluation on synthetic ``sources`` (``SyntheticSequence``); returns the report.

    Raises ``ValueError`` for a model whose expression space is not ``ict53`` (the synthetic truth's).
    """
    from tqdm.auto import tqdm

    from ..cameras import Cameras
    from ..constants import BACKGROUND_RGB
    from ..data.headmodel import HeadModel
    from ..data.synthetic import FOV_DEG
    from ..render import render
    from .evaluate import EvalConfig, _cameras_at, select_protocol
    from .visualize import save_grid

    cfg = config or ResponseConfig()
    if model.config.expression_space != "ict53":
        raise ValueError(f"the synthetic response evaluation needs an ict53 model, got {model.config.expression_space!r}")
    det = LandmarkDetector()
    hm = HeadModel.load()
    names = hm.expression_names
    dev = next(model.parameters()).device
    R = int(cfg.resolution)
    exprs = ["neutral", *cfg.expressions]
    codes = {"neutral": torch.zeros(len(names)), **{e: _code(RESPONSE_EXPRESSIONS[e], names) for e in cfg.expressions}}
    rows: list[dict[str, Any]] = []
    fails = {"truth": 0, "ours": 0, "images": 0}
    grid: list[list[Tensor]] = []
    for si, src in enumerate(tqdm(list(sources), desc="responses", disable=not progress)):
        proto = select_protocol(src, EvalConfig(num_inputs=cfg.num_inputs))
        pairs = list(zip(proto.input_timesteps, proto.input_cameras))
        views = [src.view(t, c) for t, c in pairs]
        images = torch.stack([v.image for v in views]).float()
        masks = torch.stack([v.mask for v in views]).float()
        in_imgs, in_cams = model.prepare(images, _cameras_at(src, pairs), masks=masks)
        in_expr = torch.stack([src.expression(t) for t, _ in pairs]).float() if cfg.neutralize_inputs else None
        avatar = model.reconstruct(in_imgs.to(dev), in_cams.to(dev), expressions=in_expr)
        subj = src.synthetic_subject
        for yaw in cfg.yaws:
            a = math.radians(yaw)
            cams = Cameras.look_at(torch.tensor([[math.sin(a), 0.0, math.cos(a)]]), torch.zeros(1, 3), fov_deg=FOV_DEG, width=R, height=R)
            imgs: dict[str, dict[str, Tensor]] = {"truth": {}, "ours": {}}
            lms: dict[str, dict[str, np.ndarray | None]] = {"truth": {}, "ours": {}}
            static = render(model.animate(avatar, codes["neutral"].to(dev), prior=cfg.use_prior), cams.to(dev), background=BACKGROUND_RGB, backend=cfg.backend).rgb[0].float().cpu().clamp(0, 1)
            for e in exprs:
                z = codes[e].numpy()
                gt = subj.render(subj.frame(z), cams)[0].image.float().clamp(0, 1)
                g = model.animate(avatar, codes[e].to(dev), prior=cfg.use_prior)
                ours = render(g, cams.to(dev), background=BACKGROUND_RGB, backend=cfg.backend).rgb[0].float().cpu().clamp(0, 1)
                imgs["truth"][e], imgs["ours"][e] = gt, ours
            box0 = det.box(_u8(imgs["truth"]["neutral"]))
            for kind in ("truth", "ours"):
                for e in exprs:
                    lm, ok = det.landmarks(_u8(imgs[kind][e]), box0)
                    fails["images"] += 1
                    fails[kind] += not ok
                    lms[kind][e] = lm
            true_lm3 = {e: subj.vertices(codes[e].numpy())[hm.landmarks68] for e in exprs}
            geo = {e: _project(cams, true_lm3[e].astype(np.float64)) for e in exprs}  # the mesh's own landmarks
            for e in cfg.expressions:
                row: dict[str, Any] = {"subject": src.subject, "yaw": yaw, "expression": e}
                for kind in ("truth", "ours"):
                    lm, lm0 = lms[kind][e], lms[kind]["neutral"]
                    if lm is None or lm0 is None:
                        row[kind] = None
                        continue
                    m, m0 = landmark_measures(lm), landmark_measures(lm0)
                    dsp = displacement(lm, lm0)
                    row[kind] = {"measures": m, "neutral": m0, "displacement": dsp, "change": change(e, m, m0, dsp)}
                gm, gm0 = landmark_measures(geo[e]), landmark_measures(geo["neutral"])
                gd = displacement(geo[e], geo["neutral"])
                row["mesh"] = {"measures": gm, "neutral": gm0, "displacement": gd, "change": change(e, gm, gm0, gd)}
                finish_row(row)
                uv = _project(cams, true_lm3[e].astype(np.float64))
                mb = _box(uv[48:68], cfg.region_pad, R)
                eb = _box(uv[36:48], cfg.region_pad, R)
                gt, ours = imgs["truth"][e], imgs["ours"][e]
                row["psnr_mouth"], row["psnr_eyes"] = _region_psnr(ours, gt, mb), _region_psnr(ours, gt, eb)
                row["psnr_mouth_static"], row["psnr_eyes_static"] = _region_psnr(static, gt, mb), _region_psnr(static, gt, eb)
                rows.append(row)
            if si == cfg.grid_subject:
                if not grid:
                    grid = [[] for _ in exprs]
                for i, e in enumerate(exprs):
                    grid[i] += [imgs["truth"][e], imgs["ours"][e]]
    if grid and (grid_path or out_dir):
        save_grid(Path(grid_path) if grid_path else Path(out_dir) / "responses.png", grid)
    return {"rows": rows, "summary": summarise(rows), "detector_failures": fails, "config": asdict(cfg), "grid_columns": [f"{k} yaw {y:g}" for y in cfg.yaws for k in ("truth", "ours")]}


def finish_row(row: dict[str, Any]) -> dict[str, Any]:
    """Ratios of one (subject, view, expression) row from its ``truth``/``ours``/``mesh`` measures.

    A dlib misfit (headline expressions only): dlib's change on the truth disagrees with the mesh's
    own landmarks by more than 50% (dlib misses open mouths and closed eyes on dark synthetic skin);
    such rows are left out of the dlib ratio and counted. ``response_vs_mesh`` compares ours with
    the mesh landmarks' change instead (headline expressions only: for the others the 68 landmarks
    hardly move, e.g. gaze moves no landmark).
    """
    head = row["expression"] in HEADLINE
    t, o, m = row.get("truth"), row.get("ours"), row["mesh"]
    row["truth_misfit"] = bool(head and (t is None or abs(t["change"] - m["change"]) > 0.5 * abs(m["change"]) + 0.01))
    if t and o:
        row["displacement_ratio"] = response_ratio(o["displacement"], t["displacement"])
        row["response"] = None if row["truth_misfit"] else response_ratio(o["change"], t["change"])
    else:
        row["displacement_ratio"] = row["response"] = None
    row["response_vs_mesh"] = response_ratio(o["change"], m["change"]) if (o and head) else None
    return row


def _mean(v: list[float | None]) -> float | None:
    v = [x for x in v if x is not None and math.isfinite(x)]
    return float(np.mean(v)) if v else None


def _median(v: list[float | None]) -> float | None:
    v = [x for x in v if x is not None and math.isfinite(x)]
    return float(np.median(v)) if v else None


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for e in dict.fromkeys(r["expression"] for r in rows):
        rs = [r for r in rows if r["expression"] == e]
        out[e] = {
            "response": _median([r["response"] for r in rs]),
            "response_vs_mesh": _median([r["response_vs_mesh"] for r in rs]),
            "mesh_change": _mean([r["mesh"]["change"] for r in rs]),
            "truth_misfits": sum(r["truth_misfit"] for r in rs),
            "displacement_ratio": _median([r["displacement_ratio"] for r in rs]),
            "truth_change": _mean([r["truth"]["change"] if r["truth"] else None for r in rs]),
            "ours_change": _mean([r["ours"]["change"] if r["ours"] else None for r in rs]),
            "psnr_mouth": _mean([r["psnr_mouth"] for r in rs]),
            "psnr_mouth_static": _mean([r["psnr_mouth_static"] for r in rs]),
            "psnr_eyes": _mean([r["psnr_eyes"] for r in rs]),
            "psnr_eyes_static": _mean([r["psnr_eyes_static"] for r in rs]),
            "pairs": len(rs),
        }
    return out


def _f(v, d=2):
    return "n/a" if v is None else f"{v:.{d}f}"


def responses_markdown(report: dict[str, Any]) -> str:
    """The summary as a markdown table (medians of ours/truth over subjects and views)."""
    head = (
        "| expression | truth change (dlib / mesh) | ours change | response ours/truth (dlib) | ours/mesh | dlib misfits on truth "
        "| landmark displacement ours/truth | mouth PSNR ours / static | eyes PSNR ours / static |\n"
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    )
    body = ""
    for e, s in report["summary"].items():
        body += (
            f"| {e} | {_f(s['truth_change'], 3)} / {_f(s['mesh_change'], 3)} | {_f(s['ours_change'], 3)} | {_f(s['response'])} "
            f"| {_f(s['response_vs_mesh'])} | {s['truth_misfits']}/{s['pairs']} | {_f(s['displacement_ratio'])} "
            f"| {_f(s['psnr_mouth'])} / {_f(s['psnr_mouth_static'])} | {_f(s['psnr_eyes'])} / {_f(s['psnr_eyes_static'])} |\n"
        )
    f = report["detector_failures"]
    return head + body + (
        f"\ndlib found no face on {f['truth']} truth and {f['ours']} of our images (of {f['images']}); those used the truth's "
        "neutral face box. A misfit: dlib's change on the truth disagrees with the mesh's own landmarks by more than 50% "
        "(those pairs are left out of the dlib ratio and counted here).\n"
    )
