"""Training-side augmentation of the INPUT cameras: pose noise shaped like the tracker's errors.

The paper (appendix, "Analysis on Camera Degradation") finds its model stable only for small camera
noise, since it was trained with calibrated cameras, and names camera-noise augmentation during
training as the remedy. At inference on photos, the cameras come from ``fastgha track``: a fitted
head pose ``w2c = [R | t]`` per photo (the head's pose in the camera, ``docs/tracking.md``). Its
errors are

* a rotation of the head about its own centre, mostly yaw, growing with how far the head is
  turned (through the detector on synthetic renders, median rotation error 1.6 / 4.5 / 3.1 / 5.8 /
  11.9 degrees at yaw 0 / 30 / 45 / 60 / 75; on the real photo sets yaw errors of ~10 degrees
  against annotations that are themselves +-10-15 degrees);
* a translation that is almost all depth (head size and distance are ambiguous from landmarks:
  median 4.4 % of the distance on the fitter with exact landmarks, but nearly all of it a scale
  shared by the photos of a set, which cancels when the target cameras are tracked too; within a
  set the standard deviation is ~0.5 %), and a few millimetres sideways (median 2.5 mm);

while the head centre stays where the landmarks put it in the image. :class:`InputCameraNoise`
draws exactly that per input view:

* ``dR``: the exponential map of a rotation vector ``(pitch, yaw, roll)`` about the head's own
  ``x, y, z`` axes (``docs/conventions.md``: +x subject's left, +y up, +z out of the face), each
  component normal with standard deviation ``*_std_deg * g``, where ``g = 1 + yaw_gain *
  min(|view yaw|, 90) / 60`` and the view yaw is ``atan2(c_x, c_z)`` of the camera centre ``c``;
* ``R' = R dR`` (the head turned in its own frame about its centre, so its centre's projection is
  unchanged), ``t' = (1 + eps) t + (dx, dy, 0)`` with ``eps ~ N(0, depth_std)`` (the camera moves
  along its line of sight to the head centre) and ``dx, dy ~ N(0, lateral_std_mm)`` in the camera's
  x / y axes. ``K`` is left alone.

Only the cameras given to the encoder change; the supervision cameras (``target_w2c``, which for
the first ``V`` targets are the true input cameras) stay exact, so the network is taught to place
its Gaussians where the truth is despite the wrong cameras it is told.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

__all__ = [
    "InputCameraNoise",
    "perturb_w2c",
    "view_yaw_deg",
    "rotation_vector",
    "InputCameraNoiseDataset",
    "InputMatting",
    "matte_input_view",
    "InputMattingDataset",
]


def _from_dict(cls, data: dict[str, Any] | None, key: str):
    """``cls(**data)`` for the train config's ``key`` section; unknown fields raise ``ValueError``."""
    data = dict(data or {})
    names = {f.name for f in fields(cls)}
    bad = sorted(set(data) - names)
    if bad:
        raise ValueError(f"train config: unknown {key} field(s) {bad}; expected some of {sorted(names)}")
    from ..config import check_field_types

    check_field_types(cls, data, f"train config: {key}")
    return cls(**data)


@dataclass
class InputCameraNoise:
    """Pose noise on the input cameras, shaped like tracking errors (module docstring).

    ``enabled`` is False by default and in every preset; the magnitudes are the tracking-shaped
    defaults used when it is turned on (``"input_camera_noise": {"enabled": true}`` in a training
    config, or ``fastgha train --input-camera-noise``). Angles in degrees, lengths in millimetres,
    ``depth_std`` as a fraction of the camera's distance to the head centre.
    """

    enabled: bool = False
    yaw_std_deg: float = 2.5  # about the head's up axis, at a frontal view
    pitch_std_deg: float = 2.0  # about the head's left axis, at a frontal view
    roll_std_deg: float = 1.0  # about the head's forward axis, at a frontal view
    yaw_gain: float = 2.0  # rotation stds x (1 + yaw_gain * min(|view yaw|, 90 deg) / 60 deg)
    lateral_std_mm: float = 3.0  # sideways / up-down shift per camera axis
    depth_std: float = 0.01  # relative error of the distance (per view; a scale shared by all views is not drawn)

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name == "enabled":
                continue
            v = float(getattr(self, f.name))
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"input_camera_noise.{f.name} must be a finite number >= 0, got {getattr(self, f.name)!r}")
        if self.depth_std >= 0.5:
            raise ValueError(f"input_camera_noise.depth_std must be < 0.5 (a fraction of the distance), got {self.depth_std}")

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> "InputCameraNoise":
        return _from_dict(cls, data, "input_camera_noise")


def view_yaw_deg(w2c: Tensor) -> Tensor:
    """Yaw of each camera's centre around the head, degrees: ``atan2(c_x, c_z)``, 0 = frontal.

    ``w2c [..., 4, 4]`` (head-centric world, OpenCV camera) -> ``[...]``.
    """
    R, t = w2c[..., :3, :3], w2c[..., :3, 3]
    c = -(R.transpose(-1, -2) @ t[..., None])[..., 0]
    return torch.rad2deg(torch.atan2(c[..., 0], c[..., 2]))


