"""Closed-eyed input photos and the neutral avatar's eyes (issue 16).

Each input photo's Gaussians are moved back from that photo's (known or tracked) expression to the
neutral canonical head by the expression prior's displacement (``FastGHA.build_prior``). Where a photo
shows an eye closed by a blink, its pixels over the eye are closed-lid skin and lashes. Undone, they
do not move up to where the open lid sits: they bind to the fitted eyeball (which a blink does not
move) or only partly follow the lid, and in the neutral avatar they cover the open eye of the other
views with skin. The neutral eye then reads less open: on 20 held-out synthetic subjects (seeds
1000200-1000219, 256 px) dlib's eye aspect ratio of the neutral avatar, over the truth's, was
0.70 / 0.77 (frontal / 30 degrees of yaw, means) for the 4 subjects with two input photos blinking
(eyeBlink >= 0.5), 0.71 / 0.80 with one (10 subjects) and 0.82 / 0.91 with none (6); and since the
blink response is measured relative to the neutral eye, a less open neutral eye is a smaller blink.

``show_closed_lids`` gives those bound to the eyeball the lid gate of their eye instead of the
eyeball's fade: hidden at the neutral expression (the open eye is the open-eyed views'), they appear
as the avatar's lid closes, where they show the photo's own closed lid. Those bound to the lids and
the skin around the eye are left alone: the undone displacement already put them where they belong
at the neutral expression. (Also switching those, within ``CLOSED_LID_RADIUS`` of the closed lid,
was tried: a more open neutral eye, eyeBlink 0.76 instead of 0.73 on draw B at 256 px, but held-out
PSNR 19.9675 dB against 19.9714: the closed photo's skin next to the eye was missed from some views.)
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .prior import HeadBasis, HeadFit, PriorBinding, gate_factors

__all__ = ["CLOSED_VIEW_GATE", "CLOSED_LID_RADIUS", "OPEN_COVER", "closed_lid_views", "show_closed_lids"]

# A view closes an eye when that eye's lid gate (``basis.gates[k]``, ``gate_factors``) is at least this.
CLOSED_VIEW_GATE = 0.5
# Gaussians of a closed-eyed view within this distance (metres, times the fit's scale) of that eye's
# closed upper lid (the fitted lid vertices at the view's expression) are its closed lid.
CLOSED_LID_RADIUS = 0.004
# ... and only when the views that show that eye open put at least this many Gaussians (times the
# closed view's count) within that distance of the closed lid: a side view may not see the eye, and
# hiding the closed view's lid there would leave a hole in the neutral avatar's eye.
OPEN_COVER = 0.5


def _lid_factors(ve: np.ndarray, basis: HeadBasis) -> np.ndarray:
    """``[V, G - 1]``: each view's lid gate factors (``gate_factors``; 0 = open, 1 = closed)."""
    z = torch.as_tensor(np.asarray(ve, np.float32))
    return gate_factors(z, torch.as_tensor(basis.gates), torch.as_tensor(basis.gate_ranges)).numpy()[:, 1:]


def closed_lid_views(view_expressions: np.ndarray | Tensor, basis: HeadBasis) -> np.ndarray:
    """``[V, G - 1]`` bool: input views whose expression ``view_expressions [V, E]`` closes the eye of
    lid gate ``k = 1..G-1`` (gate factor >= ``CLOSED_VIEW_GATE``). An eye no view shows open is marked
    in no view (the neutral avatar keeps an eye). Raises ``ValueError`` for another shape."""
    ve = np.asarray(view_expressions.detach().cpu() if isinstance(view_expressions, Tensor) else view_expressions, np.float32)
    if ve.ndim != 2 or ve.shape[1] != basis.num_expression:
        raise ValueError(f"closed_lid_views: expected view expressions [V, {basis.num_expression}], got {list(ve.shape)}")
    f = _lid_factors(ve, basis)
    closed = f >= CLOSED_VIEW_GATE
    closed[:, ~(f <= 0.0).any(0)] = False  # no view with that eye open: leave it
    return closed


