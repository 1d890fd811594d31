"""Thread settings for torch and numba, and a description of the machine for benchmarks.

Why this exists: torch (CPU wheel) ships its own GNU OpenMP runtime and numba's ``omp``
threading layer loads the system one, so a process that runs the deformation MLP (torch) and
the rasterizer (numba) every frame holds two OpenMP thread pools on the same cores. With the
default wait policy each pool's idle threads spin after a parallel region, and the two pools
take turns starving each other: measured on the shared 2-core machine under load, one 256²
frame of the tiny avatar took 560-1170 ms with the default spin (300 000 iterations) and
130-151 ms with ``OMP_WAIT_POLICY=PASSIVE`` (same work; docs/benchmarks.md "Machine and thread settings").
Sleeping at once costs the MLP a wake-up per small op (deform 18 ms instead of 9-10 ms), so
the default here is a short bounded spin, ``GOMP_SPINCOUNT=10000``: deform 8-10 ms, render
unaffected, no starvation seen.

The wait policy is read once, when each OpenMP runtime initialises (torch's at ``import torch``),
so ``apply_env_defaults()`` must run before torch is imported: call it first thing in the
process entry point (``fastgha_core/__init__.py`` does this when the lead wires it in). This module
imports nothing heavy at import time.
"""

from __future__ import annotations

import logging
import os
import sys
from dataclasses import asdict, dataclass
from typing import MutableMapping

__all__ = [
    "ENV_DEFAULTS",
    "MAX_SAFE_SPINCOUNT",
    "ThreadConfig",
    "apply_env_defaults",
    "wait_policy_effective",
    "configure_threads",
    "current_threads",
    "describe_machine",
    "cpu_flags",
    "ISA_FLAGS",
]

log = logging.getLogger(__name__)

# Environment defaults applied before the OpenMP runtimes start (never overriding the user's).
ENV_DEFAULTS: dict[str, str] = {"GOMP_SPINCOUNT": "10000"}
MAX_SAFE_SPINCOUNT = 100_000  # above this, idle pools starve each other under load
# /proc/cpuinfo flags that decide which fast paths exist (matmul precision, SIMD width).
ISA_FLAGS = ("avx2", "fma", "avx512f", "avx512bw", "avx512vl", "avx512_bf16", "avx512_vnni", "avx_vnni", "amx_tile", "amx_bf16", "amx_int8")


def apply_env_defaults(environ: MutableMapping[str, str] | None = None) -> dict[str, str]:
    """Set ``ENV_DEFAULTS`` in ``environ`` (default ``os.environ``) where not already set.

    Returns what was set. Effective for torch's OpenMP runtime only if torch is not imported yet
    (a warning is logged otherwise); numba's runtime starts at its first parallel kernel.
    """
    env = os.environ if environ is None else environ
    if "OMP_WAIT_POLICY" in env:  # the user chose a policy; GOMP_SPINCOUNT would override it
        return {}
    changed = {k: v for k, v in ENV_DEFAULTS.items() if k not in env}
    env.update(changed)
    if changed and environ is None and "torch" in sys.modules:
        log.warning("apply_env_defaults() ran after torch was imported: %s does not reach torch's OpenMP runtime", changed)
    return changed


def wait_policy_effective(environ: MutableMapping[str, str] | None = None) -> bool:
    """Whether idle OpenMP threads stop spinning soon (``OMP_WAIT_POLICY=PASSIVE`` or a
    ``GOMP_SPINCOUNT`` of at most ``MAX_SAFE_SPINCOUNT``).

    Judged from the environment; only meaningful if it was set before torch was imported.
    """
    env = os.environ if environ is None else environ
    if env.get("OMP_WAIT_POLICY", "").strip().upper() == "PASSIVE":
        return True
    try:
        return int(env.get("GOMP_SPINCOUNT", "")) <= MAX_SAFE_SPINCOUNT
    except ValueError:
        return False


