"""Served frames of the working tree against those of another git revision: the largest pixel change.

Both render the shipped ``tiny`` model's avatar of the sample ``synth_1000001`` (4 views) through
``model.animate`` + ``render`` + the server's quantisation, at 256² and 512², from the server's
default camera and from 30° of yaw, at 12 expressions (neutral, ``jawOpen``, both blinks, both
smiles, one blink, jaw + one blink, and 6 random ones uniform in [0, 0.6]). The other revision is
exported with ``git archive`` into a temporary folder and run there in a subprocess.

    python bench/frames_vs_rev.py a4e07d3
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def frames(repo: Path, out: Path) -> None:
    """Render the frames with the code in ``repo`` into ``out`` (npz: uint8 and float32 per frame)."""
    sys.path.insert(0, str(repo))
    import fastgha_core  # noqa: F401  (OpenMP defaults before torch)
    import numpy as np
    import torch
    from PIL import Image

    from fastgha_core.cameras import Cameras, load_request_folder
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.render import render
    from server.frames import FrameRenderer
    from server.imaging import frame_to_uint8

    m = load_model("tiny")
    paths, cams = load_request_folder(repo / "fastgha_core" / "assets" / "samples" / "synth_1000001" / "request")
    imgs = [torch.from_numpy(np.array(Image.open(p).convert("RGB"))).permute(2, 0, 1) for p in paths[:4]]
    x, c = m.prepare(imgs, cams[:4])
    av = m.reconstruct(x, c)
    names = m.expression_space.names
    zs = [torch.zeros(53)]
    for combo in (["jawOpen"], ["eyeBlink_L", "eyeBlink_R"], ["mouthSmile_L", "mouthSmile_R"], ["eyeBlink_L"], ["jawOpen", "eyeBlink_R"]):
        z = torch.zeros(53)
        z[[names.index(n) for n in combo]] = 1.0
        zs.append(z)
    gen = torch.Generator().manual_seed(0)
    zs += [torch.rand(53, generator=gen) * 0.6 for _ in range(6)]
    res = {}
    for size in (256, 512):
        front = FrameRenderer(m, "cpu").default_camera.resize(size, size)
        yaw = Cameras.look_at((0.5, 0.0, 0.866), (0.0, 0.0, 0.0), fov_deg=20.0, width=size, height=size)
        for ci, cam in enumerate((front, yaw)):
            for i, z in enumerate(zs):
                with torch.inference_mode():
                    rgb = render(m.animate(av, z), cam, background=BACKGROUND_RGB).rgb[0]
                res[f"{size}_{ci}_{i}"] = frame_to_uint8(rgb)
                res[f"{size}_{ci}_{i}_f"] = rgb.permute(1, 2, 0).numpy()
    np.savez_compressed(out, **res)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("rev", nargs="?", help="git revision to compare with")
    ap.add_argument("--render-into", nargs=2, metavar=("REPO", "OUT"), help=argparse.SUPPRESS)  # the subprocess
    args = ap.parse_args(argv)
    if args.render_into:
        frames(Path(args.render_into[0]), Path(args.render_into[1]))
        return 0
    if not args.rev:
        ap.error("give a git revision")
    import numpy as np

    with tempfile.TemporaryDirectory() as tmp:
        other = Path(tmp) / "rev"
        other.mkdir()
        archive = subprocess.run(["git", "archive", args.rev], cwd=REPO, check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(other)], input=archive, check=True)
        outs = {}
        for name, repo in ((args.rev, other), ("working tree", REPO)):
            outs[name] = Path(tmp) / f"{'rev' if repo is other else 'wt'}.npz"
            env = dict(os.environ, PYTHONPATH=str(repo))
            subprocess.run([sys.executable, __file__, "--render-into", str(repo), str(outs[name])], check=True, env=env)
        a, b = np.load(outs[args.rev]), np.load(outs["working tree"])
        keys = [k for k in a.files if not k.endswith("_f")]
        d8 = [np.abs(a[k].astype(np.int16) - b[k].astype(np.int16)) for k in keys]
        df = max(float(np.abs(a[k + "_f"] - b[k + "_f"]).max()) for k in keys)
        changed, total = sum(int((d > 0).sum()) for d in d8), sum(d.size for d in d8)
        print(f"{len(keys)} frames: largest change {max(int(d.max()) for d in d8)}/255 after quantisation "
              f"({changed} of {total} channel values differ), {df * 255:.3f}/255 before")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