def _so3_exp(v: Tensor) -> Tensor:  # [..., 3] rotation vectors (radians) -> [..., 3, 3]
    theta = v.norm(dim=-1, keepdim=True)[..., None]  # [..., 1, 1]
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    Kx = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*v.shape[:-1], 3, 3)
    small = theta < 1e-8
    ts = torch.where(small, torch.ones_like(theta), theta)
    a = torch.where(small, torch.ones_like(theta), torch.sin(ts) / ts)
    b = torch.where(small, torch.full_like(theta, 0.5), (1 - torch.cos(ts)) / ts**2)
    eye = torch.eye(3, dtype=v.dtype).expand_as(Kx)
    return eye + a * Kx + b * (Kx @ Kx)


def rotation_vector(R: Tensor) -> Tensor:
    """The rotation vector (axis x angle, radians) of rotations ``R [..., 3, 3]`` with angle < pi -> ``[..., 3]``."""
    tr = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    theta = torch.arccos(((tr - 1) / 2).clamp(-1.0, 1.0))
    w = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], dim=-1)
    s = torch.sin(theta)
    scale = torch.where(theta < 1e-8, torch.full_like(theta, 0.5), theta / (2 * s.clamp_min(1e-12)))
    return w * scale[..., None]


def perturb_w2c(w2c: Tensor, noise: InputCameraNoise, gen: torch.Generator) -> Tensor:
    """Input cameras with tracking-shaped pose noise (module docstring for the model).

    Args:
        w2c: ``[V, 4, 4]`` world-to-camera transforms (head-centric world, OpenCV camera).
        noise: the magnitudes (``noise.enabled`` is not consulted: callers decide).
        gen: a CPU ``torch.Generator``; the draw is a pure function of its state.

    Returns:
        ``[V, 4, 4]`` perturbed transforms, same dtype; the input is not modified.
    """
    if w2c.ndim != 3 or tuple(w2c.shape[-2:]) != (4, 4):
        raise ValueError(f"perturb_w2c expects w2c of shape [V, 4, 4], got {list(w2c.shape)}")
    V = w2c.shape[0]
    w = w2c.detach().to(torch.float64).cpu()
    z_rot = torch.randn((V, 3), generator=gen, dtype=torch.float64)
    z_lat = torch.randn((V, 2), generator=gen, dtype=torch.float64)
    z_dep = torch.randn((V,), generator=gen, dtype=torch.float64)
    gain = 1.0 + noise.yaw_gain * view_yaw_deg(w).abs().clamp(max=90.0) / 60.0  # [V]
    stds = torch.tensor([noise.pitch_std_deg, noise.yaw_std_deg, noise.roll_std_deg], dtype=torch.float64)  # head x, y, z
    rotvec = torch.deg2rad(z_rot * stds * gain[:, None])  # [V, 3]
    R, t = w[:, :3, :3], w[:, :3, 3]
    R2 = R @ _so3_exp(rotvec)
    t2 = t * (1.0 + noise.depth_std * z_dep)[:, None]
    t2 = t2 + torch.cat([z_lat * (noise.lateral_std_mm * 1e-3), torch.zeros(V, 1, dtype=torch.float64)], dim=-1)
    out = w.clone()
    out[:, :3, :3] = R2
    out[:, :3, 3] = t2
    return out.to(dtype=w2c.dtype, device=w2c.device)


class InputCameraNoiseDataset(Dataset):
    """Wraps a map-style dataset of ``TrainingSample`` and perturbs each sample's ``input_w2c``.

    Sample ``i``'s noise is drawn from a generator seeded by ``(seed, i)`` only, so the stream is
    deterministic whatever the number of DataLoader workers and ``--resume`` replays it exactly.
    Every other field (images, ``input_K``, all supervision cameras) is passed through unchanged.
    """

    def __init__(self, base, noise: InputCameraNoise, seed: int = 0):
        self.base = base
        self.noise = noise
        self.seed = int(seed)

    def __len__(self) -> int:
        return len(self.base)

    def generator(self, index: int) -> torch.Generator:
        return torch.Generator().manual_seed(int(np.random.default_rng([self.seed, 5, int(index)]).integers(2**62)))

    def __getitem__(self, index: int):
        sample = self.base[index]
        return replace(sample, input_w2c=perturb_w2c(sample.input_w2c, self.noise, self.generator(index)))


