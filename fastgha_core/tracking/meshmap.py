"""MediaPipe Face Mesh points -> ICT-FaceKit vertices (the correspondence the fitter uses).

MediaPipe's face landmark model (``mediapipe.solutions.face_mesh``, 468 points in the topology of
its canonical face mesh) and the ICT head model have different topologies, so each Face Mesh
point is tied to one ICT vertex, computed once and shipped as
``assets/headmodel/mediapipe_ict.json`` (rebuild: ``python -m fastgha_core.tracking.meshmap``):

1. The 3D Face Mesh of two public-domain frontal portraits (scikit-image's ``astronaut``,
   matplotlib's ``grace_hopper.jpg``), in head axes (+x subject's left, +y up, +z out of the face;
   MediaPipe's ``z`` is in units of the image width, smaller = nearer), aligned to each other by a
   similarity transform and averaged.
2. ``MP68``: the Face Mesh indices of the 68 Multi-PIE / iBUG 300-W points (the subset widely
   used to convert MediaPipe to dlib's layout; checked against dlib's predictor on both portraits:
   median distance 1.7 px on a 130 px face, jaw line 4.6 px). They are matched to the ICT model's
   ``landmarks68`` vertices: a similarity transform (Umeyama) on the 51 inner points, then the ICT
   identity (50 modes) and expression (53, in [0, 1]) fitted in 3D to all 68, three rounds.
3. Every Face Mesh point takes the nearest vertex of the fitted ICT face (vertices 0-9408);
   points farther than ``MAX_SNAP_MM`` are left out (none are, with these portraits).

**Pose-dependent map** (``assets/headmodel/mediapipe_ict_pose.npz``, ``build_pose_table``, rebuild
with ``--pose``, ~30 s): the Face Mesh squeezes the far half of a turned head onto the visible half,
so beyond ~40 degrees its points no longer sit on the vertices above; on a pitched head its face
outline (jaw line, chin) slides 1-2 cm along the surface. On renders of synthetic ICT heads at
known yaw (every 15 degrees) and pitch (-30 .. +45, every 15) each point is tied to the surface
point it actually lands on; the fitter re-chooses the table's cells by the current yaw and pitch
(``FitConfig.yaw_map``, ``FitConfig.pitch_map``). Its pitch-0 row is the earlier yaw-only table
(``mediapipe_ict_yaw.npz``, which it replaces).

MediaPipe's own depth places the face-outline points (which, in a frontal photo, lie on the
cheeks' far slope): tying them instead to the ICT vertex seen at their image position under a
dlib fit removes a 5-7 degree pitch offset on frontal photos but makes turned heads come out
less turned (median yaw error on the real sets 16.6 against 12.3 degrees), so this 3D map is kept.
"""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

import numpy as np

__all__ = ["MP68", "MediaPipeMap", "load_mediapipe_map", "build_mediapipe_map", "MAP_ASSET"]

MAP_ASSET = Path(__file__).resolve().parent.parent / "assets" / "headmodel" / "mediapipe_ict.json"

# Face Mesh index of each of the 68 Multi-PIE points (0-16 jaw from the subject's right, 17-26 brows,
# 27-35 nose, 36-47 eyes, 48-67 mouth)
MP68 = (
    162, 234, 93, 58, 172, 136, 149, 148, 152, 377, 378, 365, 397, 288, 323, 454, 389,
    71, 63, 105, 66, 107, 336, 296, 334, 293, 301,
    168, 197, 5, 4, 75, 97, 2, 326, 305,
    33, 160, 158, 133, 153, 144, 362, 385, 387, 263, 373, 380,
    61, 39, 37, 0, 267, 269, 291, 405, 314, 17, 84, 181, 78, 82, 13, 312, 308, 317, 14, 87,
)  # fmt: skip
MAX_SNAP_MM = 6.0
FACE_VERTICES = 9409  # ICT face region: vertices 0 .. 9408


