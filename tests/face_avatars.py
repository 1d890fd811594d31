"""Avatars of what frontal photos see, built with and without one of the expression prior's shells,
for the shell tests (``test_chin_shell``, ``test_cheek_shell``)."""

from __future__ import annotations

import copy

import numpy as np
import torch

SKIN = np.array([0.78, 0.58, 0.48], np.float32)


def face_avatars(flag: str, opacity: float = 0.95):
    """ICT skin in front of the ears, above the chin and not facing down, one skin-coloured Gaussian at
    ``opacity`` on every other vertex, built by the ``tiny`` model (its deformation MLP zeroed) with
    ``config.deform.<flag>`` on and off: ``({"on": (model, avatar), "off": ...}, n, lm [68, 3])``,
    ``n`` the face's Gaussians."""
    from fastgha_core.config import get_preset
    from fastgha_core.data.headmodel import HeadModel, vertex_normals
    from fastgha_core.gaussians import Gaussians
    from fastgha_core.model.avatar import CanonicalAvatar
    from fastgha_core.model.fastgha import FastGHA
    from fastgha_core.model.prior import CHIN_SHELL_DOWN, load_basis

    basis = load_basis("ict53")
    hm = HeadModel.load()
    v = hm.neutral
    lm = v[hm.landmarks68]
    ny = vertex_normals(v, basis.bind_faces)[:, 1]
    face = np.arange(0, 11248, 2)
    face = face[(v[face, 2] > lm[0, 2] - 0.01) & (v[face, 1] > lm[8, 1] - 0.005) & (ny[face] > CHIN_SHELL_DOWN)]
    n = len(face)
    g = Gaussians(
        torch.from_numpy(v[face].copy()), torch.tensor([1.0, 0, 0, 0]).expand(n, 4).clone(), torch.full((n, 3), 0.0025),
        torch.full((n,), opacity), torch.from_numpy(np.tile(SKIN, (n, 1))), torch.zeros(n, 32),
    )
    torch.manual_seed(0)
    on = FastGHA(get_preset("tiny")).eval()
    with torch.no_grad():
        on.deform.out.weight.zero_()
        on.deform.out.bias.zero_()
    setattr(on.config.deform, flag, True)
    off = copy.deepcopy(on)
    setattr(off.config.deform, flag, False)
    out = {}
    for name, m in (("on", on), ("off", off)):
        g2, b, n_int = m.build_prior(g)
        out[name] = (m, CanonicalAvatar(g2, "tiny", "ict53", b, n_int))
    return out, n, lm
