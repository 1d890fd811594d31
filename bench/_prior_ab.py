"""What the expression-prior frame benchmarks share (``prior_frame_ab.py``, ``prior_frame_profile.py``):
one model with the prior (A) and the same weights on the old prior-off path (B), and their avatars
of the shipped sample ``synth_1000001`` (its first 4 request photos)."""

from __future__ import annotations

import copy
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


def rev_package(rev: str, tmp: str) -> str:
    """Export ``fastgha_core`` of git revision ``rev`` into ``tmp`` as the package ``fastgha_rev`` (its
    modules import each other relatively) and put ``tmp`` on ``sys.path``; returns the package name.
    Raises ``ValueError`` when git cannot export the revision."""
    import subprocess
    import sys

    dest = Path(tmp)
    try:
        data = subprocess.run(["git", "-C", str(REPO), "archive", rev, "fastgha_core"], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(dest)], input=data, check=True, capture_output=True)
    except subprocess.CalledProcessError as e:
        raise ValueError(f"cannot export fastgha_core of revision {rev!r}: {e.stderr.decode(errors='replace').strip()}") from None
    (dest / "fastgha_core").rename(dest / "fastgha_rev")
    sys.path.insert(0, str(dest))
    return "fastgha_rev"


def rev_frame(pkg: str, model_name: str, camera):
    """The prior path of another revision's package ``pkg`` (``rev_package``): its model with its
    avatar of the same sample, and ``frame(z, size, quality)`` doing what ``server.frames.FrameRenderer.render``
    does (animate, render, quantise, JPEG) with that package's code."""
    import importlib

    import numpy as np
    import torch
    from PIL import Image

    from fastgha_core.constants import BACKGROUND_RGB
    from server.imaging import encode_jpeg, frame_to_uint8

    fg = importlib.import_module(f"{pkg}.model.fastgha")
    cmod = importlib.import_module(f"{pkg}.cameras")
    render = importlib.import_module(f"{pkg}.render").render
    model = fg.load_model(model_name)
    paths, cams = cmod.load_request_folder(REPO / "fastgha_core" / "assets" / "samples" / "synth_1000001" / "request")
    imgs = [torch.from_numpy(np.array(Image.open(p).convert("RGB"))).permute(2, 0, 1) for p in paths[:4]]
    x, c = model.prepare(imgs, cams[:4])
    avatar = model.reconstruct(x, c)
    base = cmod.Cameras(camera.K, camera.w2c, camera.width, camera.height)

    def frame(z, size: int, quality: int) -> bytes:
        cam = base.resize(size, size)
        with torch.inference_mode():
            g = model.animate(avatar, z)
            img = frame_to_uint8(render(g, cam, background=BACKGROUND_RGB).rgb[0])
        return encode_jpeg(img, quality)

    return model, avatar, frame