class MediaPipeMap:
    """``mp_index [N]`` Face Mesh indices tied to ``ict_vertex [N]`` ICT vertex ids; ``snap_mm [N]``."""

    def __init__(self, mp_index: np.ndarray, ict_vertex: np.ndarray, snap_mm: np.ndarray):
        self.mp_index = np.asarray(mp_index, dtype=np.int64)
        self.ict_vertex = np.asarray(ict_vertex, dtype=np.int64)
        self.snap_mm = np.asarray(snap_mm, dtype=np.float64)

    def __len__(self) -> int:
        return int(self.mp_index.shape[0])


@functools.lru_cache(maxsize=1)
def load_mediapipe_map(path: str | None = None) -> MediaPipeMap:
    """The shipped correspondence (module doc)."""
    d = json.loads(Path(path or MAP_ASSET).read_text())
    return MediaPipeMap(d["mp_index"], d["ict_vertex"], d["snap_mm"])


def load_pose_table(path: str | None = None) -> dict | None:
    """The shipped pose-dependent table (``build_pose_table``: ``yaw [B]``, ``pitch [P]`` degrees,
    both ascending, ``vertex [P, B, 468]`` ICT vertex ids (-1 = no hit), ``hits [P, B, 468]``), or
    None when the file is absent (the fitter then uses the frontal map). Raises ``ValueError`` naming
    the file when it lacks one of those arrays or their shapes disagree (e.g. the yaw-only
    ``mediapipe_ict_yaw.npz`` of earlier versions, which had no ``pitch``)."""
    p = Path(path) if path else POSE_ASSET
    if not p.is_file():
        return None
    with np.load(p) as d:
        out = {k: d[k] for k in d.files}
    missing = [k for k in ("yaw", "pitch", "vertex", "hits") if k not in out]
    if missing:
        raise ValueError(f"{p}: not a pose table (build_pose_table), missing {missing}; rebuild with python -m fastgha_core.tracking.meshmap --pose")
    yaw, pitch = out["yaw"], out["pitch"]
    shape = (len(pitch), len(yaw), 468)
    ascending = yaw.ndim == pitch.ndim == 1 and len(yaw) > 0 and len(pitch) > 0 and (np.diff(yaw) > 0).all() and (np.diff(pitch) > 0).all()
    if not ascending or out["vertex"].shape != shape or out["hits"].shape != shape:
        raise ValueError(f"{p}: expected ascending yaw [B >= 1] and pitch [P >= 1] bins and vertex, hits [P, B, 468], got yaw "
                         f"{yaw.tolist()}, pitch {pitch.tolist()}, vertex {list(out['vertex'].shape)}, hits {list(out['hits'].shape)}")
    return out


def _umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity ``s, R, t`` minimising ``|s R src + t - dst|^2`` (Umeyama 1991)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (a**2).sum(1).mean())
    return s, R, md - s * R @ ms


def _mesh3d(img: np.ndarray) -> np.ndarray:
    import mediapipe as mp

    h, w = img.shape[:2]
    with mp.solutions.face_mesh.FaceMesh(static_image_mode=True, max_num_faces=1) as fm:
        res = fm.process(np.ascontiguousarray(img))
    if not res.multi_face_landmarks:
        raise ValueError("no face in a reference portrait")
    p = np.array([[q.x * w, q.y * h, q.z * w] for q in res.multi_face_landmarks[0].landmark[:468]])
    return p * np.array([1.0, -1.0, -1.0])  # image axes -> head axes


