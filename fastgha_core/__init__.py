"""FastGHA core library: cameras, Gaussians, expression spaces, the reconstruction model, the
rasterizer, data, training and evaluation. No web code lives here."""

__version__ = "0.1.0"

# torch (libgomp bundled) and numba (system OpenMP) run two thread pools on the same cores; with
# spinning idle threads they starve each other (frames up to ~9x slower). Must run before torch loads.
from . import perf as _perf  # noqa: E402

_perf.apply_env_defaults()

from .cameras import Cameras  # noqa: E402
from .gaussians import Gaussians  # noqa: E402

__all__ = ["Cameras", "Gaussians", "__version__"]


def __getattr__(name: str):
    # Heavy entry points are imported lazily so that `fastgha --help` stays fast.
    if name == "load_model":
        from .model.fastgha import load_model

        return load_model
    raise AttributeError(f"module 'fastgha_core' has no attribute {name!r}")