@dataclass
class ThreadConfig:
    """Threads in use.

    Attributes:
        torch_threads: torch intra-op threads (matmuls, elementwise ops).
        torch_interop_threads: torch inter-op threads.
        numba_threads: threads the CPU rasterizer uses (``cpu_backend.num_threads()``).
        numba_layer: numba threading layer (``omp``, ``workqueue``, ``tbb``; ``unset`` before the
            first parallel kernel).
        omp_wait_policy: ``OMP_WAIT_POLICY`` and ``GOMP_SPINCOUNT`` as set in the environment.
    """

    torch_threads: int
    torch_interop_threads: int
    numba_threads: int
    numba_layer: str
    omp_wait_policy: str

    def to_dict(self) -> dict:
        return asdict(self)


def current_threads() -> ThreadConfig:
    import numba
    import torch

    from .render.cpu_backend import num_threads

    try:
        layer = numba.threading_layer()
    except ValueError:  # no parallel kernel has run yet
        layer = "unset"
    return ThreadConfig(
        torch.get_num_threads(), torch.get_num_interop_threads(), num_threads(), layer,
        f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', '')} GOMP_SPINCOUNT={os.environ.get('GOMP_SPINCOUNT', '')}",
    )


def configure_threads(threads: int | None = None, numba_threads: int | None = None) -> ThreadConfig:
    """Use ``threads`` torch intra-op threads (default: all cores) and ``numba_threads`` rasterizer threads.

    The rasterizer and the MLP run one after the other within a frame, so both use all cores;
    concurrency across streams comes from the server's render pool. ``numba_threads`` is passed
    through ``FASTGHA_NUMBA_THREADS`` (``numba.set_num_threads`` is per calling thread and the
    rasterizer applies it per call). Logs a warning when idle OpenMP threads spin.
    """
    import torch

    cores = os.cpu_count() or 1
    n = cores if threads is None else int(threads)
    if n < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    torch.set_num_threads(n)
    if numba_threads is not None:
        if int(numba_threads) < 1:
            raise ValueError(f"numba_threads must be >= 1, got {numba_threads}")
        os.environ["FASTGHA_NUMBA_THREADS"] = str(int(numba_threads))
    if not wait_policy_effective():
        log.warning(
            "idle OpenMP threads spin long (no OMP_WAIT_POLICY=PASSIVE or GOMP_SPINCOUNT<=%d): torch's and numba's "
            "pools may starve each other (frames several times slower); start the process with GOMP_SPINCOUNT=10000",
            MAX_SAFE_SPINCOUNT,
        )
    return current_threads()


def cpu_flags(cpuinfo: str | None = None) -> tuple[str, set[str]]:
    """``(model name, flags)`` from ``/proc/cpuinfo`` text (read when not given); ``("unknown", set())`` elsewhere."""
    if cpuinfo is None:
        try:
            with open("/proc/cpuinfo") as f:
                cpuinfo = f.read()
        except OSError:
            return "unknown", set()
    model, flags = "unknown", set()
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if key == "model name" and model == "unknown":
            model = value.strip()
        elif key == "flags" and not flags:
            flags = set(value.split())
    return model, flags


def describe_machine() -> dict:
    """CPU model, cores, ISA flags that matter here, threads, load average, library versions."""
    import platform

    import numba
    import torch

    model, flags = cpu_flags()
    try:
        load = list(os.getloadavg())
    except OSError:
        load = None
    return {
        "cpu_model": model,
        "cores": os.cpu_count(),
        "isa_flags": {f: (f in flags) for f in ISA_FLAGS},
        "threads": current_threads().to_dict(),
        "load_average_1_5_15": load,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numba": numba.__version__,
        "cuda": torch.cuda.is_available(),
    }


def fast_bf16(device: str = "cpu", flags: set[str] | None = None) -> bool:
    """Whether bf16 matmuls run natively here: a CUDA device with bf16 support, or a CPU with
    AVX512-BF16 or AMX (elsewhere bf16 is emulated and slower than fp32)."""
    import torch

    dev = torch.device(device)
    if dev.type == "cuda":
        return bool(torch.cuda.is_available() and torch.cuda.is_bf16_supported())
    if flags is None:
        flags = cpu_flags()[1]
    return bool({"avx512_bf16", "amx_bf16"} & set(flags))


def cpp_compiler() -> str | None:
    """Path of the C++ compiler torch.compile's inductor would use on CPU (``CXX``, then c++/g++/clang++), or None."""
    import shutil

    for name in (os.environ.get("CXX"), "c++", "g++", "clang++"):
        if name and (path := shutil.which(name)):
            return path
    return None


