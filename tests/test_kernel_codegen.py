"""The compositing kernels' row loops vectorise 8 float32 lanes wide on AVX2.

On AVX2 (sixteen 256-bit registers, no vector int64 -> float conversion) LLVM sized the row loops'
vectors by a 64-bit lane in them (the column index converted to float, a stop mask built with
``1 << q``) and took 4 float lanes, leaving the gradient row mostly scalar: 2.5x slower than the
AVX-512 build on the same core (docs/benchmarks-log.md, "Traced and fixed the next morning";
``fastgha_core/render/cpu_kernels.py``). This compiles both kernels, in a fresh process, for
``x86-64-v3`` with every AVX-512 feature off (``bench/_bench_cli.py`` ``avx2_env``, the environment
``--isa avx2`` gives whole benchmarks) and reads their optimised LLVM IR: float vectors 8 lanes wide (4-lane ones
rare), no vector of 64-bit integers. The kernels before the fix fail it (checked against 1a81e15
with ``FASTGHA_CODEGEN_ROOT``).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from test_bench_scripts_cli import avx2_env

ROOT = Path(os.environ.get("FASTGHA_CODEGEN_ROOT", Path(__file__).resolve().parents[1]))  # another checkout's kernels

PROBE = r"""
import json, re
import fastgha_core
from fastgha_core.bench.render import bench_camera, head_scene
from fastgha_core.gaussians import Gaussians
from fastgha_core.render import cpu_kernels as K, render

# one float32 render with gradients compiles both compositing kernels for this target
g, cams = head_scene(2048), bench_camera(64)
x = {k: getattr(g, k).detach().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "colors")}
out = render(Gaussians(**x), cams, background=(1.0, 1.0, 1.0), backend="cpu")
(out.rgb.sum() + out.alpha.sum() + 0.1 * out.depth.sum()).backward()
res = {}
for fn in (K.raster_forward_fast, K.raster_backward_fast):
    ir = "\n".join(fn.inspect_llvm().values())
    res[fn.__name__] = {
        "float_vectors": {w: ir.count(f"<{w} x float>") for w in (4, 8, 16)},
        "i64_vectors": len(re.findall(r"<\d+ x i64>", ir)),
    }
print(json.dumps(res))
"""


@pytest.mark.skipif(avx2_env() is None, reason="needs an x86 CPU with AVX2 (LLVM targets the host's feature list)")
def test_row_loops_vectorise_eight_wide_on_avx2(tmp_path):
    env = {**os.environ, **avx2_env(), "NUMBA_CACHE_DIR": str(tmp_path),
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}  # fmt: skip
    run = subprocess.run([sys.executable, "-c", PROBE], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    got = json.loads(run.stdout.strip().splitlines()[-1])
    for name, ir in got.items():
        v = ir["float_vectors"]
        assert v["8"] > 10 * v["4"] and v["16"] == 0, (name, ir)  # 8 lanes, as wide as AVX2 goes
        assert ir["i64_vectors"] == 0, (name, ir)
