"""Synthetic multi-view head captures from ICT-FaceKit (the data we can ship and test on).

A subject is a seed. ``make_sequence(seed, timesteps, num_cameras, resolution, sequence)``
returns a ``SyntheticSequence`` (a ``SequenceSource``): everything is drawn from
``numpy.random.SeedSequence`` streams keyed by ``(seed, purpose[, sequence])``, so a sequence is
a pure function of its arguments and renders lazily and identically in any process.

Per subject (seed): identity ``[100] ~ N(0, IDENTITY_STD^2)``; procedural appearance and baked
lighting (``appearance.py``); a camera rig of ``num_cameras`` cameras on the frontal hemisphere
(yaw in [-90, 90] degrees, pitch in [-35, 35], ~1 m from the head centre, ``FOV_DEG`` vertical
field of view) with small per-subject jitter. Per sequence: an ``ict53`` expression trajectory
(``expression_trajectory``): sparse, smooth gestures (blinks, winks, jaw open, smiles, brows,
frowns, asymmetric shapes, gaze) over a near-neutral baseline.

Ground truth comes from the CPU mesh rasterizer (``meshraster.py``), never from the Gaussian
renderer: RGB composited over ``BACKGROUND_RGB``, the alpha mask and the true camera z. The
"VGGT depth prior" of the geometry loss is this true depth; ``degrade_depth`` imitates a
network's error (noise, low-pass, scale error, holes).

Seed ranges: ``TRAIN_SEEDS = range(0, 1_000_000)`` for training, ``HELDOUT_SEEDS =
range(1_000_000, 1_010_000)`` for evaluation, the shipped samples and tests of generalisation.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from scipy.ndimage import gaussian_filter

from ..cameras import Cameras
from ..constants import BACKGROUND_RGB
from .appearance import AppearanceParams, SubjectAlbedo, hair_shell_faces, head_regions, shade, subject_albedo
from .headmodel import HeadModel, vertex_normals
from .meshraster import render_mesh
from .sample import View

__all__ = [
    "TRAIN_SEEDS",
    "HELDOUT_SEEDS",
    "IDENTITY_STD",
    "FOV_DEG",
    "CAMERA_DISTANCE",
    "SyntheticSubject",
    "SyntheticSequence",
    "make_sequence",
    "render_views",
    "expression_trajectory",
    "camera_rig",
    "degrade_depth",
    "subject_name",
    "GESTURES",
]

TRAIN_SEEDS = range(0, 1_000_000)
HELDOUT_SEEDS = range(1_000_000, 1_010_000)
IDENTITY_STD = 0.8
FOV_DEG = 18.0  # vertical field of view of the rig; the head (with hair) fills ~80% of the frame
CAMERA_DISTANCE = 1.0  # metres from the head centre
SUPERSAMPLE = 2  # 2x2 samples per pixel
_FACE_VERTICES = 9409  # ICT-FaceKit face vertex ids 0-9408

# stream ids for SeedSequence([seed, purpose, ...])
_S_IDENTITY, _S_APPEARANCE, _S_CAMERAS, _S_EXPRESSION = 1, 2, 3, 4


def subject_name(seed: int) -> str:
    return f"synth_{int(seed):07d}"


def _rng(*key: int) -> np.random.Generator:
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(k) for k in key])))


# ---------------------------------------------------------------------------- expressions
# Gestures: named combinations of ict53 blendshapes (weights at full strength).
GESTURES: dict[str, dict[str, float]] = {
    "jaw_open": {"jawOpen": 0.9, "mouthLowerDown_L": 0.3, "mouthLowerDown_R": 0.3},
    "talk": {"jawOpen": 0.35, "mouthFunnel": 0.15, "mouthLowerDown_L": 0.2, "mouthLowerDown_R": 0.2},
    "smile": {"mouthSmile_L": 1.0, "mouthSmile_R": 1.0, "cheekSquint_L": 0.5, "cheekSquint_R": 0.5, "eyeSquint_L": 0.3, "eyeSquint_R": 0.3},
    "grin": {"mouthSmile_L": 1.0, "mouthSmile_R": 1.0, "jawOpen": 0.3, "mouthUpperUp_L": 0.4, "mouthUpperUp_R": 0.4, "mouthStretch_L": 0.3, "mouthStretch_R": 0.3, "cheekSquint_L": 0.5, "cheekSquint_R": 0.5},
    "half_smile_L": {"mouthSmile_L": 1.0, "cheekSquint_L": 0.4, "mouthDimple_L": 0.4},
    "half_smile_R": {"mouthSmile_R": 1.0, "cheekSquint_R": 0.4, "mouthDimple_R": 0.4},
    "surprise": {"browInnerUp_L": 1.0, "browInnerUp_R": 1.0, "browOuterUp_L": 1.0, "browOuterUp_R": 1.0, "eyeWide_L": 0.8, "eyeWide_R": 0.8, "jawOpen": 0.5},
    "brows_up": {"browInnerUp_L": 0.9, "browInnerUp_R": 0.9, "browOuterUp_L": 0.8, "browOuterUp_R": 0.8},
    "brow_raise_L": {"browOuterUp_L": 1.0, "browInnerUp_L": 0.5},
    "brow_raise_R": {"browOuterUp_R": 1.0, "browInnerUp_R": 0.5},
    "frown": {"browDown_L": 1.0, "browDown_R": 1.0, "mouthFrown_L": 0.7, "mouthFrown_R": 0.7, "eyeSquint_L": 0.3, "eyeSquint_R": 0.3},
    "anger": {"browDown_L": 1.0, "browDown_R": 1.0, "noseSneer_L": 0.6, "noseSneer_R": 0.6, "mouthPress_L": 0.5, "mouthPress_R": 0.5, "eyeSquint_L": 0.4, "eyeSquint_R": 0.4},
    "disgust": {"noseSneer_L": 0.8, "noseSneer_R": 0.8, "mouthUpperUp_L": 0.6, "mouthUpperUp_R": 0.6, "browDown_L": 0.4, "browDown_R": 0.4},
    "sneer_L": {"noseSneer_L": 1.0, "mouthUpperUp_L": 0.6},
    "pucker": {"mouthPucker": 1.0},
    "funnel": {"mouthFunnel": 0.9, "jawOpen": 0.2},
    "cheek_puff": {"cheekPuff_L": 1.0, "cheekPuff_R": 1.0, "mouthClose": 0.2},
    "mouth_left": {"mouthLeft": 1.0},
    "mouth_right": {"mouthRight": 1.0},
    "jaw_left": {"jawLeft": 0.8},
    "jaw_right": {"jawRight": 0.8},
    "stretch": {"mouthStretch_L": 0.8, "mouthStretch_R": 0.8, "jawOpen": 0.2},
    "press": {"mouthRollLower": 0.7, "mouthRollUpper": 0.6, "mouthPress_L": 0.5, "mouthPress_R": 0.5},
    "shrug": {"mouthShrugLower": 0.8, "mouthShrugUpper": 0.4, "mouthFrown_L": 0.3, "mouthFrown_R": 0.3},
    "squint": {"eyeSquint_L": 0.9, "eyeSquint_R": 0.9, "cheekSquint_L": 0.4, "cheekSquint_R": 0.4},
    "look_left": {"eyeLookOut_L": 0.9, "eyeLookIn_R": 0.9},  # towards the subject's left (+x)
    "look_right": {"eyeLookIn_L": 0.9, "eyeLookOut_R": 0.9},
    "look_up": {"eyeLookUp_L": 0.8, "eyeLookUp_R": 0.8},
    "look_down": {"eyeLookDown_L": 0.8, "eyeLookDown_R": 0.8},
}
_BLINK = {"eyeBlink_L": 1.0, "eyeBlink_R": 1.0}
_WINK = ({"eyeBlink_L": 1.0, "cheekSquint_L": 0.3}, {"eyeBlink_R": 1.0, "cheekSquint_R": 0.3})


def _envelope(num: int, start: int, duration: int) -> np.ndarray:
    """Smooth bump ``[num]``: 0 outside [start, start + duration), rising to 1 and back."""
    k = np.arange(num, dtype=np.float64)
    p = (k - start + 0.5) / max(duration, 1)
    inside = (p > 0) & (p < 1)
    ramp = min(0.35, 0.5)
    up = np.clip(p / ramp, 0, 1)
    down = np.clip((1 - p) / ramp, 0, 1)
    env = (up * up * (3 - 2 * up)) * (down * down * (3 - 2 * down))
    if duration <= 2:
        env = np.where(inside, 1.0, 0.0)
    return np.where(inside, env, 0.0)


def expression_trajectory(
    rng: np.random.Generator,
    timesteps: int,
    names: Sequence[str],
    activity: float = 0.35,
    strength: tuple[float, float] = (0.35, 1.0),
    blink_rate: float = 0.08,
) -> np.ndarray:
    """An ``ict53`` trajectory ``[T, 53]`` in [0, 1].

    Gestures from ``GESTURES`` arrive one after another (they may overlap a little), each with a
    smooth attack/hold/release of 3-12 frames and a random strength in ``strength``; the expected
    fraction of frames inside a gesture is ``activity``, so near-neutral frames dominate for the
    default 0.35. Blinks (and occasional winks) arrive at ``blink_rate`` per frame, 1-2 frames
    long. A small slowly varying baseline (|w| < ~0.05) keeps neutral frames from being exactly 0.
    """
    if timesteps < 1:
        raise ValueError(f"timesteps must be >= 1, got {timesteps}")
    if not 0.0 <= activity <= 1.0:
        raise ValueError(f"activity must be in [0, 1], got {activity}")
    index = {n: i for i, n in enumerate(names)}
    T, E = timesteps, len(names)
    out = np.zeros((T, E))
    gesture_names = sorted(GESTURES)

    def add(shape: dict[str, float], env: np.ndarray, amp: float) -> None:
        for name, w in shape.items():
            out[:, index[name]] += amp * w * env

    mean_dur = 7.0
    mean_gap = mean_dur * (1.0 - activity) / max(activity, 1e-3)
    t = -rng.uniform(0, mean_dur) if activity > 0 else T
    while activity > 0 and t < T:
        dur = int(rng.integers(3, 13))
        start = int(round(t))
        g = GESTURES[gesture_names[int(rng.integers(len(gesture_names)))]]
        add(g, _envelope(T, start, dur), float(rng.uniform(*strength)))
        if rng.uniform() < 0.3:  # a second gesture combined with the first (e.g. smile + brows)
            g2 = GESTURES[gesture_names[int(rng.integers(len(gesture_names)))]]
            add(g2, _envelope(T, start + int(rng.integers(0, 3)), dur), float(rng.uniform(*strength)) * 0.6)
        t += dur * rng.uniform(0.7, 1.0) + rng.exponential(mean_gap) if mean_gap > 0 else dur * 0.8
    for k in range(T):
        if rng.uniform() < blink_rate:
            shape = _BLINK if rng.uniform() < 0.85 else _WINK[int(rng.integers(2))]
            add(shape, _envelope(T, k, int(rng.integers(1, 3))), float(rng.uniform(0.7, 1.0)))
    base = gaussian_filter(rng.standard_normal((T + 16, E)), sigma=(4.0, 0.0), mode="wrap")[8 : 8 + T]
    base = np.clip(base * 0.08 * rng.uniform(0.2, 1.0, size=E), 0, None)
    out = np.clip(out + base, 0.0, 1.0)
    return out.astype(np.float32)


# ---------------------------------------------------------------------------- cameras
def camera_rig(
    rng: np.random.Generator,
    num_cameras: int,
    resolution: int,
    yaw_range: float = 90.0,
    pitch_range: float = 35.0,
    distance: float = CAMERA_DISTANCE,
    fov_deg: float = FOV_DEG,
    jitter: bool = True,
) -> Cameras:
    """``num_cameras`` cameras ``[C]`` spread over the frontal hemisphere, looking at the head.

    Yaw is stratified over [-yaw_range, yaw_range] and pitch follows a golden-ratio sequence over
    [-pitch_range, pitch_range] (uniform in sin(pitch)), so any prefix is well spread. With
    ``jitter``: +/-4 degrees yaw, +/-3 degrees pitch, +/-5% distance and a +/-1 cm look-at offset.
    """
    if num_cameras < 1:
        raise ValueError(f"num_cameras must be >= 1, got {num_cameras}")
    C = num_cameras
    order = np.argsort(((np.arange(C) * 0.6180339887498949) % 1.0), kind="stable")
    u = np.empty(C)
    u[order] = (np.arange(C) + 0.5) / C  # stratified yaw slots, visited in golden-ratio order
    v = (0.5 + np.arange(C) * 0.6180339887498949 + 0.25) % 1.0
    yaw = np.radians(-yaw_range + 2 * yaw_range * u)
    sp_ = math.sin(math.radians(pitch_range))
    pitch = np.arcsin(np.clip((2 * v - 1) * sp_, -1, 1))
    dist = np.full(C, distance)
    target = np.zeros((C, 3))
    if jitter:
        yaw = yaw + np.radians(rng.uniform(-4, 4, C))
        pitch = pitch + np.radians(rng.uniform(-3, 3, C))
        dist = dist * rng.uniform(0.95, 1.05, C)
        target = target + rng.uniform(-0.01, 0.01, (C, 3))
    eye = np.stack([np.cos(pitch) * np.sin(yaw), np.sin(pitch), np.cos(pitch) * np.cos(yaw)], axis=-1) * dist[:, None] + target
    return Cameras.look_at(
        torch.tensor(eye, dtype=torch.float32), torch.tensor(target, dtype=torch.float32), fov_deg=fov_deg, width=resolution, height=resolution
    )


# ---------------------------------------------------------------------------- depth prior
def degrade_depth(
    depth: np.ndarray | torch.Tensor,  # [..., H, W] camera z in metres, 0 = no surface
    rng: np.random.Generator,
    noise_std: float = 0.002,
    blur_sigma: float = 1.5,
    scale_error: float = 0.01,
    hole_fraction: float = 0.02,
    hole_size: int = 6,
):
    """Imitate a depth network's error: low-pass, global scale error, noise and holes.

    ``blur_sigma`` in pixels (blurred only inside the surface, normalised by the blurred mask so
    the silhouette does not bleed); ``scale_error`` = std of a global multiplicative factor;
    ``noise_std`` in metres; holes are ``hole_size``-pixel squares covering about
    ``hole_fraction`` of the image, set to 0 (= no value). Returns the same type as ``depth``.
    """
    is_torch = isinstance(depth, torch.Tensor)
    d = depth.detach().cpu().numpy() if is_torch else np.asarray(depth)
    d = d.astype(np.float32)
    H, W = d.shape[-2:]
    flat = d.reshape(-1, H, W)
    out = np.empty_like(flat)
    for i, img in enumerate(flat):
        valid = (img > 0).astype(np.float32)
        if blur_sigma > 0:
            num = gaussian_filter(img * valid, blur_sigma)
            den = gaussian_filter(valid, blur_sigma)
            img = np.where(valid > 0, num / np.maximum(den, 1e-6), 0.0)
        img = img * np.float32(1.0 + rng.normal(0, scale_error)) if scale_error > 0 else img
        if noise_std > 0:
            img = img + rng.normal(0, noise_std, img.shape).astype(np.float32) * valid
        if hole_fraction > 0:
            n_holes = int(round(hole_fraction * H * W / max(hole_size * hole_size, 1)))
            ys = rng.integers(0, max(H - hole_size, 1), n_holes)
            xs = rng.integers(0, max(W - hole_size, 1), n_holes)
            for y, x in zip(ys, xs):
                img[y : y + hole_size, x : x + hole_size] = 0.0
        out[i] = np.where(valid > 0, img, 0.0)
    out = out.reshape(d.shape).astype(np.float32)
    return torch.from_numpy(out) if is_torch else out


# ---------------------------------------------------------------------------- subject
@dataclass
class _Frame:
    """The shaded mesh of one timestep (world space)."""

    points: np.ndarray  # [Nv + Ns, 3] mesh vertices then hair-shell vertices
    colors: np.ndarray  # [Nv + Ns, 3] shaded sRGB
    faces: np.ndarray  # [F, 3] visible triangles then hair-shell triangles


class SyntheticSubject:
    """One synthetic person: identity, appearance, lighting and camera rig, all from ``seed``."""

    def __init__(self, seed: int, model: HeadModel | None = None):
        self.seed = int(seed)
        self.name = subject_name(seed)
        self.model = model or HeadModel.load()
        self.identity = (_rng(seed, _S_IDENTITY).standard_normal(self.model.num_identity) * IDENTITY_STD).astype(np.float32)  # [100]
        self.params = AppearanceParams.sample(_rng(seed, _S_APPEARANCE))
        self.albedo: SubjectAlbedo = subject_albedo(self.model, self.params)
        self.base = self.model.vertices(self.identity)  # [Nv, 3] neutral of this identity
        self.faces = self.model.visible_faces()
        self.shell_faces = hair_shell_faces(self.model, head_regions(self.model), self.albedo.hair_weight)
        self.shell_vertices = np.unique(self.shell_faces)  # [Ns] mesh vertex ids under hair
        remap = np.full(self.model.num_vertices, -1, dtype=np.int64)
        remap[self.shell_vertices] = np.arange(len(self.shell_vertices)) + self.model.num_vertices
        self.all_faces = np.concatenate([self.faces, remap[self.shell_faces]]).astype(np.int32)  # [F, 3]
        # exposure: bring the neutral frame's face to a fixed brightness
        self.exposure = 1.0
        neutral = self.frame(np.zeros(self.model.num_expression, np.float32))
        face_ids = np.flatnonzero(self.albedo.hair_weight[:_FACE_VERTICES] < 0.1)
        lum = float(np.percentile(neutral.colors[face_ids].mean(axis=1) ** 2.2, 90))
        ref = float(np.mean(self.params.skin) ** 2.2)  # a fully lit skin patch should stay near its albedo
        self.exposure = float(np.clip(1.1 * ref / max(lum, 1e-4), 0.6, 2.5))

    def vertices(self, expression: np.ndarray) -> np.ndarray:
        """Mesh vertices ``[Nv, 3]`` (world, metres) for an ``ict53`` expression ``[53]``."""
        from .meshraster import blend_basis

        return self.base + blend_basis(self.model.expression_basis, np.asarray(expression, np.float32))

    def frame(self, expression: np.ndarray) -> _Frame:
        v = self.vertices(expression)
        n = vertex_normals(v, self.faces)
        sv = self.shell_vertices
        shell = v[sv] + n[sv] * self.albedo.hair_thickness[sv, None]
        points = np.concatenate([v, shell]).astype(np.float32)
        alb = np.concatenate([self.albedo.skin, self.albedo.hair[sv]])
        normals = np.concatenate([n, n[sv]])
        spec = np.concatenate([self.albedo.specular, np.full(len(sv), 0.12, np.float32)])
        shin = np.concatenate([self.albedo.shininess, np.full(len(sv), 12.0, np.float32)])
        colors = shade(alb, normals, spec, shin, self.params, exposure=getattr(self, "exposure", 1.0)).astype(np.float32)
        return _Frame(points=points, colors=colors, faces=self.all_faces)

    def render(self, frame: _Frame, cameras: Cameras, supersample: int = SUPERSAMPLE) -> list[View]:
        """Render ``frame`` from every camera of ``cameras`` (batch ``[C]``) -> ``C`` views."""
        cams = cameras.flatten()
        views = []
        bg = np.asarray(BACKGROUND_RGB, dtype=np.float64)
        for i in range(len(cams)):
            w2c = cams.w2c[i].double().numpy()
            R, t = w2c[:3, :3], w2c[:3, 3]
            p = frame.points.astype(np.float64)
            pc = p[:, 0:1] * R[:, 0] + p[:, 1:2] * R[:, 1] + p[:, 2:3] * R[:, 2] + t  # [N, 3]
            r = render_mesh(pc, frame.faces, frame.colors, cams.K[i].double().numpy(), cams.width, cams.height, supersample, bg)
            views.append(
                View(
                    image=torch.from_numpy(np.ascontiguousarray(r.color.transpose(2, 0, 1))).clamp_(0, 1),
                    mask=torch.from_numpy(r.alpha)[None],
                    depth=torch.from_numpy(r.depth)[None],
                )
            )
        return views


# ---------------------------------------------------------------------------- sequence
class SyntheticSequence:
    """A ``SequenceSource`` of one synthetic subject (see module doc). Renders lazily."""

    expression_space = "ict53"

    def __init__(self, seed: int, timesteps: int = 32, num_cameras: int = 16, resolution: int = 256, sequence: int = 0,
                 activity: float = 0.35, strength: tuple[float, float] = (0.35, 1.0), cache_frames: int = 4):
        if timesteps < 1 or num_cameras < 1 or resolution < 8:
            raise ValueError(f"need timesteps >= 1, num_cameras >= 1, resolution >= 8; got {timesteps}, {num_cameras}, {resolution}")
        self.seed = int(seed)
        self.sequence_index = int(sequence)
        self.subject = subject_name(seed)
        self.sequence = f"seq{int(sequence):03d}"
        self.resolution = int(resolution)
        self._T = int(timesteps)
        self._C = int(num_cameras)
        self.activity, self.strength = activity, strength
        self._rig = camera_rig(_rng(seed, _S_CAMERAS), num_cameras, resolution)
        self._cache_size = cache_frames
        self._init_lazy()

    def _init_lazy(self) -> None:
        self._subject: SyntheticSubject | None = None
        self._expr: np.ndarray | None = None
        self._frames: collections.OrderedDict[int, _Frame] = collections.OrderedDict()

    def __getstate__(self):  # DataLoader workers rebuild the heavy state lazily
        state = self.__dict__.copy()
        state["_subject"], state["_frames"] = None, collections.OrderedDict()
        return state

    def __repr__(self) -> str:
        return f"SyntheticSequence({self.subject}/{self.sequence}, T={self._T}, C={self._C}, {self.resolution}px)"

    @property
    def num_timesteps(self) -> int:
        return self._T

    @property
    def num_cameras(self) -> int:
        return self._C

    @property
    def synthetic_subject(self) -> SyntheticSubject:
        if self._subject is None:
            self._subject = SyntheticSubject(self.seed)
        return self._subject

    @property
    def expressions(self) -> np.ndarray:
        """All ``ict53`` codes ``[T, 53]`` float32."""
        if self._expr is None:
            names = HeadModel.load().expression_names
            self._expr = expression_trajectory(
                _rng(self.seed, _S_EXPRESSION, self.sequence_index), self._T, names, self.activity, self.strength
            )
        return self._expr

    def _check_t(self, t: int) -> int:
        if not 0 <= int(t) < self._T:
            raise IndexError(f"timestep {t} out of range [0, {self._T})")
        return int(t)

    def cameras(self, t: int) -> Cameras:  # [C]
        self._check_t(t)
        return self._rig

    def expression(self, t: int) -> torch.Tensor:  # [53]
        return torch.from_numpy(self.expressions[self._check_t(t)].copy())

    def frame(self, t: int) -> _Frame:
        t = self._check_t(t)
        if t in self._frames:
            self._frames.move_to_end(t)
            return self._frames[t]
        f = self.synthetic_subject.frame(self.expressions[t])
        self._frames[t] = f
        while len(self._frames) > self._cache_size:
            self._frames.popitem(last=False)
        return f

    def view(self, t: int, c: int) -> View:
        if not 0 <= int(c) < self._C:
            raise IndexError(f"camera {c} out of range [0, {self._C})")
        return self.synthetic_subject.render(self.frame(t), self._rig[int(c) : int(c) + 1])[0]

    def views(self, t: int) -> list[View]:
        """All ``C`` views of timestep ``t``."""
        return self.synthetic_subject.render(self.frame(t), self._rig)

    def landmarks(self, t: int) -> np.ndarray:
        """The 68 landmarks ``[68, 3]`` (world, metres) at timestep ``t``."""
        v = self.frame(t).points[: HeadModel.load().num_vertices]
        return v[HeadModel.load().landmarks68]


def make_sequence(seed: int, timesteps: int = 32, num_cameras: int = 16, resolution: int = 256, sequence: int = 0, **kwargs) -> SyntheticSequence:
    """The synthetic ``SequenceSource`` of subject ``seed`` (see module doc). Extra keyword
    arguments (``activity``, ``strength``) shape the expression trajectory."""
    return SyntheticSequence(seed, timesteps, num_cameras, resolution, sequence, **kwargs)


def render_views(seq: SyntheticSequence, t: int, cams: Cameras, supersample: int = SUPERSAMPLE) -> list[View]:
    """Ground truth of ``seq`` at timestep ``t`` from arbitrary cameras ``cams`` (batch ``[C]``)."""
    return seq.synthetic_subject.render(seq.frame(t), cams, supersample)
