"""Fit the ICT-FaceKit head model to 2D landmarks: one joint fit per person (bounded
Levenberg-Marquardt with priors).

Unknowns, for ``V`` photos of one person:
- identity ``beta [Ki]``: the first ``num_identity`` (50) ICT identity modes, **shared** by all
  photos, Gaussian prior ``identity_weight * |beta|^2`` (modes are ~N(0, 1));
- per photo: expression ``e_v [53]`` (``ict53``), **bounded to [0, 1]**, ridge prior
  ``expression_weight * |e_v|^2`` pulling unobservable shapes to 0; head rotation ``R_v``
  (head -> camera, updated multiplicatively ``R <- exp([d]x) R``) and translation ``t_v`` (metres).

The 3D landmarks are fixed vertices of the model in one of two layouts (``LandmarkModel``):
dlib's 68 points (``HeadModel.landmarks68``) or the MediaPipe Face Mesh points
(``meshmap.py``), linear in ``beta`` and ``e``: ``X = n + B_id beta + B_e e``. They are projected
with the given pinhole ``K`` (one focal length for the set, chosen by the caller: EXIF or
:func:`default_intrinsics`): ``u = K (R X + t)``. Residuals are landmark errors divided by
``landmark_sigma`` x the face size (the landmark box diagonal), so weights do not depend on the
image resolution; a dense layout's total weight is normalised to 68 points. dlib's 17 jaw-line
landmarks follow the visible silhouette, not fixed skin points, so they get ``contour_weight``;
Face Mesh points on the far side of the head get ``occluded_weight`` (``visibility_weights``).

Stages: a rigid-only fit per photo (pose only) from five yaw guesses (-60 .. +60 degrees) keeps
the best; the joint fit; for the Face Mesh layout, ``yaw_map_rounds`` rounds that re-tie each
photo's points to the vertices the detector lands on at its current yaw and pitch (``meshmap``'s
pose table; the pitch clipped to ``[pitch_map_min_deg, pitch_map_max_deg]``); for the Face Mesh layout without a warm start, a re-pose (identity and expressions fixed)
of the photos turned beyond the fit's saturation towards the yaw regressed from the 2D layout
(``yawprior.py``, ``FitConfig.yaw_prior``); optionally the outline of a person mask for side
views (``silhouette.py``).

Solver: Levenberg-Marquardt on the stacked residuals with the analytic Jacobian (dense normal
equations; checked against finite differences in the tests). The box [0, 1] on ``e`` is kept by
an active set: weights at a bound whose gradient points outwards are frozen for the step, the
step is clamped.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["FitConfig", "FitResult", "KnownCameraFit", "LandmarkModel", "fit_landmarks", "fit_known_cameras", "default_intrinsics", "intrinsics_from_35mm", "rodrigues", "FRONTAL_R", "head_angles_deg"]

logger = logging.getLogger(__name__)

# Head -> camera rotation of a head looking straight into the camera: head +y up -> camera -y
# (down), head +z out of the face -> camera -z (towards the camera), head +x -> camera +x.
FRONTAL_R = np.diag([1.0, -1.0, -1.0])

CONTOUR = slice(0, 17)  # dlib jaw-line landmarks

# ict53 shapes that 68 sparse landmarks hardly see (gaze, cheeks, squints, nose, dimples): on
# real photos they absorb the mismatch between dlib's landmark definitions and the model's fixed
# vertices, so they get a much stronger prior (``weak_expression_weight``).
WEAKLY_OBSERVED = (
    "cheekPuff_L", "cheekPuff_R", "cheekSquint_L", "cheekSquint_R", "eyeLookDown_L", "eyeLookDown_R",
    "eyeLookIn_L", "eyeLookIn_R", "eyeLookOut_L", "eyeLookOut_R", "eyeLookUp_L", "eyeLookUp_R",
    "eyeSquint_L", "eyeSquint_R", "eyeWide_L", "eyeWide_R", "noseSneer_L", "noseSneer_R",
    "mouthDimple_L", "mouthDimple_R", "jawForward",
)  # fmt: skip


@dataclass
class FitConfig:
    """Options of :func:`fit_landmarks` (see module doc)."""

    num_identity: int = 50  # identity modes estimated (of 100); the rest stay 0
    identity_weight: float = 0.3  # prior weight on |beta|^2 (modes ~ N(0, 1))
    # ridge weights on |e|^2 per photo. 10 / 40 (was 1 / 20 with dlib): on calm real photos the
    # differences between the detector's landmark definitions and the model's vertices otherwise come
    # out as saturated shapes (browDown 0.7, mouthLeft 0.8); docs/tracking-log.md has the trade-off figures
    expression_weight: float = 10.0
    weak_expression_weight: float = 40.0  # ridge weight of the shapes in WEAKLY_OBSERVED
    landmark_sigma: float = 0.01  # landmark noise, as a fraction of the face-box diagonal
    contour_weight: float = 0.5  # weight of the 17 jaw-line landmarks (silhouette, not fixed points)
    iterations: int = 40  # LM iterations of the full fit
    rigid_iterations: int = 10  # LM iterations of the rigid stage (per yaw guess)
    yaw_guesses_deg: tuple[float, ...] = (-60.0, -30.0, 0.0, 30.0, 60.0)
    occluded_weight: float = 0.1  # weight of points on the far side of the head (visibility_weights)
    silhouette_weight: float = 1.0  # outline points of a photo together weigh this x its landmarks (silhouette.py)
    silhouette_clip: float = 0.08  # outline residuals are clipped at this fraction of the face size
    silhouette_min_yaw: float = 30.0  # use the outline for photos turned at least this much (degrees)
    silhouette_rounds: int = 3  # outline points re-chosen this many times
    yaw_map: bool = True  # Face Mesh layout: tie points to vertices by the head's pose (meshmap.build_pose_table; its pitch axis: pitch_map)
    yaw_map_rounds: int = 3  # re-chosen this many times as the yaw (and pitch) moves
    # the map's pitch axis too (meshmap.build_pose_table): the Face Mesh's lip, chin and nose points slide
    # on pitched heads; with the pitch-0 map, heads pitched up read short and grow mouthStretch (docs/tracking-log.md, "Pitched heads")
    pitch_map: bool = True
    # the pitch range over which the map follows the head (degrees, + = nose up); beyond it, the map of the
    # nearest end. Pitched-down rows are shipped but not used by default: on renders they help as much as the
    # pitched-up ones, on the real sets they read the pitched-down photo at -43 and frontal photos 4-5 degrees
    # lower, and the avatars from those cameras lose 0.3-1.4 dB (docs/tracking-log.md, "Pitched heads")
    pitch_map_min_deg: float = 0.0
    pitch_map_max_deg: float = 45.0
    # Face Mesh layout: beyond ~60 degrees the landmark fit saturates; a regression from the 2D layout
    # to the yaw (yawprior.py, learned on synthetic renders) then pulls the yaw further out, for photos
    # the fit finds turned >= yaw_prior_min_fit_deg that the regression finds turned further and >= yaw_prior_min_deg
    yaw_prior: bool = True
    yaw_prior_min_deg: float = 55.0  # where the fit starts to saturate on synthetic renders
    yaw_prior_min_fit_deg: float = 30.0
    yaw_prior_sigma_deg: float = 0.2  # the prior's residual is (yaw - regressed yaw) / this (0.2: nearly a constraint)
    # a photo whose landmark RMS exceeds this fraction of its face size under the prior keeps its
    # landmark-only pose (the pipeline refuses photos beyond 6 %: the prior must not cause a refusal)
    yaw_prior_max_rms: float = 0.05
    tolerance: float = 1e-7  # stop when the relative cost decrease is below this


@dataclass
class FitResult:
    """Fitted parameters for ``V`` photos."""

    identity: np.ndarray  # [100] float64, zeros beyond num_identity
    expressions: np.ndarray  # [V, 53] float64 in [0, 1]
    rotations: np.ndarray  # [V, 3, 3] head -> camera
    translations: np.ndarray  # [V, 3] metres (head origin in camera coordinates)
    K: np.ndarray  # [V, 3, 3] the intrinsics used
    rms_px: np.ndarray  # [V] RMS landmark reprojection error in pixels
    cost: float = 0.0
    outline_px: np.ndarray | None = None  # [V] RMS distance of the model's outline to the mask's (px); NaN = not used

    def project(self, model: "LandmarkModel", v: int) -> np.ndarray:
        """Projected model landmarks ``[N, 2]`` of photo ``v``."""
        X = model.points(self.identity[: model.num_identity], self.expressions[v])
        return _project(X, self.rotations[v], self.translations[v], self.K[v])[0]


@dataclass
class LandmarkModel:
    """The head model restricted to ``N`` landmark vertices (metres, axes of docs/conventions.md).

    Two layouts: ``"dlib68"`` (the model's ``landmarks68`` vertices, dlib's order; the 17 jaw
    points get ``contour_weight``) and ``"mediapipe"`` (the Face Mesh points of
    ``meshmap.load_mediapipe_map()``, in its ``mp_index`` order).
    """

    mean: np.ndarray  # [N, 3]
    identity: np.ndarray  # [Ki, N, 3]
    expression: np.ndarray  # [53, N, 3]
    num_total_identity: int = 100
    layout: str = "dlib68"
    vertex_ids: np.ndarray | None = None  # [N] ICT vertex ids
    normals: np.ndarray | None = None  # [N, 3] unit normals of the generic neutral at those vertices
    _flat_id: np.ndarray = field(init=False, repr=False)
    _flat_ex: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._flat_id = self.identity.reshape(self.identity.shape[0], -1).T.copy()  # [3N, Ki]
        self._flat_ex = self.expression.reshape(self.expression.shape[0], -1).T.copy()  # [3N, 53]

    @property
    def num_identity(self) -> int:
        return int(self.identity.shape[0])

    @property
    def num_points(self) -> int:
        return int(self.mean.shape[0])

    @staticmethod
    def from_head_model(head=None, num_identity: int = 30, layout: str = "dlib68") -> "LandmarkModel":
        from ..data.headmodel import HeadModel

        head = HeadModel.load() if head is None else head
        if layout == "dlib68":
            lm = np.asarray(head.landmarks68)
        elif layout == "mediapipe":
            from .meshmap import load_mediapipe_map

            lm = load_mediapipe_map().ict_vertex
        else:
            raise ValueError(f"layout must be 'dlib68' or 'mediapipe', got {layout!r}")
        if not 0 <= num_identity <= head.num_identity:
            raise ValueError(f"num_identity must be in [0, {head.num_identity}], got {num_identity}")
        normals = _model_normals(head)[lm]
        return LandmarkModel(
            mean=head.neutral[lm].astype(np.float64),
            identity=head.identity_basis[:num_identity, lm].astype(np.float64),
            expression=head.expression_basis[:, lm].astype(np.float64),
            num_total_identity=head.num_identity,
            layout=layout,
            vertex_ids=lm,
            normals=normals.astype(np.float64),
        )

    def points(self, beta: np.ndarray, e: np.ndarray) -> np.ndarray:
        """Landmark points ``[N, 3]`` for identity ``[Ki]`` and expression ``[53]``."""
        flat = self.mean.reshape(-1) + self._flat_id @ beta + self._flat_ex @ e
        return flat.reshape(-1, 3)

    @staticmethod
    def from_vertex_ids(head, ids: np.ndarray, num_identity: int, layout: str) -> "LandmarkModel":
        ids = np.asarray(ids, dtype=np.int64)
        return LandmarkModel(
            mean=head.neutral[ids].astype(np.float64),
            identity=head.identity_basis[:num_identity, ids].astype(np.float64),
            expression=head.expression_basis[:, ids].astype(np.float64),
            num_total_identity=head.num_identity,
            layout=layout,
            vertex_ids=ids,
            normals=_model_normals(head)[ids].astype(np.float64),
        )

    def blend(self, other: "LandmarkModel", a: float) -> "LandmarkModel":
        """``(1 - a) * self + a * other`` point by point (both linear in identity and expression)."""
        if a <= 0.0:
            return self
        if a >= 1.0:
            return other
        n = self.normals * (1 - a) + other.normals * a
        return LandmarkModel(
            mean=(1 - a) * self.mean + a * other.mean,
            identity=(1 - a) * self.identity + a * other.identity,
            expression=(1 - a) * self.expression + a * other.expression,
            num_total_identity=self.num_total_identity,
            layout=self.layout,
            vertex_ids=self.vertex_ids,
            normals=n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9),
        )

    def base_weights(self, cfg: "FitConfig") -> np.ndarray:
        """``[N]`` per-point weights of the layout (dlib's jaw line: ``contour_weight``)."""
        w = np.ones(self.num_points)
        if self.layout == "dlib68":
            w[CONTOUR] = cfg.contour_weight
        return w


_NORMALS: dict[int, np.ndarray] = {}


def _model_normals(head) -> np.ndarray:
    key = id(head)
    if key not in _NORMALS:
        _NORMALS[key] = head.vertex_normals(head.neutral)
    return _NORMALS[key]


def default_intrinsics(width: int, height: int, fov_deg: float = 30.0) -> np.ndarray:
    """The assumed pinhole ``K [3, 3]``: field of view ``fov_deg`` across the **longer** image side,
    principal point at the image centre, square pixels.

    30 degrees is between a phone's main camera (~65 degrees, 26 mm equivalent) and a portrait lens
    (~15 degrees, 85 mm): a wrong focal length mostly changes the fitted distance (the head's image
    size fixes f / z), hardly the rotation.
    """
    if not 1.0 <= fov_deg <= 150.0:
        raise ValueError(f"fov_deg must be in [1, 150] degrees, got {fov_deg}")
    f = 0.5 * max(width, height) / math.tan(math.radians(fov_deg) / 2)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def intrinsics_from_35mm(width: int, height: int, focal_35mm: float) -> np.ndarray:
    """``K [3, 3]`` from a 35 mm-equivalent focal length (EXIF ``FocalLengthIn35mmFilm``), in mm.

    The equivalent focal length is defined on the diagonal: ``f_px = f_35 * diag_px / 43.27 mm``
    (the diagonal of a 36 x 24 mm frame). Principal point at the centre, square pixels.
    """
    if not 4.0 <= focal_35mm <= 2000.0:
        raise ValueError(f"focal_35mm must be in [4, 2000] mm, got {focal_35mm}")
    f = focal_35mm * math.hypot(width, height) / math.hypot(36.0, 24.0)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def rodrigues(w: np.ndarray) -> np.ndarray:
    """Axis-angle ``[3]`` -> rotation ``[3, 3]``."""
    t = float(np.linalg.norm(w))
    S = _skew(w)
    if t < 1e-8:
        return np.eye(3) + S + 0.5 * S @ S
    return np.eye(3) + math.sin(t) / t * S + (1 - math.cos(t)) / t**2 * (S @ S)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _project(X: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray):
    """``X [N, 3]`` -> uv ``[N, 2]``, camera points ``P [N, 3]``."""
    P = X @ R.T + t
    z = np.maximum(P[:, 2], 1e-6)
    uv = np.stack([K[0, 0] * P[:, 0] / z + K[0, 1] * P[:, 1] / z + K[0, 2], K[1, 1] * P[:, 1] / z + K[1, 2]], axis=1)
    return uv, P


def _dproj(P: np.ndarray, K: np.ndarray) -> np.ndarray:
    """d uv / d P ``[N, 2, 3]`` (skew K[0,1] ignored in the derivative; it is 0 for our cameras)."""
    z = np.maximum(P[:, 2], 1e-6)
    J = np.zeros((P.shape[0], 2, 3))
    J[:, 0, 0] = K[0, 0] / z
    J[:, 0, 2] = -K[0, 0] * P[:, 0] / z**2
    J[:, 1, 1] = K[1, 1] / z
    J[:, 1, 2] = -K[1, 1] * P[:, 1] / z**2
    return J


class _Problem:
    """Stacked residuals and Jacobian for V views (internal)."""

    def __init__(self, model: LandmarkModel, obs: np.ndarray, K: np.ndarray, cfg: FitConfig, weights: np.ndarray | None,
                 free_identity: bool, free_expression: bool):
        self.m, self.obs, self.K, self.cfg = model, obs, K, cfg
        self.ms = [model] * obs.shape[0]  # per view (the yaw-dependent Face Mesh map gives each view its own)
        self.V, self.N = obs.shape[0], obs.shape[1]
        # per-point weights; a dense layout's points are not independent (their errors are smooth
        # over the face), so the total weight is normalised to 68 points and the priors keep their meaning
        w = np.broadcast_to(model.base_weights(cfg) * min(1.0, 68.0 / self.N), (self.V, self.N)).copy()
        if weights is not None:
            w = w * np.broadcast_to(np.asarray(weights, dtype=np.float64), (self.V, self.N))
        diag = np.linalg.norm(obs.max(axis=1) - obs.min(axis=1), axis=1)  # [V]
        self.scale = np.sqrt(w) / (cfg.landmark_sigma * np.maximum(diag, 1.0))[:, None]  # [V, N]
        self._w0 = model.base_weights(cfg) * min(1.0, 68.0 / self.N)
        self.free_id = free_identity and model.num_identity > 0
        self.free_ex = free_expression
        self.nid = model.num_identity if self.free_id else 0
        self.nex = 53 if free_expression else 0
        self.nv = 6 + self.nex
        from ..expressions import ICT53_NAMES

        ew = np.full(53, cfg.expression_weight)
        ew[[ICT53_NAMES.index(n) for n in WEAKLY_OBSERVED]] = cfg.weak_expression_weight
        self.ex_sqrt_w = np.sqrt(ew)  # [53]
        self.sil: list[dict | None] = [None] * self.V  # per view: outline terms (set_silhouettes)
        self.yaw_target = np.full(self.V, np.nan)  # per view: regressed yaw (radians) pulled towards, NaN = none
        self.diag = diag

    def set_weights(self, weights: np.ndarray) -> None:
        """Replace the extra per-point weights ``[V, N]`` (the layout's own weights stay)."""
        self.scale = np.sqrt(self._w0[None] * weights) / (self.cfg.landmark_sigma * np.maximum(self.diag, 1.0))[:, None]

    def set_silhouettes(self, head, targets, beta, E, Rs, ts) -> int:
        """Choose each view's outline points at the current estimate (silhouette.py); returns their count."""
        from .silhouette import outline_vertices

        n = 0
        for v, tg in enumerate(targets):
            self.sil[v] = None
            if tg is None:
                continue
            full_id = np.zeros(head.num_identity, dtype=np.float32)
            full_id[: self.m.num_identity] = beta
            verts = head.vertices(full_id, E[v].astype(np.float32)).astype(np.float64)
            h, w = tg.sdf.shape
            ids = outline_vertices(head, verts, Rs[v], ts[v], self.K[v], w, h)
            if len(ids) < 5:
                continue
            Ki = self.m.num_identity
            # weight: all outline points of a photo together weigh silhouette_weight x its landmarks
            wsum = float((self.scale[v] ** 2).sum()) * 2.0
            per = self.cfg.silhouette_weight * wsum / len(ids)
            self.sil[v] = {
                "mean": head.neutral[ids].astype(np.float64),
                "idb": head.identity_basis[:Ki, ids].astype(np.float64),
                "exb": head.expression_basis[:, ids].astype(np.float64),
                "target": tg, "sqrt_w": math.sqrt(per), "clip": self.cfg.silhouette_clip * tg.face_px,
            }  # fmt: skip
            n += len(ids)
        return n

    def _sil_points(self, v, beta, e):
        s = self.sil[v]
        return s["mean"] + np.einsum("k,knd->nd", beta, s["idb"]) + np.einsum("k,knd->nd", e, s["exb"])

    def _sil_residuals(self, beta, E, Rs, ts) -> list[np.ndarray]:
        out = []
        for v in range(self.V):
            if self.sil[v] is None:
                continue
            s = self.sil[v]
            uv, _ = _project(self._sil_points(v, beta, E[v]), Rs[v], ts[v], self.K[v])
            val, _ = s["target"].sample(uv, s["clip"])
            out.append(s["sqrt_w"] * val)
        return out

    def residuals(self, beta, E, Rs, ts) -> np.ndarray:
        out = []
        for v in range(self.V):
            uv, _ = _project(self.ms[v].points(beta, E[v]), Rs[v], ts[v], self.K[v])
            out.append(((uv - self.obs[v]) * self.scale[v][:, None]).reshape(-1))
        if self.free_id:
            out.append(math.sqrt(self.cfg.identity_weight) * beta)
        if self.free_ex:
            out.append((self.ex_sqrt_w[None] * E).reshape(-1))
        out.extend(self._sil_residuals(beta, E, Rs, ts))
        out.append(self._yaw_residuals(Rs))
        return np.concatenate(out)

    def _yaw_residuals(self, Rs) -> np.ndarray:
        k = np.flatnonzero(np.isfinite(self.yaw_target))
        y = np.array([math.atan2(Rs[v][0, 2], -Rs[v][2, 2]) for v in k])
        return (y - self.yaw_target[k]) / math.radians(self.cfg.yaw_prior_sigma_deg)

    def jacobian(self, beta, E, Rs, ts) -> np.ndarray:
        n2 = 2 * self.N
        n_lm = self.V * n2
        n_sil = sum(len(s["mean"]) for s in self.sil if s is not None)
        yaw_views = np.flatnonzero(np.isfinite(self.yaw_target))
        n_rows = n_lm + self.nid + self.V * self.nex + n_sil + len(yaw_views)
        n_cols = self.nid + self.V * self.nv
        J = np.zeros((n_rows, n_cols))
        r0 = n_lm + self.nid + self.V * self.nex
        for v in range(self.V):
            if self.sil[v] is None:
                continue
            s = self.sil[v]
            X = self._sil_points(v, beta, E[v])
            uv, P = _project(X, Rs[v], ts[v], self.K[v])
            _, g = s["target"].sample(uv, s["clip"])  # [M, 2]
            D = np.einsum("ni,nij->nj", g, _dproj(P, self.K[v])) * s["sqrt_w"]  # [M, 3]
            m = D.shape[0]
            rows = slice(r0, r0 + m)
            c0 = self.nid + v * self.nv
            J[rows, c0 : c0 + 3] = np.cross(P - ts[v], D)
            J[rows, c0 + 3 : c0 + 6] = D
            DR = D @ Rs[v]  # [M, 3]
            if self.free_ex:
                J[rows, c0 + 6 : c0 + 6 + 53] = np.einsum("nk,ank->na", DR, s["exb"])
            if self.free_id:
                J[rows, : self.nid] = np.einsum("nk,ank->na", DR, s["idb"])
            r0 += m
        for v in yaw_views:  # yaw = atan2(n0, -n2), n = R[:, 2]; R <- exp([d]x) R gives dn = d x n
            n = Rs[v][:, 2]
            g = np.array([-n[2], 0.0, n[0]]) / max(n[0] ** 2 + n[2] ** 2, 1e-12)  # d yaw / d n
            J[r0, self.nid + v * self.nv : self.nid + v * self.nv + 3] = np.cross(n, g) / math.radians(self.cfg.yaw_prior_sigma_deg)
            r0 += 1
        for v in range(self.V):
            X = self.ms[v].points(beta, E[v])
            _, P = _project(X, Rs[v], ts[v], self.K[v])
            D = _dproj(P, self.K[v]) * self.scale[v][:, None, None]  # [N, 2, 3]
            rows = slice(v * n2, (v + 1) * n2)
            c0 = self.nid + v * self.nv
            RX = P - ts[v]
            # d(R X)/d(rotation increment) = -[RX]x, so d uv / d rot = D @ -[RX]x = cross(RX, D rows)
            J[rows, c0 : c0 + 3] = np.cross(RX[:, None, :], D).reshape(n2, 3)
            J[rows, c0 + 3 : c0 + 6] = D.reshape(n2, 3)
            DR = np.einsum("nij,jk->nik", D, Rs[v])  # [N, 2, 3]: d uv / d X
            if self.free_ex:
                J[rows, c0 + 6 : c0 + 6 + 53] = np.einsum("nik,ank->nia", DR, self.ms[v].expression).reshape(n2, 53)
            if self.free_id:
                J[rows, : self.nid] = np.einsum("nik,ank->nia", DR, self.ms[v].identity).reshape(n2, self.nid)
        if self.free_id:
            J[n_lm : n_lm + self.nid, : self.nid] = math.sqrt(self.cfg.identity_weight) * np.eye(self.nid)
        if self.free_ex:
            for v in range(self.V):
                r0 = n_lm + self.nid + v * 53
                c0 = self.nid + v * self.nv + 6
                J[r0 : r0 + 53, c0 : c0 + 53] = np.diag(self.ex_sqrt_w)
        return J

    def apply(self, x, beta, E, Rs, ts):
        beta, E, Rs, ts = beta.copy(), E.copy(), Rs.copy(), ts.copy()
        if self.free_id:
            beta = beta + x[: self.nid]
        for v in range(self.V):
            c0 = self.nid + v * self.nv
            Rs[v] = rodrigues(x[c0 : c0 + 3]) @ Rs[v]
            ts[v] = ts[v] + x[c0 + 3 : c0 + 6]
            if self.free_ex:
                E[v] = np.clip(E[v] + x[c0 + 6 : c0 + 6 + 53], 0.0, 1.0)
        return beta, E, Rs, ts

    def expression_columns(self) -> np.ndarray:
        """``[V, 53]`` column index of each expression unknown."""
        return np.array([[self.nid + v * self.nv + 6 + k for k in range(53)] for v in range(self.V)])


def _gram(J: np.ndarray, chunk: int = 256) -> np.ndarray:
    """``J.T @ J`` for ``J [M, n]`` whose rows each touch few columns (a view's landmarks touch the
    identity and that view's pose and expression, a prior its own unknowns): per chunk of ``chunk``
    rows, only the columns the chunk touches are multiplied. Equal to the dense product up to float
    rounding (the sums run in another order)."""
    n = J.shape[1]
    H = np.zeros((n, n))
    for r0 in range(0, J.shape[0], chunk):
        Jc = J[r0 : r0 + chunk]
        cols = np.flatnonzero(np.any(Jc != 0.0, axis=0))
        if len(cols) == 0:
            continue
        if len(cols) > 0.7 * n:
            H += Jc.T @ Jc
        else:
            Js = Jc[:, cols]
            H[np.ix_(cols, cols)] += Js.T @ Js
    return H


def _lm(prob: _Problem, beta, E, Rs, ts, iterations: int, tol: float, reduce=None):
    """Levenberg-Marquardt on ``prob``. ``reduce = (T [n_full, n_red], ecols [V, 53])``: the unknowns
    are ``x_red`` with ``x_full = T x_red`` (the known-camera fit's one shared head pose), ``ecols``
    the reduced columns of the expressions."""
    r = prob.residuals(beta, E, Rs, ts)
    cost = 0.5 * float(r @ r)
    lam = 1e-3
    T = None
    ecols = prob.expression_columns() if prob.free_ex else None
    if reduce is not None:
        T, ecols = reduce
    for _ in range(iterations):
        J = prob.jacobian(beta, E, Rs, ts)
        g, H = J.T @ r, _gram(J)
        if T is not None:  # the reduced unknowns: J T
            g, H = T.T @ g, T.T @ H @ T
        free = np.ones(H.shape[0], dtype=bool)
        if ecols is not None:  # active set of the [0, 1] box
            gi = g[ecols]
            free[ecols[((E <= 0.0) & (gi > 0)) | ((E >= 1.0) & (gi < 0))]] = False
        idx = np.flatnonzero(free)
        Hf, gf = H[np.ix_(idx, idx)], g[idx]
        improved = False
        for _ in range(8):
            A = Hf + lam * (np.diag(np.diag(Hf)) + 1e-9 * np.eye(len(idx)))
            try:
                step = -np.linalg.solve(A, gf)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            x = np.zeros(H.shape[0])
            x[idx] = step
            if T is not None:
                x = T @ x
            nb, nE, nR, nt = prob.apply(x, beta, E, Rs, ts)
            nr = prob.residuals(nb, nE, nR, nt)
            ncost = 0.5 * float(nr @ nr)
            if ncost < cost:
                rel = (cost - ncost) / max(cost, 1e-12)
                beta, E, Rs, ts, r, cost = nb, nE, nR, nt, nr, ncost
                lam = max(lam / 3.0, 1e-7)
                improved = True
                break
            lam *= 4.0
        if not improved or rel < tol:
            break
    return beta, E, Rs, ts, cost


def _initial_translation(model: LandmarkModel, obs: np.ndarray, K: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Translation placing the rotated mean landmarks over the observed ones (scale from spread)."""
    X = model.mean @ R.T
    spread_m = np.sqrt(((X[:, :2] - X[:, :2].mean(0)) ** 2).sum(1).mean())
    spread_px = np.sqrt(((obs - obs.mean(0)) ** 2).sum(1).mean())
    f = 0.5 * (K[0, 0] + K[1, 1])
    z = f * spread_m / max(spread_px, 1e-6)
    c = obs.mean(0)
    ray = np.linalg.solve(K, np.array([c[0], c[1], 1.0]))
    return ray * z - X.mean(0)


_YAW_MODELS: dict = {}


def _yaw_models(model: "LandmarkModel"):
    """``(yaws [B], pitches [P], models [P][B], valid [P, B, N])`` of the pose-dependent Face Mesh
    map (``meshmap.load_pose_table``), or None when no table is shipped. Yaw columns the detector does not reach at pitch 0 (fewer
    than half of the points hit) are dropped; a cell of a kept column that the detector does not
    reach takes the cell next to it towards pitch 0, so the grid is full for the bilinear blend."""
    key = (model.num_identity, id(model.vertex_ids) if model.vertex_ids is None else model.vertex_ids.tobytes())
    if key not in _YAW_MODELS:
        from ..data.headmodel import HeadModel
        from .meshmap import load_mediapipe_map, load_pose_table

        tab = load_pose_table()
        if tab is None:
            _YAW_MODELS[key] = None
        else:
            head = HeadModel.load()
            mp_index = load_mediapipe_map().mp_index
            pitches = np.asarray(tab["pitch"], dtype=np.float64)
            vert = np.asarray(tab["vertex"], dtype=np.int64)[:, :, mp_index]  # [P, B, N]
            q0 = int(np.argmin(np.abs(pitches)))
            valid = vert >= 0
            cols = [b for b in range(vert.shape[1]) if valid[q0, b].mean() >= 0.5]  # yaws the detector reaches
            for q in sorted(range(len(pitches)), key=lambda q: abs(q - q0)):  # fill outwards from pitch 0
                if q == q0:
                    continue
                toward = q + 1 if q < q0 else q - 1
                for b in cols:
                    if valid[q, b].mean() < 0.5:
                        vert[q, b], valid[q, b] = vert[toward, b], valid[toward, b]
            models = [[LandmarkModel.from_vertex_ids(head, np.where(valid[q, b], vert[q, b], model.vertex_ids), model.num_identity, model.layout)
                       for b in cols] for q in range(len(pitches))]  # fmt: skip
            _YAW_MODELS[key] = (np.asarray(tab["yaw"], dtype=np.float64)[cols], pitches, models, valid[:, cols])
    return _YAW_MODELS[key]


def _bin(bins: np.ndarray, x: float) -> tuple[int, float]:
    """Lower bin index and blend fraction of ``x`` (clipped to the bins' range); (0, 0) for a single bin."""
    if len(bins) == 1:
        return 0, 0.0
    x = float(np.clip(x, bins[0], bins[-1]))
    b = int(np.clip(np.searchsorted(bins, x) - 1, 0, len(bins) - 2))
    return b, (x - bins[b]) / (bins[b + 1] - bins[b])


def _model_at_yaw(table, yaw: float, pitch: float = 0.0):
    """The model blended bilinearly from the four (pitch, yaw) cells around the pose (degrees,
    clipped to the table's range) and the points' weights ``[N]`` (0 = no hit)."""
    yaws, pitches, models, oks = table
    b, a = _bin(yaws, yaw)
    q, c = _bin(pitches, pitch)
    b1, q1 = min(b + 1, len(yaws) - 1), min(q + 1, len(pitches) - 1)
    lo = models[q][b].blend(models[q][b1], a)
    hi = models[q1][b].blend(models[q1][b1], a)
    w = (1 - c) * ((1 - a) * oks[q, b] + a * oks[q, b1]) + c * ((1 - a) * oks[q1, b] + a * oks[q1, b1])
    return lo.blend(hi, c), w.astype(np.float64)


def _use_yaw_map(prob: "_Problem", table, Rs: np.ndarray, ts: np.ndarray, base: np.ndarray, cfg: "FitConfig") -> None:
    """Give each photo of ``prob`` the pose map's model at its current yaw and pitch (``Rs [V, 3, 3]``)
    and the weights ``base [V, N]`` times the map's hits (times the visibility ramp when
    ``occluded_weight`` < 1)."""
    wv = base.copy()
    for v in range(len(Rs)):
        prob.ms[v], hit = _model_at_yaw(table, _yaw_deg(Rs[v]), _map_pitch(Rs[v], cfg))
        wv[v] *= hit
        if cfg.occluded_weight < 1.0:
            wv[v] *= visibility_weights(prob.ms[v], Rs[v : v + 1], ts[v : v + 1], cfg.occluded_weight)[0]
    prob.set_weights(wv)


def _pose_table(model: "LandmarkModel", cfg: "FitConfig"):
    """The pose map for ``fit_landmarks`` / ``fit_known_cameras``: None unless the Face Mesh layout
    and ``cfg.yaw_map``."""
    if not (cfg.yaw_map and model.layout == "mediapipe"):
        return None
    return _yaw_models(model)


def _map_pitch(R: np.ndarray, cfg: "FitConfig") -> float:
    """The pitch (degrees) at which the pose map is read for a head -> camera rotation ``R``: the
    head's pitch clipped to ``[cfg.pitch_map_min_deg, cfg.pitch_map_max_deg]``, or 0 (the yaw-only
    map) without ``cfg.pitch_map``. Raises ``ValueError`` when ``pitch_map_min_deg > pitch_map_max_deg``."""
    if not cfg.pitch_map:
        return 0.0
    if cfg.pitch_map_min_deg > cfg.pitch_map_max_deg:
        raise ValueError(f"FitConfig: pitch_map_min_deg ({cfg.pitch_map_min_deg:g}) must not exceed pitch_map_max_deg ({cfg.pitch_map_max_deg:g})")
    return float(np.clip(head_angles_deg(R)[1], cfg.pitch_map_min_deg, cfg.pitch_map_max_deg))


def landmark_models(model: "LandmarkModel", rotations: np.ndarray, cfg: "FitConfig") -> list["LandmarkModel"]:
    """The landmark model of each photo at its pose (``rotations [V, 3, 3]``): the pose map's blend
    (``_model_at_yaw``) for the Face Mesh layout when ``cfg.yaw_map`` and the table is shipped, else
    ``model`` itself; the models ``fit_landmarks`` measures its ``rms_px`` with."""
    table = _pose_table(model, cfg)
    return [model if table is None else _model_at_yaw(table, _yaw_deg(R), _map_pitch(R, cfg))[0] for R in rotations]


def head_angles_deg(R: np.ndarray) -> tuple[float, float, float]:
    """(yaw, pitch, roll) in degrees of a head -> camera rotation ``R [3, 3]`` (OpenCV camera).

    yaw: + = nose towards the image's right edge; pitch: + = nose up; roll: + = the head's up axis
    turned clockwise in the image. 0, 0, 0 = looking straight into the camera (``FRONTAL_R``).
    """
    n = R[:, 2]  # the nose direction (head +z) in camera axes
    up = R[:, 1]  # head +y
    yaw = math.degrees(math.atan2(n[0], -n[2]))
    pitch = math.degrees(math.atan2(-n[1], math.hypot(n[0], n[2])))
    roll = math.degrees(math.atan2(up[0], -up[1]))
    return yaw, pitch, roll


def _yaw_deg(R: np.ndarray) -> float:
    """Yaw of a head -> camera rotation (``head_angles_deg``): + = nose towards the image's right."""
    return head_angles_deg(R)[0]


def _regressed_yaw_targets(obs: np.ndarray, Rs: np.ndarray, cfg: FitConfig) -> np.ndarray:
    """``[V]`` yaw (radians) the prior pulls each photo to (``yawprior.py``), NaN where it does not apply."""
    from .meshmap import load_mediapipe_map
    from .yawprior import load_regression, predict_yaw

    out = np.full(obs.shape[0], np.nan)
    coef = load_regression()
    if coef is None:
        return out
    mp_index = load_mediapipe_map().mp_index
    for v in range(obs.shape[0]):
        yf = _yaw_deg(Rs[v])
        if abs(yf) < cfg.yaw_prior_min_fit_deg:
            continue
        full = np.zeros((468, 2))
        full[mp_index] = obs[v]
        try:
            yr = predict_yaw(full, coef)
        except ValueError:
            continue
        if yr * yf > 0 and abs(yr) >= cfg.yaw_prior_min_deg and abs(yr) > abs(yf):
            out[v] = math.radians(yr)
    return out


def visibility_weights(model: LandmarkModel, Rs: np.ndarray, ts: np.ndarray, occluded: float) -> np.ndarray:
    """``[V, N]`` weights: 1 for points whose (generic) normal faces the camera, down to ``occluded``
    for points on the far side of the head (their positions are guessed by the landmark detector),
    a smooth ramp over ``cos = -0.1 .. 0.25`` between the normal and the direction to the camera."""
    out = np.ones((Rs.shape[0], model.num_points))
    for v in range(Rs.shape[0]):
        P = model.mean @ Rs[v].T + ts[v]
        n = model.normals @ Rs[v].T
        c = -(n * P).sum(1) / np.maximum(np.linalg.norm(P, axis=1), 1e-9)
        out[v] = occluded + (1.0 - occluded) * np.clip((c + 0.1) / 0.35, 0.0, 1.0)
    return out


def fit_landmarks(*args, **kwargs) -> FitResult:
    """Fit identity (shared), expression and head pose (per photo) to 2D landmarks (module doc).

    Args:
        landmarks: ``[V, N, 2]`` (or ``[N, 2]``) pixels, in the layout of ``model`` (dlib's 68
            points, or the Face Mesh points of ``meshmap``; inferred from ``N`` when model is None).
        K: ``[V, 3, 3]`` or ``[3, 3]`` intrinsics.
        config: ``FitConfig``; model: a ``LandmarkModel`` (built from the shipped head when None).
        identity: ``[100]`` (or ``[Ki]``) fixed identity; estimated (shared) when None.
        init: a ``FitResult`` to warm-start pose and expression from (skips the rigid stage).
        weights: ``[N]`` or ``[V, N]`` extra per-landmark weights.
    """
    from .blas import one_blas_thread

    with one_blas_thread():
        return _fit_landmarks(*args, **kwargs)


def _fit_landmarks(
    landmarks: np.ndarray,  # [V, N, 2] pixels
    K: np.ndarray,  # [V, 3, 3] or [3, 3]
    config: FitConfig | None = None,
    model: LandmarkModel | None = None,
    *,
    identity: np.ndarray | None = None,  # [100] or [Ki]: fixed identity (not estimated) when given
    init: FitResult | None = None,  # warm start (pose + expression); skips the rigid stage
    weights: np.ndarray | None = None,  # [N] or [V, N] extra per-landmark weights
    silhouettes: list | None = None,  # V x silhouette.SilhouetteTarget or None: outline constraint for side views
) -> FitResult:
    cfg = config or FitConfig()
    obs = np.asarray(landmarks, dtype=np.float64)
    if obs.ndim == 2:
        obs = obs[None]
    if model is None and obs.ndim == 3 and obs.shape[1] != 68:
        model = LandmarkModel.from_head_model(num_identity=cfg.num_identity, layout="mediapipe")
    model = model or LandmarkModel.from_head_model(num_identity=cfg.num_identity)
    N = model.num_points
    if obs.ndim != 3 or obs.shape[1:] != (N, 2):
        raise ValueError(f"landmarks must have shape [V, {N}, 2] (layout {model.layout}), got {list(np.shape(landmarks))}")
    if not np.isfinite(obs).all():
        raise ValueError("landmarks must be finite")
    V = obs.shape[0]
    K = np.asarray(K, dtype=np.float64)
    K = np.broadcast_to(K, (V, 3, 3)).copy() if K.shape == (3, 3) else K
    if K.shape != (V, 3, 3):
        raise ValueError(f"K must have shape [3, 3] or [V={V}, 3, 3], got {list(K.shape)}")
    W = np.ones((V, N)) if weights is None else np.broadcast_to(np.asarray(weights, dtype=np.float64), (V, N)).copy()
    Ki = model.num_identity
    if identity is not None:
        identity = np.asarray(identity, dtype=np.float64)
        if identity.shape[0] < Ki:
            raise ValueError(f"identity must have at least {Ki} entries, got {identity.shape[0]}")
        beta = identity[:Ki].copy()
    else:
        beta = np.zeros(Ki)

    if init is not None:
        E = np.array(init.expressions, dtype=np.float64).reshape(V, 53)
        Rs = np.array(init.rotations, dtype=np.float64).reshape(V, 3, 3)
        ts = np.array(init.translations, dtype=np.float64).reshape(V, 3)
        if identity is None:
            beta = np.array(init.identity[:Ki], dtype=np.float64)
    else:
        E = np.zeros((V, 53))
        Rs = np.zeros((V, 3, 3))
        ts = np.zeros((V, 3))
        for v in range(V):
            sub = _Problem(model, obs[v : v + 1], K[v : v + 1], cfg, W[v : v + 1], False, False)
            best = None
            for yaw in cfg.yaw_guesses_deg:
                R0 = FRONTAL_R @ rodrigues(np.array([0.0, math.radians(yaw), 0.0]))
                t0 = _initial_translation(model, obs[v], K[v], R0)
                out = _lm(sub, beta, E[v : v + 1], R0[None], t0[None], cfg.rigid_iterations, cfg.tolerance)
                if best is None or out[4] < best[4]:
                    best = out
            Rs[v], ts[v] = best[2][0], best[3][0]
    W_user = W.copy()
    if cfg.occluded_weight < 1.0 and model.normals is not None:
        W = W * visibility_weights(model, Rs, ts, cfg.occluded_weight)

    prob = _Problem(model, obs, K, cfg, W, free_identity=identity is None, free_expression=True)
    table = _pose_table(model, cfg)

    def use_yaw_map(p=prob):
        _use_yaw_map(p, table, Rs, ts, W_user, cfg)

    if table is not None and init is not None:  # warm start (video): the map of the previous pose, one solve
        use_yaw_map()
        beta, E, Rs, ts, cost = _lm(prob, beta, E, Rs, ts, cfg.iterations, cfg.tolerance)
    else:
        beta, E, Rs, ts, cost = _lm(prob, beta, E, Rs, ts, cfg.iterations, cfg.tolerance)
        for _ in range(cfg.yaw_map_rounds if table is not None else 0):
            use_yaw_map()
            beta, E, Rs, ts, cost = _lm(prob, beta, E, Rs, ts, cfg.iterations, cfg.tolerance)
        targets = _regressed_yaw_targets(obs, Rs, cfg) if cfg.yaw_prior and model.layout == "mediapipe" and N == 468 else None
        if targets is not None and np.isfinite(targets).any():
            # re-pose only: identity and expressions stay (freeing them lets the shared identity move
            # the other photos and the expressions absorb the prior's pull on the landmarks)
            pose = _Problem(model, obs, K, cfg, W, free_identity=False, free_expression=False)
            pose.ms, pose.scale, pose.yaw_target = list(prob.ms), prob.scale, targets
            R0, t0, ms0 = Rs.copy(), ts.copy(), list(prob.ms)
            for _ in range(max(1, cfg.yaw_map_rounds if table is not None else 1)):
                if table is not None:
                    use_yaw_map(pose)
                beta, E, Rs, ts, cost = _lm(pose, beta, E, Rs, ts, cfg.iterations, cfg.tolerance)
            # with identity and expressions fixed the views are independent: one can be reverted alone
            for v in np.flatnonzero(np.isfinite(targets)):
                uv, _ = _project(pose.ms[v].points(beta, E[v]), Rs[v], ts[v], K[v])
                rms_v = float(np.sqrt(((uv - obs[v]) ** 2).sum(1).mean()))
                if rms_v > cfg.yaw_prior_max_rms * max(pose.diag[v], 1.0):
                    logger.info("photo %d: the yaw prior leaves landmark RMS %.1f px; keeping the landmark-only pose", v, rms_v)
                    Rs[v], ts[v], pose.ms[v], pose.yaw_target[v] = R0[v], t0[v], ms0[v], np.nan
            r = pose.residuals(beta, E, Rs, ts)
            cost = 0.5 * float(r @ r)
            prob = pose
    outline = np.full(V, np.nan)
    if silhouettes is not None and any(t is not None for t in silhouettes):
        from ..data.headmodel import HeadModel

        if len(silhouettes) != V:
            raise ValueError(f"got {len(silhouettes)} silhouette targets for {V} photos")
        head = HeadModel.load()
        for _ in range(cfg.silhouette_rounds):
            # side views only (landmarks pin frontal ones); re-decided each round as the yaw moves
            side = [t if t is not None and abs(_yaw_deg(Rs[v])) >= cfg.silhouette_min_yaw else None for v, t in enumerate(silhouettes)]
            if prob.set_silhouettes(head, side, beta, E, Rs, ts) == 0:
                break
            beta, E, Rs, ts, cost = _lm(prob, beta, E, Rs, ts, cfg.iterations, cfg.tolerance)
        for v in range(V):
            if prob.sil[v] is not None:
                sv = prob.sil[v]
                uv, _ = _project(prob._sil_points(v, beta, E[v]), Rs[v], ts[v], K[v])
                outline[v] = float(np.sqrt(np.mean(sv["target"].sample(uv, sv["clip"])[0] ** 2)))

    rms = np.zeros(V)
    for v in range(V):
        uv, _ = _project(prob.ms[v].points(beta, E[v]), Rs[v], ts[v], K[v])
        rms[v] = float(np.sqrt(((uv - obs[v]) ** 2).sum(1).mean()))
    full_id = np.zeros(model.num_total_identity)
    full_id[:Ki] = beta
    return FitResult(identity=full_id, expressions=E, rotations=Rs, translations=ts, K=K, rms_px=rms, cost=cost, outline_px=outline)


@dataclass
class KnownCameraFit:
    """The head of one person fitted to photos whose cameras are known (:func:`fit_known_cameras`).

    ``V`` photos, of which those with ``detected`` landmarks took part in the fit.
    """

    identity: np.ndarray  # [100] float64, zeros beyond num_identity (shared)
    expressions: np.ndarray  # [V, 53] float64 in [0, 1]; photos without landmarks: neutral, or what their outline moved
    head_to_world: np.ndarray  # [4, 4] rigid: x_world = R x_head + t (metres), one for all photos
    rms_px: np.ndarray  # [V] RMS landmark reprojection error through the given cameras (pixels); NaN = not detected
    detected: np.ndarray  # [V] bool: the photo's landmarks were found and fitted
    pose_spread_deg: np.ndarray  # [V] angle between each photo's own (photo-only) head pose and the shared one; NaN = not detected
    pose_spread_mm: np.ndarray  # [V] distance between each photo's own head origin and the shared one (mm); NaN = not detected
    cost: float = 0.0


def _world_pose(R: np.ndarray, t: np.ndarray, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Head -> camera ``(R, t)`` through a camera ``w2c [4, 4]`` -> head -> world."""
    C, c = w2c[:3, :3], w2c[:3, 3]
    return C.T @ R, C.T @ (t - c)


def _orthonormal(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def _shared_pose_reduction(nid: int, nv: int, Cs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(T, ecols)`` for ``_lm(reduce=...)``: unknowns ``[identity | world rotation (3), world
    translation (3) | expressions of each view]`` mapped to the per-view ``_Problem`` columns."""
    n = len(Cs)
    T = np.zeros((nid + n * nv, nid + 6 + n * 53))
    T[:nid, :nid] = np.eye(nid)
    for j in range(n):
        c0 = nid + j * nv
        T[c0 : c0 + 3, nid : nid + 3] = Cs[j]  # world rotation increment seen from camera j
        T[c0 + 3 : c0 + 6, nid + 3 : nid + 6] = Cs[j]  # world translation increment
        T[c0 + 6 : c0 + 6 + 53, nid + 6 + j * 53 : nid + 6 + (j + 1) * 53] = np.eye(53)
    return T, nid + 6 + np.arange(n)[:, None] * 53 + np.arange(53)[None]


def fit_known_cameras(
    landmarks: list,
    K: np.ndarray,
    w2c: np.ndarray,
    config: FitConfig | None = None,
    model: LandmarkModel | None = None,
    masks: list | None = None,
) -> KnownCameraFit:
    """Fit one head to photos with **known** cameras: identity shared, an expression per photo, and
    one rigid head -> world transform for all photos (the cameras' world need not be head-centric).

    Stages: the photo-only fit (:func:`fit_landmarks` on the photos with landmarks, each photo its
    own head pose through its ``K``) gives every photo a head -> world pose through its ``w2c``;
    their chordal mean (rotation) and mean (translation) start a joint Levenberg-Marquardt where
    the head pose is one unknown shared by all photos (per photo ``R_v = C_v R_hw``,
    ``t_v = C_v t_hw + c_v`` with ``w2c_v = [C_v | c_v]``), with the same residuals, priors,
    visibility weights and, for the Face Mesh layout, the same yaw-dependent map rounds. The yaw
    prior of the photo-only path is not used (the cameras fix the yaw); outlines are, when
    ``masks`` are given.

    Args:
        landmarks: ``V`` entries, each ``[N, 2]`` pixels in ``model``'s layout, or None for a photo
            without landmarks (a profile the detector misses): neutral expression unless its outline
            joins the fit.
        masks: optional ``V`` entries ``[H_v, W_v]`` alpha in [0, 1] or None: the outline stage
            (``_known_camera_outlines``) adds the face band's outline of every photo turned by at
            least ``config.silhouette_min_yaw`` degrees (``silhouette.py``), profiles without
            landmarks included; ``config.silhouette_rounds`` rounds.
        K: ``[V, 3, 3]`` intrinsics of the photos (pixels); w2c: ``[V, 4, 4]`` world -> camera
            (OpenCV, metres; ``docs/conventions.md``).
        config: ``FitConfig``; model: a ``LandmarkModel`` (Face Mesh layout when ``N != 68``).
    Returns:
        ``KnownCameraFit``; ``pose_spread_*`` says how far the photos' own poses disagreed.
    Raises:
        ValueError: when no photo has landmarks, or on mismatched shapes.
    """
    from .blas import one_blas_thread

    cfg = config or FitConfig()
    V = len(landmarks)
    K = np.asarray(K, dtype=np.float64).reshape(-1, 3, 3)
    w2c = np.asarray(w2c, dtype=np.float64).reshape(-1, 4, 4)
    if K.shape[0] != V or w2c.shape[0] != V:
        raise ValueError(f"fit_known_cameras: got {V} landmark sets, {K.shape[0]} intrinsics and {w2c.shape[0]} cameras")
    idx = [v for v, lm in enumerate(landmarks) if lm is not None]
    if not idx:
        raise ValueError(f"fit_known_cameras: none of the {V} photos has landmarks")
    obs = np.stack([np.asarray(landmarks[v], dtype=np.float64) for v in idx])
    if model is None:
        model = LandmarkModel.from_head_model(num_identity=cfg.num_identity, layout="dlib68" if obs.shape[1] == 68 else "mediapipe")
    own = fit_landmarks(obs, K[idx], cfg, model)
    n = len(idx)
    poses = [_world_pose(own.rotations[j], own.translations[j], w2c[v]) for j, v in enumerate(idx)]
    R_hw = _orthonormal(sum(p[0] for p in poses))
    t_hw = np.mean([p[1] for p in poses], axis=0)
    Cs, cs = w2c[idx, :3, :3], w2c[idx, :3, 3]
    Rs = np.einsum("vij,jk->vik", Cs, R_hw)
    ts = np.einsum("vij,j->vi", Cs, t_hw) + cs
    beta, E = own.identity[: model.num_identity].copy(), own.expressions.copy()

    with one_blas_thread():
        W = np.ones((n, model.num_points))
        if cfg.occluded_weight < 1.0 and model.normals is not None:
            W = visibility_weights(model, Rs, ts, cfg.occluded_weight)
        prob = _Problem(model, obs, K[idx], cfg, W, free_identity=True, free_expression=True)
        T, ecols = _shared_pose_reduction(prob.nid, prob.nv, Cs)
        table = _pose_table(model, cfg)
        beta, E, Rs, ts, cost = _lm(prob, beta, E, Rs, ts, cfg.iterations, cfg.tolerance, reduce=(T, ecols))
        for _ in range(cfg.yaw_map_rounds if table is not None else 0):
            _use_yaw_map(prob, table, Rs, ts, np.ones((n, model.num_points)), cfg)
            beta, E, Rs, ts, cost = _lm(prob, beta, E, Rs, ts, cfg.iterations, cfg.tolerance, reduce=(T, ecols))
        R_hw, t_hw = _world_pose(Rs[0], ts[0], w2c[idx[0]])
        E_all = np.zeros((V, 53))
        E_all[idx] = E
        if masks is not None and cfg.silhouette_rounds > 0:
            beta, E_all, R_hw, t_hw, cost = _known_camera_outlines(
                model, prob, obs, idx, K, w2c, masks, beta, E_all, _orthonormal(R_hw), t_hw, cfg, cost
            )
    R_hw = _orthonormal(R_hw)
    H = np.eye(4)
    H[:3, :3], H[:3, 3] = R_hw, t_hw
    expressions = np.zeros((V, 53))
    rms = np.full(V, np.nan)
    spread_deg, spread_mm = np.full(V, np.nan), np.full(V, np.nan)
    expressions[:] = E_all
    for j, v in enumerate(idx):
        R_v, t_v = Cs[j] @ R_hw, Cs[j] @ t_hw + cs[j]
        uv, _ = _project(prob.ms[j].points(beta, E[j]), R_v, t_v, K[v])
        rms[v] = float(np.sqrt(((uv - obs[j]) ** 2).sum(1).mean()))
        cos = (np.trace(poses[j][0].T @ R_hw) - 1.0) / 2.0
        spread_deg[v] = math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0))))
        spread_mm[v] = 1000.0 * float(np.linalg.norm(poses[j][1] - t_hw))
    full_id = np.zeros(model.num_total_identity)
    full_id[: model.num_identity] = beta
    return KnownCameraFit(full_id, expressions, H, rms, np.array([lm is not None for lm in landmarks]), spread_deg, spread_mm, cost)


