"""Shared helpers of the client and browser tests: a small model folder, a synthetic sample
subject, and a real uvicorn server process on 127.0.0.1.

The server is the normal ``server.app:create_app``; its ``/v1/samples`` routes point at a test
folder through ``FASTGHA_SAMPLES_DIR``. Keyword arguments override any ``FASTGHA_*`` setting.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parent.parent
API_KEY = "test-api-key"
SAMPLE_NAME = "testhead"
SAMPLE_SIZE = 64  # request photo size of the synthetic sample


def make_model_dir(path: Path) -> Path:
    """A ``tiny``-architecture model at 64 x 64 whose deformation output layer is non-zero
    (a fresh one is the identity, so expressions would not change the picture)."""
    import torch

    from fastgha_core.config import get_preset
    from fastgha_core.model.fastgha import FastGHA

    cfg = get_preset("tiny")
    cfg.input_size = 64
    cfg.render_size = 64
    torch.manual_seed(0)
    model = FastGHA(cfg)
    with torch.no_grad():
        model.deform.out.weight.normal_(0.0, 0.2)
    model.save_pretrained(path)
    return path


def make_sample_dir(root: Path, name: str = SAMPLE_NAME, frames: int = 12) -> Path:
    """A synthetic sample subject ``root/name`` in the shipped layout (request/, expressions.npy, orbit.json)."""
    from PIL import Image

    from fastgha_core.cameras import cameras_to_json, orbit_cameras
    from fastgha_core.expressions import get_space

    d = root / name
    req = d / "request"
    req.mkdir(parents=True, exist_ok=True)
    n, s = 4, SAMPLE_SIZE
    cams = orbit_cameras(n, width=s, height=s)
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[0:s, 0:s]
    for i in range(n):
        img = np.full((s, s, 3), 255, np.uint8)
        inside = ((xx - s / 2) / (0.3 * s)) ** 2 + ((yy - s / 2) / (0.4 * s)) ** 2 < 1.0  # a face-sized ellipse
        img[inside] = rng.integers(80, 200, 3, dtype=np.uint8)
        img = np.clip(img.astype(int) + rng.integers(-25, 25, img.shape), 0, 255).astype(np.uint8)
        Image.fromarray(img).save(req / f"{i:02d}.jpg", quality=92)
        Image.fromarray((inside * 255).astype(np.uint8)).save(req / f"{i:02d}_mask.png")
    (req / "cameras.json").write_text(json.dumps(cameras_to_json(cams)))
    dim = get_space("ict53").dim
    t = np.linspace(0, 2 * np.pi, frames, endpoint=False)[:, None]
    expr = (0.5 + 0.5 * np.sin(t + np.arange(dim)[None] * 0.3)).astype(np.float32)  # [T, E]
    np.save(d / "expressions.npy", expr)
    orbit = orbit_cameras(8, width=s, height=s)
    (d / "orbit.json").write_text(json.dumps(cameras_to_json(orbit)))
    return d


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerProcess:
    """``uvicorn --factory server.app:create_app`` on a free loopback port."""

    def __init__(
        self, model_dir: Path, data_dir: Path, samples_dir: Path | None, log_path: Path, *, serve_cli: bool = False, **env_overrides: str
    ) -> None:
        """``serve_cli``: start it as ``fastgha serve`` does (uvicorn with server/security.py's guarded
        protocols and connection limits) instead of plain ``uvicorn --factory``."""
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.ws_base = f"ws://127.0.0.1:{self.port}"
        env = dict(os.environ)
        env.update(
            FASTGHA_MODEL=str(model_dir),
            FASTGHA_DEVICE="cpu",
            FASTGHA_DATA_DIR=str(data_dir),
            FASTGHA_API_KEYS=API_KEY,
            FASTGHA_WARMUP="true",
            FASTGHA_WARMUP_FRAMES="1",
            FASTGHA_RENDER_WORKERS="2",
            FASTGHA_COMPILE="off",  # tests/test_server.py turns it on once; compiling costs seconds per start
            PYTHONPATH=os.pathsep.join([str(REPO), str(REPO / "tests"), env.get("PYTHONPATH", "")]),
        )
        if samples_dir is not None:
            env["FASTGHA_SAMPLES_DIR"] = str(samples_dir)
        env.update(env_overrides)
        self.log_path = log_path
        self.log = open(log_path, "ab")
        argv = (
            [sys.executable, "-m", "fastgha_core.cli", "serve", "--host", "127.0.0.1", "--port", str(self.port)]
            if serve_cli
            else [sys.executable, "-m", "uvicorn", "--factory", "server.app:create_app", "--host", "127.0.0.1",
                  "--port", str(self.port), "--timeout-graceful-shutdown", "5"]
        )  # fmt: skip
        self.proc = subprocess.Popen(argv, cwd=REPO, env=env, stdout=self.log, stderr=subprocess.STDOUT)
        self._wait_ready()

    def _wait_ready(self, timeout: float = 240.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited with {self.proc.returncode}:\n{self.log_path.read_text()[-3000:]}")
            try:
                if httpx.get(self.base + "/healthz", timeout=2).json().get("status") == "ok":
                    return
            except (httpx.HTTPError, ValueError):
                pass
            time.sleep(0.3)
        raise RuntimeError(f"server did not start:\n{self.log_path.read_text()[-3000:]}")

    def alive(self) -> bool:
        return self.proc.poll() is None and httpx.get(self.base + "/healthz", timeout=5).json()["status"] == "ok"

    def stop(self, sig: int = signal.SIGTERM) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()
        return self.proc.returncode


def random_avatar(n: int = 16, seed: int = 0):
    """A small random ``CanonicalAvatar`` (``n`` Gaussians, 4 features, ``tiny`` / ``ict53``) for store tests."""
    import torch

    from fastgha_core.gaussians import Gaussians
    from fastgha_core.model.avatar import CanonicalAvatar

    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g)
    gs = Gaussians(
        means=torch.randn(n, 3, generator=g) * 0.1,
        quats=q / q.norm(dim=-1, keepdim=True),
        scales=torch.rand(n, 3, generator=g) * 0.01 + 1e-3,
        opacities=torch.rand(n, generator=g) * 0.9 + 0.05,
        colors=torch.rand(n, 3, generator=g),
        features=torch.randn(n, 4, generator=g),
    )
    return CanonicalAvatar(gs, "tiny", "ict53")
