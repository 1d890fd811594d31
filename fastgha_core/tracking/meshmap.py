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
    m = build_mediapipe_map()
    MAP_ASSET.write_text(json.dumps({
        "source": "fastgha_core/tracking/meshmap.py (python -m fastgha_core.tracking.meshmap)",
        "mp_index": m.mp_index.tolist(), "ict_vertex": m.ict_vertex.tolist(), "snap_mm": m.snap_mm.tolist(),
    }))  # fmt: skip
    print(f"wrote {MAP_ASSET}: {len(m)} of 468 Face Mesh points tied to ICT vertices (median snap {np.median(m.snap_mm):.2f} mm)")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