def show_closed_lids(binding: PriorBinding, points: np.ndarray | Tensor, view_index: Tensor, view_expressions: np.ndarray | Tensor, fit: HeadFit, basis: HeadBasis) -> PriorBinding:
    """Give the closed-lid Gaussians of closed-eyed input views their eye's lid gate (see module doc).

    Args:
        binding: the reconstructed Gaussians' binding (``N``).
        points: ``[N, 3]`` where each Gaussian sits at its own view's expression (before neutralising;
            metres, the fit's world frame).
        view_index: ``[N]`` input view of each Gaussian.
        view_expressions: ``[V, E]`` the views' expressions.
        fit: the head fit (its vertices, transform).
        basis: the head basis; without lid gates (``basis.interior_group`` has no group ``k >= 1``,
            e.g. ``flame120``) the binding is returned unchanged.
    Returns:
        The binding with group ``k`` (appear with lid gate ``k``) for each Gaussian of a view that
        closes eye ``k`` (``closed_lid_views``), with weight > 0, within ``CLOSED_LID_RADIUS`` (times
        the fit's scale) of that eye's closed upper lid at that view's expression, and bound to that
        eye's eyeball (group ``G - 1 + k``: it hid as the lid closed and showed on the open eye, the
        inverse of what a closed lid's pixel should do); only where the views
        that show that eye open have at least ``OPEN_COVER`` times as many Gaussians within that
        distance (else that view's lid is left as it was: no hole in the neutral eye).
    Raises:
        ValueError: ``points`` or ``view_index`` not ``[N, 3]`` / ``[N]``.
    """
    from scipy.spatial import cKDTree

    p = points.detach().cpu().float().numpy() if isinstance(points, Tensor) else np.asarray(points, np.float32)
    if view_index.shape != (len(binding),) or p.shape != (len(binding), 3):
        raise ValueError(f"show_closed_lids: points and view_index must have shapes [{len(binding)}, 3] and [{len(binding)}], got {list(p.shape)} and {list(view_index.shape)}")
    G = int(basis.gates.shape[0])
    ig = basis.interior_group
    lash = np.zeros(len(ig), bool) if basis.lash is None else basis.lash
    if G < 2 or ig is None or not (ig >= 1).any():
        return binding
    ve = np.asarray(view_expressions.detach().cpu() if isinstance(view_expressions, Tensor) else view_expressions, np.float64)
    closed = closed_lid_views(ve, basis)  # [V, G-1]
    if not closed.any():
        return binding
    vi = view_index.detach().cpu().long().numpy()
    M = fit.transform[:3, :3].astype(np.float64)
    scale = float(np.cbrt(abs(np.linalg.det(M))))
    grp = binding.groups().cpu().numpy().copy()
    live = binding.weight.cpu().numpy() > 0
    opened = _lid_factors(ve, basis) <= 0.0  # [V, G-1]: views that show each eye open
    for k in range(1, G):
        lid = basis.interior_vertices[(ig == k) & ~lash]
        for v in np.flatnonzero(closed[:, k - 1]):
            mine = np.flatnonzero((vi == v) & live & (grp == G - 1 + k))  # bound to that eyeball
            if not len(mine):
                continue
            at = fit.vertices[lid].astype(np.float64) + np.tensordot(ve[v], basis.expression_basis[:, lid], axes=1) @ M.T
            tree = cKDTree(at)
            sel = mine[tree.query(p[mine])[0] < CLOSED_LID_RADIUS * scale]
            # only where the open-eyed views draw that eye too (a side view may not see it): else a hole
            other = np.flatnonzero(opened[vi, k - 1] & live)
            cover = int((tree.query(p[other])[0] < CLOSED_LID_RADIUS * scale).sum()) if len(other) else 0
            if cover >= OPEN_COVER * len(sel):
                grp[sel] = k
    return PriorBinding(
        binding.vertex_ids, binding.bary, binding.weight, binding.transform, binding.identity, binding.space,
        torch.from_numpy(grp).to(binding.vertex_ids.device),
    )