def build_mediapipe_map() -> MediaPipeMap:
    """Recompute the correspondence (module doc); needs mediapipe, scikit-image and matplotlib."""
    import matplotlib.cbook as cbook
    import skimage.data
    from PIL import Image
    from scipy.optimize import lsq_linear
    from scipy.spatial import cKDTree

    from ..data.headmodel import HeadModel

    imgs = [skimage.data.astronaut(), np.asarray(Image.open(cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)).convert("RGB"))]
    meshes = [_mesh3d(im) for im in imgs]
    aligned = []
    for m in meshes:
        s, R, t = _umeyama(m, meshes[0])
        aligned.append(m @ R.T * s + t)
    tmpl = np.mean(aligned, axis=0)  # [468, 3]
    head = HeadModel.load()
    lm = head.landmarks68
    mp68 = np.array(MP68)
    Bi = head.identity_basis[:50, lm].reshape(50, -1).T.astype(np.float64)  # [204, 50]
    Be = head.expression_basis[:, lm].reshape(53, -1).T.astype(np.float64)  # [204, 53]
    beta, e = np.zeros(50), np.zeros(53)
    for _ in range(3):
        target = (head.neutral[lm] + (Bi @ beta + Be @ e).reshape(68, 3)).astype(np.float64)
        s, R, t = _umeyama(tmpl[mp68[17:]], target[17:])
        P = tmpl @ R.T * s + t  # [468, 3] metres, head space
        A = np.concatenate([np.concatenate([Bi, Be], 1), np.diag(np.r_[np.full(50, 0.05), np.full(53, 0.02)])])
        b = np.r_[(P[mp68] - head.neutral[lm]).reshape(-1), np.zeros(103)]
        sol = lsq_linear(A, b, bounds=(np.r_[np.full(50, -4.0), np.zeros(53)], np.r_[np.full(50, 4.0), np.ones(53)]))
        beta, e = sol.x[:50], sol.x[50:]
    verts = head.vertices(np.r_[beta, np.zeros(50)].astype(np.float32), e.astype(np.float32))[:FACE_VERTICES]
    d, idx = cKDTree(verts).query(P)
    keep = d * 1000.0 <= MAX_SNAP_MM
    return MediaPipeMap(np.flatnonzero(keep), idx[keep], np.round(d[keep] * 1000.0, 2))