# ---------------------------------------------------------------------------- our own matting on the inputs
@dataclass
class InputMatting:
    """Input images matted by the project's own matting instead of the renderer's exact alpha.

    At inference on photos the inputs are cut out by ``tracking/matting.py`` (a trimap from the
    *fitted* head, MediaPipe selfie segmentation deciding the rest), so hair tips get cut, a strip of
    wall can stay and the edge is a 1 px feather. With ``enabled``, each synthetic input view is put
    on a random wall with the subject's own soft shadow (``tracking.matting_eval.composite_on_wall``)
    and matted by ``matte_from_head`` from a head that misses like a fit: the true head at the view's
    expression, turned about its centre by ``N(0, head_yaw_std_deg)`` of yaw and scaled by
    ``1 + |N(0, head_scale_std)|`` (fits make the skull too large rather than too small,
    ``docs/tracking-log.md``, "Why the face only"); its 68 landmarks give the face region and the mouth row. Supervision images
    and masks stay exact. Only for ``--data synthetic`` (the head mesh is needed). Off by default.
    """

    enabled: bool = False
    method: str = "auto"  # MattingConfig.method: "auto" (segmentation with MediaPipe, else mixture) | ...
    head_yaw_std_deg: float = 5.0
    head_scale_std: float = 0.05

    def __post_init__(self) -> None:
        if self.method not in ("auto", "mixture", "grabcut", "segmentation"):
            raise ValueError(f"input_matting.method must be 'auto', 'mixture', 'grabcut' or 'segmentation', got {self.method!r}")
        for name in ("head_yaw_std_deg", "head_scale_std"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"input_matting.{name} must be a finite number >= 0, got {getattr(self, name)!r}")

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> "InputMatting":
        return _from_dict(cls, data, "input_matting")


def matte_input_view(subject, expression: np.ndarray, view, w2c: Tensor, K: Tensor, cfg: InputMatting, rng: np.random.Generator) -> tuple[Tensor, Tensor]:
    """One synthetic view on a wall, matted by our matting from a fit-like head.

    Args:
        subject: the view's ``data.synthetic.SyntheticSubject``.
        expression: ``[53]`` ict53 code of the view's timestep.
        view: the rendered ``View`` (image over ``BACKGROUND_RGB`` ``[3, S, S]``, mask ``[1, S, S]``).
        w2c: ``[4, 4]``, K: ``[3, 3]`` the view's camera (pixels of the ``S x S`` image).
        rng: the draw (wall, shadow, head error).

    Returns:
        ``(image [3, S, S] float32 over BACKGROUND_RGB, matte [1, S, S] float32 in [0, 1])``.
    """
    from ..constants import BACKGROUND_RGB
    from ..tracking.fit import rodrigues
    from ..tracking.matting import MattingConfig, head_silhouette, matte_from_head
    from ..tracking.matting_eval import composite_on_wall

    S = int(view.image.shape[-1])
    if view.image.shape[-2] != S:
        raise ValueError(f"matte_input_view expects a square view, got {list(view.image.shape[-2:])}")
    verts = subject.vertices(np.asarray(expression, np.float32)).astype(np.float64)
    centre = verts.mean(0)
    err = rodrigues(np.radians([0.0, float(rng.normal(0.0, cfg.head_yaw_std_deg)), 0.0]))
    scale = 1.0 + abs(float(rng.normal(0.0, cfg.head_scale_std)))
    wrong = (verts - centre) @ err.T * scale + centre
    photo, _, _ = composite_on_wall(view, rng)
    w = w2c.detach().double().cpu().numpy()
    R, t, Kn = w[:3, :3], w[:3, 3], K.detach().double().cpu().numpy()
    sil = head_silhouette(wrong, subject.model.visible_faces(eyelashes=False), R, t, Kn, S)
    lm = (subject.model.landmarks(wrong) @ R.T + t) @ Kn.T
    lm = lm[:, :2] / lm[:, 2:]
    m = matte_from_head(photo, sil, Kn[0, 0] / t[2], float(lm[57, 1]), None, MattingConfig(method=cfg.method), face_points=lm)
    m_t = torch.from_numpy(np.ascontiguousarray(m, dtype=np.float32))[None]  # [1, S, S]
    img = torch.from_numpy(photo.astype(np.float32) / 255.0).permute(2, 0, 1)
    bg = torch.tensor(BACKGROUND_RGB, dtype=torch.float32)[:, None, None]
    return (img * m_t + bg * (1 - m_t)).clamp(0, 1), m_t


class InputMattingDataset(Dataset):
    """Wraps a ``SyntheticTrainingDataset``: each sample's input images are re-matted by
    :func:`matte_input_view` (draw seeded by ``(seed, index)``); every other field is unchanged."""

    def __init__(self, base, matting: InputMatting, seed: int = 0):
        if not (hasattr(base, "plan") and hasattr(base, "source") and hasattr(base, "subject_of")):
            raise ValueError(f"input matting needs the synthetic training data (--data synthetic), got {type(base).__name__}")
        self.base = base
        self.matting = matting
        self.seed = int(seed)

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, index: int):
        sample = self.base[index]
        src, plan = self.base.plan(index)
        subject = src.synthetic_subject
        rng = np.random.default_rng([self.seed, 6, int(index)])
        images = []
        for i, (t, c) in enumerate(zip(plan.input_timesteps, plan.input_cameras)):
            img, _ = matte_input_view(subject, src.expressions[t], src.view(t, c), sample.input_w2c[i], sample.input_K[i], self.matting, rng)
            images.append(img)
        return replace(sample, input_images=torch.stack(images).to(sample.input_images.dtype))
