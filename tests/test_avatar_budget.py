"""The server's avatar budget (``FastGHA.serving_nbytes``) against the bytes an animated avatar holds.

The reference walks every tensor reachable from the avatar after it has streamed a frame (Gaussians,
prior binding, deformation cache, prior runtime), counting each storage once and leaving out the
blendshape basis shared by all avatars.
"""

from __future__ import annotations

import torch
from test_prior import model_and_avatar  # noqa: F401  (module fixture: random-weight tiny model, ICT-skin avatar)

from fastgha_core.model import prior as prior_mod


def _tensor_bytes(x, seen: set[int]) -> int:
    if isinstance(x, torch.Tensor):
        if x.layout == torch.sparse_csr:
            return sum(_tensor_bytes(t, seen) for t in (x.crow_indices(), x.col_indices(), x.values()))
        key = x.untyped_storage().data_ptr()
        if key in seen:
            return 0
        seen.add(key)
        return x.untyped_storage().nbytes()
    if isinstance(x, (list, tuple)):
        return sum(_tensor_bytes(t, seen) for t in x)
    return 0


def _held_bytes(avatar) -> int:
    seen = {t.untyped_storage().data_ptr() for t, *_ in prior_mod._SHARED.values()}  # shared by all avatars
    parts = [vars(avatar.gaussians).values(), vars(avatar.prior).values(), [avatar.deform_cache]]
    if avatar.prior_runtime is not None:
        parts.append(vars(avatar.prior_runtime).values())
    return sum(_tensor_bytes(v, seen) for part in parts for v in part)


def test_serving_bytes_match_what_an_animated_avatar_holds(model_and_avatar):  # noqa: F811 (the imported fixture)
    model, avatar, _ = model_and_avatar
    avatar.deform_cache = avatar.prior_runtime = None
    estimate = model.serving_nbytes(avatar)
    z = model.expression_space.parse({"jawOpen": 0.8, "eyeBlink_L": 1.0})
    model.animate(avatar, z)  # the server's CPU frame path: fills the MLP cache and the prior's compact basis
    held = _held_bytes(avatar)
    assert avatar.prior_runtime is not None and avatar.prior_runtime._compact is not None
    assert abs(estimate - held) <= 0.02 * held, (estimate, held)
    # the Gaussians alone (what the budget counted before) miss most of it
    assert int(avatar.nbytes) < 0.6 * held