def main(argv: list[str] | None = None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="python -m fastgha_core.tracking.meshmap", description="rebuild the Face Mesh -> ICT maps")
    p.add_argument("--pose", action="store_true",
                   help="rebuild the pose-dependent table (yaw x pitch, synthetic renders, ~30 s) instead")
    # --yaw rebuilt the yaw-only table (mediapipe_ict_yaw.npz) that the pose table replaced on
    # 2026-12-01; it still works for old scripts, but is hidden and warns: the name no longer says
    # what it builds (yaw x pitch, another file)
    p.add_argument("--yaw", dest="yaw", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.yaw:
        print("warning: --yaw is deprecated: the yaw-only table was replaced by the yaw x pitch pose table; "
              "use --pose (this run builds the pose table)", file=sys.stderr)
    if args.pose or args.yaw:
        d = build_pose_table()
        np.savez_compressed(POSE_ASSET, **d)
        print(f"wrote {POSE_ASSET}: yaw bins {d['yaw'].tolist()}, pitch bins {d['pitch'].tolist()}, "
              f"points with a hit per cell (pitch x yaw) {(d['vertex'] >= 0).sum(2).tolist()}")
        return 0
    m = build_mediapipe_map()
    MAP_ASSET.write_text(json.dumps({
        "source": "fastgha_core/tracking/meshmap.py (python -m fastgha_core.tracking.meshmap)",
        "mp_index": m.mp_index.tolist(), "ict_vertex": m.ict_vertex.tolist(), "snap_mm": m.snap_mm.tolist(),
    }))  # fmt: skip
    print(f"wrote {MAP_ASSET}: {len(m)} of 468 Face Mesh points tied to ICT vertices (median snap {np.median(m.snap_mm):.2f} mm)")
    return 0


# ---------------------------------------------------------------------------- pose-dependent map
YAW_BINS = (-90.0, -75.0, -60.0, -45.0, -30.0, -15.0, 0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)
CALIBRATION_SEEDS = tuple(range(1_000_100, 1_000_108))  # synthetic held-out subjects (data/synthetic.py)
PITCH_BINS = (-30.0, -15.0, 0.0, 15.0, 30.0, 45.0)  # -45: the detector's chin outline lands on the chest, its mean hit is meaningless
POSE_ASSET = MAP_ASSET.with_name("mediapipe_ict_pose.npz")


def build_pose_table(seeds=CALIBRATION_SEEDS, size: int = 512, fov_deg: float = 25.0, yaw_bins=YAW_BINS,
                     pitch_bins=PITCH_BINS, occlusion_mm: float | None = None) -> dict:
    """Where the Face Mesh puts its points on a turned or pitched head, measured on synthetic renders.

    The Face Mesh squeezes the far half of a turned face onto the visible half: on renders of the
    ICT head with known cameras, a 75-degree head fitted with the frontal map comes out at ~57.
    Pitch does the same to the lips, chin and nose: the points slide along the surface, so with the
    pitch-0 map a head pitched by -30 / +30 degrees comes out at about -15 / +25 and the codes
    absorb the rest (mouthStretch on heads pitched up; docs/tracking-log.md, "Pitched heads").
    For each (pitch, yaw) in ``pitch_bins x yaw_bins`` and each synthetic subject
    (``data/synthetic.py``, neutral expression, camera at 1 m looking at the head origin from
    azimuth ``-yaw`` and elevation ``-pitch``, ``fov_deg``; pitch + = nose up = camera below, as
    ``fit.head_angles_deg``) the render's Face Mesh points are cast onto the true mesh (the
    camera-facing face/head vertex whose projection is nearest, within 2 % of the face size), the
    hit vertices' generic positions are averaged over subjects and snapped to the nearest generic
    vertex. Deterministic (renders and detector).

    ``occlusion_mm`` (None, the shipped table): cast the points only onto vertices the render shows,
    at most this many millimetres behind its depth buffer (a variant tried and not kept,
    docs/tracking-log.md "Pitched heads").

    Returns ``{"yaw": [B] degrees, "pitch": [P] degrees, "vertex": [P, B, 468] int16 ICT vertex id
    (-1 = no hit in at least half of the renders), "hits": [P, B, 468] int16}``.
    Raises ImportError without mediapipe (``faces`` extra).
    """
    from scipy.spatial import cKDTree

    from ..cameras import Cameras
    from ..data.synthetic import SyntheticSubject
    from .faces import MeshDetector

    det = MeshDetector(min_face_px=1.0)
    P_, B = len(pitch_bins), len(yaw_bins)
    acc = np.zeros((P_, B, 468, 3))
    cnt = np.zeros((P_, B, 468))
    subj0 = None
    for seed in seeds:
        sub = SyntheticSubject(seed)
        head = sub.model
        subj0 = head
        frame = sub.frame(np.zeros(head.num_expression, np.float32))
        verts = sub.base.astype(np.float64)  # neutral expression: frame vertices = base
        normals = head.vertex_normals(verts)
        cand = np.arange(0, 11248)
        for q, pitch in enumerate(pitch_bins):
            for b, yaw in enumerate(yaw_bins):
                cam = Cameras.facing_head(yaw, pitch, fov_deg=fov_deg, size=size)  # azimuth -yaw, below the head for + pitch: nose up
                view = sub.render(frame, cam)[0]
                img = (view.image.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
                faces = det.detect_all(img)
                if not faces:
                    continue
                pts = faces[0][1]
                w2c = cam.w2c[0].double().numpy()
                K = cam.K[0].double().numpy()
                P = verts[cand] @ w2c[:3, :3].T + w2c[:3, 3]
                uv = (P @ K.T)[:, :2] / (P @ K.T)[:, 2:]
                front = ((normals[cand] @ w2c[:3, :3].T) * P).sum(1) < 0
                if occlusion_mm is not None:  # only vertices the render shows (not behind the lips, nose or chin)
                    depth = view.depth[0].numpy()
                    px = np.clip(np.round(uv - 0.5).astype(np.int64), 0, [size - 1, size - 1])
                    zb = depth[px[:, 1], px[:, 0]]
                    front &= (zb > 0) & (P[:, 2] <= zb + occlusion_mm / 1000.0)
                ids = cand[front]
                d, j = cKDTree(uv[front]).query(pts)
                face_px = np.linalg.norm(pts.max(0) - pts.min(0))
                ok = d < 0.02 * face_px
                acc[q, b, ok] += head.neutral[ids[j[ok]]]
                cnt[q, b, ok] += 1
    tree = cKDTree(subj0.neutral[:11248].astype(np.float64))
    vertex = np.full((P_, B, 468), -1, dtype=np.int16)
    good = cnt >= max(1, len(seeds) // 2)
    mean = acc[good] / cnt[good][:, None]
    vertex[good] = tree.query(mean)[1]
    return {"yaw": np.array(yaw_bins, dtype=np.float64), "pitch": np.array(pitch_bins, dtype=np.float64), "vertex": vertex,
            "hits": cnt.astype(np.int16)}


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
