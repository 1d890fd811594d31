"""Avatars of what frontal photos see, built with and without one of the expression prior's shells,
for the shell tests (``test_chin_shell``, ``test_cheek_shell``)."""

from __future__ import annotations

import copy

import numpy as np
import torch

SKIN = np.array([0.78, 0.58, 0.48], np.float32)


def face_avatars(flag: str, opacity: float = 0.95, back_color=None, on=True, off=False):
    """ICT skin in front of the ears, above the chin and not facing down, one skin-coloured Gaussian at
    ``opacity`` on every other vertex, built by the ``tiny`` model (its deformation MLP zeroed) with
    ``config.deform.<flag>`` on and off (set to ``on`` / ``off``): ``({"on": (model, avatar), "off": ...}, n, lm [68, 3])``,
    ``n`` the face's Gaussians. ``back_color``: also opaque Gaussians of that RGB on every other head
    vertex 3 cm or more behind the ears (dark hair: the back shell then takes its colour), counted in ``n``."""
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
    cols, opac = np.tile(SKIN, (n, 1)), np.full(n, opacity, np.float32)
    if back_color is not None:
        back = np.arange(0, 11248, 2)
        back = back[v[back, 2] < lm[0, 2] - 0.03]
        face = np.concatenate([face, back])
        cols = np.concatenate([cols, np.tile(np.asarray(back_color, np.float32), (len(back), 1))])
        opac = np.concatenate([opac, np.ones(len(back), np.float32)])
        n = len(face)
    g = Gaussians(
        torch.from_numpy(v[face].copy()), torch.tensor([1.0, 0, 0, 0]).expand(n, 4).clone(), torch.full((n, 3), 0.0025),
        torch.from_numpy(opac), torch.from_numpy(cols.astype(np.float32)), torch.zeros(n, 32),
    )
    torch.manual_seed(0)
    m_on = FastGHA(get_preset("tiny")).eval()
    with torch.no_grad():
        m_on.deform.out.weight.zero_()
        m_on.deform.out.bias.zero_()
    setattr(m_on.config.deform, flag, on)
    m_off = copy.deepcopy(m_on)
    setattr(m_off.config.deform, flag, off)
    out = {}
    for name, m in (("on", m_on), ("off", m_off)):
        g2, b, n_int = m.build_prior(g)
        out[name] = (m, CanonicalAvatar(g2, "tiny", "ict53", b, n_int))
    return out, n, lm
