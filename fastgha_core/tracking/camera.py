"""Fitted head pose -> head-centric OpenCV camera (our convention, docs/conventions.md).

The fitter gives the head's pose in the camera: ``x_cam = R x_head + t`` with ``x_head`` in the
canonical head space (metres, +x subject's left, +y up, +z out of the face; origin = the ICT
head centre, see ``data/headmodel.py``). Since head pose lives in the cameras, the camera's
world-to-camera transform **is** that pose: ``w2c = [[R, t], [0, 0, 0, 1]]``.
"""

from __future__ import annotations

import numpy as np
import torch

from ..cameras import Cameras

__all__ = ["pose_to_cameras", "cameras_to_pose"]


def pose_to_cameras(R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int) -> Cameras:
    """Cameras ``[V]`` from head rotations ``R [V, 3, 3]`` (head -> camera), translations ``t [V, 3]``
    (metres) and intrinsics ``K [V, 3, 3]`` (or ``[3, 3]``) of ``width`` x ``height`` images."""
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
    if R.shape[0] != t.shape[0]:
        raise ValueError(f"got {R.shape[0]} rotations but {t.shape[0]} translations")
    K = np.broadcast_to(np.asarray(K, dtype=np.float64), (R.shape[0], 3, 3))
    # re-orthonormalise (float drift of the multiplicative updates) so Cameras' checks hold
    U, _, Vt = np.linalg.svd(R)
    R = U @ Vt
    w2c = np.zeros((R.shape[0], 4, 4))
    w2c[:, :3, :3] = R
    w2c[:, :3, 3] = t
    w2c[:, 3, 3] = 1.0
    return Cameras(torch.tensor(K, dtype=torch.float32), torch.tensor(w2c, dtype=torch.float32), width, height)


def cameras_to_pose(cams: Cameras) -> tuple[np.ndarray, np.ndarray]:
    """The inverse: ``(R [V, 3, 3], t [V, 3])`` of the head in each camera."""
    c = cams.flatten()
    return c.R.double().numpy(), c.t.double().numpy()
