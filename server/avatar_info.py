"""What an avatar's frames are made with: view blending and the expression prior.

``GET /v1/avatars/{id}`` (and the ``avatar`` of a ready status) reports, per avatar:

- ``view_blend``: whether the avatar carries per-view data (``CanonicalAvatar.view_blend``: avatars
  built on a tracked head, e.g. from photos without cameras), from how many input views, the
  server's tau (``FASTGHA_VIEW_BLEND_TAU_DEG``, else the model's ``gaussians.view_blend_tau_deg``)
  and whether its frames are therefore view-blended (``active``: per-view data of at least two
  views and tau > 0; with one view every weight is 1; ``fastgha_core/model/viewblend.py``);
- ``expression_prior``: whether the model runs the head-model expression prior
  (``DeformConfig.prior``), whether this avatar has its binding to a fitted head and how many
  mouth-interior Gaussians it holds, and the prior's options (shading, rotation, back shell, fade).

The avatar-level facts are recorded once, at creation, by :func:`avatar_facts` (stored in the
avatar's metadata); the server-level options are read when the resource is asked for, since they
are what frames are rendered with now. Avatars created before these facts were recorded get them
from their file (:func:`avatar_facts` of the loaded avatar).
"""

from __future__ import annotations

from typing import Any

__all__ = ["FACT_KEYS", "avatar_facts", "avatar_options", "server_options"]

#: metadata keys written by :func:`avatar_facts`
FACT_KEYS = ("view_blend_views", "prior_bound", "num_interior")


def avatar_facts(avatar: Any) -> dict:
    """``{"view_blend_views": V or 0, "prior_bound": bool, "num_interior": int}`` of a
    ``CanonicalAvatar`` (``V`` = input views with per-view data, 0 = none)."""
    vb = getattr(avatar, "view_blend", None)
    return {
        "view_blend_views": 0 if vb is None else int(vb.directions.shape[0]),
        "prior_bound": getattr(avatar, "prior", None) is not None,
        "num_interior": int(getattr(avatar, "num_interior", 0)),
    }


def server_options(model: Any) -> dict:
    """The model's view-blending tau and expression-prior options as the server runs them
    (``GET /v1/model``): ``{"view_blend_tau_deg": float, "mirror_views": bool, "expression_prior": {...}}``."""
    d = model.config.deform
    return {
        "view_blend_tau_deg": float(model.config.gaussians.view_blend_tau_deg),
        "mirror_views": bool(model.config.gaussians.mirror_views),
        "expression_prior": {
            "enabled": bool(d.prior),
            "shading": bool(d.prior and d.prior_shading),
            "rotate": bool(d.prior and d.prior_rotate),
            "mouth_interior": bool(d.prior and d.mouth_interior),
            "back_shell": bool(d.prior and d.back_shell),
            "chin_shell": bool(d.prior and d.chin_shell),
            "cheek_shell": bool(d.prior and d.cheek_shell),
            "face_shell": d.face_shell if d.prior else "off",
            "fade_m": [float(x) for x in d.prior_fade],
        },
    }


def avatar_options(model: Any, facts: dict) -> dict:
    """``{"view_blend": {...}, "expression_prior": {...}}`` of one avatar (module doc) from its
    :func:`avatar_facts` and the loaded model."""
    opts = server_options(model)
    tau = opts["view_blend_tau_deg"]
    views = int(facts.get("view_blend_views", 0))
    prior = dict(opts["expression_prior"])
    # bound at creation; a model with the prior binds an avatar without one on its first frame (FastGHA.attach_prior)
    prior["bound"] = bool(facts.get("prior_bound", False))
    prior["mouth_interior_gaussians"] = int(facts.get("num_interior", 0))
    return {
        "view_blend": {"per_view_data": views > 0, "views": views, "tau_deg": tau, "active": views > 1 and tau > 0},
        "expression_prior": prior,
    }
