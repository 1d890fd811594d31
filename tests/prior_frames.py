"""The two frame paths of an avatar with the expression prior, for tests that compare them."""

from __future__ import annotations

import torch

from fastgha_core.model.fastgha import _combine


def fast_and_plain(model, avatar, z: torch.Tensor):
    """``(fast, plain)`` Gaussians of ``avatar`` at expression ``z [E]``.

    ``fast``: ``model.animate`` (on CPU with one expression, ``PriorRuntime.frame``'s one numba pass);
    ``plain``: the general torch path (``_combine`` of the MLP's output, less ``residual_anchor``, with the runtime's displacement,
    gate, shading and, when ``deform.prior_rotate`` is on, rotation), untrimmed past the frame's length.
    """
    fast = model.animate(avatar, z)
    rt = avatar.prior_runtime
    with torch.inference_mode():
        dxyz, drgb = model.deform.forward_split(model._deform_partial(avatar), z)
        anchor = model.residual_anchor(avatar)  # avatars on a tracked surface: relative to each view's expression
        if anchor is not None:
            dxyz = dxyz - anchor
        rot = rt.rotation(z) if rt.rotate_on else None
        plain = _combine(avatar.gaussians, dxyz, drgb, rt.displacement(z), avatar.num_interior, model._gate(z, rt), trim=True, shade=rt.shading(z), rot=rot)
    return fast, plain