# ----------------------------------------------------------------- MLP precision, chosen by measuring
BF16_MARGIN = 0.95  # bf16 must take at most this fraction of fp32's time to be chosen (it costs accuracy)
PRECISION_REPS = 7


@dataclass
class PrecisionChoice:
    """The deformation MLP's precision and why.

    Attributes:
        precision: ``"fp32"`` or ``"bf16"``.
        reason: ``"measured"`` (auto, by ``choose_mlp_precision``), ``"configured"`` (fp32/bf16 set
            explicitly), or ``"bf16 failed: <error>"`` (auto, bf16 could not run here).
        fp32_ms, bf16_ms: median milliseconds of one served chunk in each precision (None when not measured).
        reps: timed repetitions per precision.
        margin: bf16 is chosen when ``bf16_ms <= margin * fp32_ms``.
    """

    precision: str
    reason: str
    fp32_ms: float | None = None
    bf16_ms: float | None = None
    reps: int = 0
    margin: float = BF16_MARGIN

    @property
    def bf16(self) -> bool:
        return self.precision == "bf16"

    def to_dict(self) -> dict:
        d = asdict(self)
        for k in ("fp32_ms", "bf16_ms"):
            if d[k] is not None:
                d[k] = round(d[k], 3)
        return d


def choose_mlp_precision(run_fp32, run_bf16, reps: int = PRECISION_REPS, margin: float = BF16_MARGIN, timer=None) -> PrecisionChoice:
    """Pick fp32 or bf16 for the deformation MLP by timing both on this machine.

    ``run_fp32()`` / ``run_bf16()`` run one served chunk in each precision (and synchronise the
    device). Each runs once untimed (warm-up), then ``reps`` timed runs alternate between the two,
    so that a load change on a shared machine hits both alike; the medians decide: bf16 when
    ``median_bf16 <= margin * median_fp32`` (bf16 costs a little accuracy, so it must be clearly
    faster), else fp32. If ``run_bf16`` raises, fp32 is chosen and the reason says why.
    ``timer`` (seconds, default ``time.perf_counter``) is injectable for tests.
    Raises ``ValueError`` when ``reps < 1`` or ``margin <= 0``.
    """
    import statistics
    import time

    if reps < 1:
        raise ValueError(f"reps must be >= 1, got {reps}")
    if margin <= 0:
        raise ValueError(f"margin must be > 0, got {margin}")
    timer = timer or time.perf_counter
    run_fp32()
    try:
        run_bf16()
    except Exception as e:  # no bf16 kernels on this device / build
        return PrecisionChoice("fp32", f"bf16 failed: {type(e).__name__}: {str(e)[:120]}", reps=0, margin=margin)
    t32, t16 = [], []
    for _ in range(reps):
        for fn, out in ((run_fp32, t32), (run_bf16, t16)):
            t0 = timer()
            fn()
            out.append(1e3 * (timer() - t0))
    m32, m16 = statistics.median(t32), statistics.median(t16)
    return PrecisionChoice("bf16" if m16 <= margin * m32 else "fp32", "measured", m32, m16, reps, margin)


def measure_mlp_precision(model, reps: int = PRECISION_REPS, chunk_size: int = 8192, margin: float = BF16_MARGIN) -> PrecisionChoice:
    """``choose_mlp_precision`` on ``model``'s deformation MLP at the shape the server runs per frame:
    the per-chunk tail (every layer after the cached first-layer term) on ``[chunk_size, hidden]``
    rows, eager, under ``torch.inference_mode`` (bf16 = autocast on the model's device)."""
    import torch

    deform = model.deform
    dev = next(deform.parameters()).device
    hidden = int(deform.first.weight.shape[0])
    gen = torch.Generator().manual_seed(0)
    h = (0.5 * torch.randn(chunk_size, hidden, generator=gen)).to(dev)  # [chunk, H]
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)

    def run(bf16: bool):
        def f():
            with torch.inference_mode(), torch.autocast(device_type=dev.type, dtype=torch.bfloat16, enabled=bf16):
                deform._tail_raw(h)
            sync()

        return f

    return choose_mlp_precision(run(False), run(True), reps=reps, margin=margin)
