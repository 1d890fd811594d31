"""What the expression-prior frame benchmarks share (``prior_frame_ab.py``, ``prior_frame_profile.py``):
one model with the prior (A) and the same weights on the old prior-off path (B), and their avatars
of the shipped sample ``synth_1000001`` (its first 4 request photos)."""

from __future__ import annotations

import copy
import json
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def prior_on_off(model_name: str):
    """``(model_a, model_b, avatar_a, avatar_b)``; raises ``ValueError`` when the model has no prior."""
    import numpy as np
    import torch
    from PIL import Image

    from fastgha_core.cameras import load_request_folder
    from fastgha_core.model.fastgha import load_model

    model_a = load_model(model_name)
    if not model_a.config.deform.prior:
        raise ValueError(f"model {model_name!r} has no expression prior: nothing to compare")
    model_b = copy.deepcopy(model_a)
    model_b.config.deform.prior = False
    paths, cams = load_request_folder(REPO / "fastgha_core" / "assets" / "samples" / "synth_1000001" / "request")
    imgs = [torch.from_numpy(np.array(Image.open(p).convert("RGB"))).permute(2, 0, 1) for p in paths[:4]]
    x, c = model_a.prepare(imgs, cams[:4])
    return model_a, model_b, model_a.reconstruct(x, c), model_b.reconstruct(x, c)


def write_json(path: str | None, report: dict) -> None:
    """Write ``report`` to ``path`` (its folder created) when a path was given (``--json``)."""
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps(report, indent=2))