def _known_camera_outlines(model, prob, obs, idx, K, w2c, masks, beta, E_all, R_hw, t_hw, cfg, cost):
    """Outline stage of :func:`fit_known_cameras`: every photo with a mask whose head is turned by
    at least ``silhouette_min_yaw`` (profiles the detector misses included, with zero landmark
    weight) adds the face band's outline residual (``silhouette.py``); all outline points of a
    photo weigh ``silhouette_weight`` x the mean landmark weight of a photo with landmarks."""
    from ..data.headmodel import HeadModel
    from .silhouette import SilhouetteTarget

    V = len(masks)
    Cw, cw = w2c[:, :3, :3], w2c[:, :3, 3]
    views = [v for v in range(V) if v in idx or masks[v] is not None]
    Rs = np.einsum("vij,jk->vik", Cw[views], R_hw)
    ts = np.einsum("vij,j->vi", Cw[views], t_hw) + cw[views]
    full_obs, W = [], []
    for j, v in enumerate(views):
        if v in idx:
            full_obs.append(obs[idx.index(v)])
            W.append(prob.scale[idx.index(v)] ** 2 * (cfg.landmark_sigma * max(prob.diag[idx.index(v)], 1.0)) ** 2 / np.maximum(prob._w0, 1e-12))
        else:  # no landmarks: the model's own projection as a placeholder, weight 0
            full_obs.append(_project(model.points(beta, E_all[v]), Rs[j], ts[j], K[v])[0])
            W.append(np.zeros(model.num_points))
    full_obs = np.stack(full_obs)
    p2 = _Problem(model, full_obs, K[views], cfg, np.stack(W), free_identity=True, free_expression=True)
    for j, v in enumerate(views):
        if v in idx:
            p2.ms[j] = prob.ms[idx.index(v)]
    T, ecols = _shared_pose_reduction(p2.nid, p2.nv, Cw[views])
    ref = float(np.mean([(prob.scale[k] ** 2).sum() * 2.0 for k in range(len(idx))]))
    targets = []
    for j, v in enumerate(views):
        tg = None
        if masks[v] is not None:
            face = float(np.linalg.norm(full_obs[j].max(0) - full_obs[j].min(0)))
            try:
                tg = SilhouetteTarget.from_mask(np.asarray(masks[v], dtype=np.float32), face)
            except ValueError:
                tg = None
        targets.append(tg)
    head = HeadModel.load()
    E = E_all[views]
    for _ in range(cfg.silhouette_rounds):
        side = [t if t is not None and abs(_yaw_deg(Rs[j])) >= cfg.silhouette_min_yaw else None for j, t in enumerate(targets)]
        if p2.set_silhouettes(head, side, beta, E, Rs, ts) == 0:
            break
        for j, v in enumerate(views):
            if v not in idx and p2.sil[j] is not None:
                p2.sil[j]["sqrt_w"] = math.sqrt(cfg.silhouette_weight * ref / len(p2.sil[j]["mean"]))
        beta, E, Rs, ts, cost = _lm(p2, beta, E, Rs, ts, cfg.iterations, cfg.tolerance, reduce=(T, ecols))
    E_all = E_all.copy()
    E_all[views] = E
    R_hw, t_hw = _world_pose(Rs[0], ts[0], w2c[views[0]])
    return beta, E_all, R_hw, t_hw, cost
