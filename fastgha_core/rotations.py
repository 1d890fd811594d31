"""Rotation conversions shared by cameras (FLAME head poses) and expression spaces (6D codes).

Conventions:
- axis-angle ``[..., 3]``: direction = rotation axis, length = angle in radians (right-handed),
  the parameterisation FLAME, VHAP and NeRSemble use for ``global_orient``/``jaw_pose``/``eyes_pose``;
- rotation matrices ``[..., 3, 3]`` act on column vectors: ``x' = R @ x``;
- 6D rotation (Zhou et al. 2019): the **first two columns** of ``R``, flattened column by column,
  ``[R00, R10, R20, R01, R11, R21]``; the identity is ``[1, 0, 0, 0, 1, 0]``. (pytorch3d's
  ``matrix_to_rotation_6d`` takes the first two *rows* instead, i.e. the 6D code of ``R^T``.)
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["axis_angle_to_matrix", "matrix_to_rotation_6d", "rotation_6d_to_matrix", "IDENTITY_6D"]

# 6D code of the identity rotation (first two columns of I, column by column).
IDENTITY_6D: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)


def _skew(v: Tensor) -> Tensor:  # [..., 3] -> [..., 3, 3]
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*v.shape[:-1], 3, 3)


def axis_angle_to_matrix(axis_angle: Tensor) -> Tensor:
    """Rodrigues' formula: ``axis_angle [..., 3]`` -> rotation matrices ``[..., 3, 3]``.

    ``R = I + a [w]x + b [w]x^2`` with ``a = sin(t)/t``, ``b = (1 - cos t)/t^2``, ``t = |w|``;
    Taylor series are used for small angles so that the result and its gradient stay finite at 0.
    """
    if axis_angle.shape[-1:] != (3,):
        raise ValueError(f"axis-angle rotations must have shape [..., 3], got {list(axis_angle.shape)}")
    w = axis_angle
    t2 = (w * w).sum(-1)  # [...]
    small = t2 < 1e-8
    t2_safe = torch.where(small, torch.ones_like(t2), t2)
    t = t2_safe.sqrt()
    a = torch.where(small, 1.0 - t2 / 6.0, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24.0, (1.0 - torch.cos(t)) / t2_safe)
    S = _skew(w)  # [..., 3, 3]
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(S.shape)
    return eye + a[..., None, None] * S + b[..., None, None] * (S @ S)


def matrix_to_rotation_6d(R: Tensor) -> Tensor:
    """``R [..., 3, 3]`` -> 6D code ``[..., 6]`` = first two columns ``[R00, R10, R20, R01, R11, R21]``."""
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices must have shape [..., 3, 3], got {list(R.shape)}")
    return torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1)


def rotation_6d_to_matrix(d6: Tensor) -> Tensor:
    """6D code ``[..., 6]`` -> rotation matrix ``[..., 3, 3]`` by Gram-Schmidt on the two columns.

    The inverse of :func:`matrix_to_rotation_6d` on valid rotations; any 6D vector whose two
    3-vectors are non-zero and not parallel maps to the nearest-in-spirit rotation.
    """
    if d6.shape[-1:] != (6,):
        raise ValueError(f"6D rotations must have shape [..., 6], got {list(d6.shape)}")
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = a1 / a1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    a2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = a2 / a2.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)  # columns
