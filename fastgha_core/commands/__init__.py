"""One module per ``fastgha`` subcommand (see ``fastgha_core.cli``)."""


def loading(model: str) -> None:
    """Say on stderr that the model is loading: the first load imports the encoders (transformers,
    diffusers) and takes several seconds on a CPU, with nothing else on screen."""
    import sys

    print(f"loading model {str(model)!r} ...", file=sys.stderr, flush=True)


def rasterizer_cache_cold() -> bool:
    """True when numba's on-disk cache holds no compiled copy of the CPU rasterizer's main kernel
    (``render/cpu_kernels.py``, ``cache=True``: compiled on first use, then loaded from the index file
    numba keeps beside the module or in ``NUMBA_CACHE_DIR``). False when it is there, or when this numba
    does not expose where (its cache object is numba's internal ``FunctionCache``)."""
    import os

    from ..render import cpu_kernels

    try:
        index = cpu_kernels.raster_forward_fast._cache._cache_file._index_path
    except AttributeError:
        return False
    return not os.path.exists(index)


def note_first_compilation(device: str) -> None:
    """Say on stderr that this run compiles the CPU rasterizer's kernels (the first run after an
    installation: 10-30 s more on 2 cores, once; later runs load them from numba's cache), so that the
    pause is explained. Silent on CUDA devices (gsplat) and when the cache is filled."""
    import sys

    if str(device).startswith("cuda") or not rasterizer_cache_cold():
        return
    print("first run: numba compiles the CPU rasterizer's kernels once (10-30 s; later runs load them from its cache) ...",
          file=sys.stderr, flush=True)


def check_model_has_weights(spec: str) -> None:
    """Refuse a preset name without shipped weights (``paper``): it would build a randomly initialised
    network (minutes and gigabytes for ``paper``) only to reconstruct or render noise. Model folders
    and shipped presets pass. Raises ``ValueError`` naming the presets that ship weights."""
    from ..config import PRESETS
    from ..model.fastgha import ASSET_MODELS_DIR, CONFIG_NAME, WEIGHTS_NAME

    shipped = sorted(n for n in PRESETS if (ASSET_MODELS_DIR / n / CONFIG_NAME).is_file() and (ASSET_MODELS_DIR / n / WEIGHTS_NAME).is_file())
    if spec in PRESETS and spec not in shipped:
        raise ValueError(
            f"--model {spec!r}: no shipped weights for this preset (shipped: {', '.join(shipped) or 'none'}); "
            "give a trained model folder instead (`fastgha train ... --out RUN` writes RUN/model)"
        )


#: Largest view-blending tau (degrees) the commands and the server accept: angles between cameras are at most
#: 180 degrees, so beyond this every weight is above exp(-1/2) and the value only hides a typo (0 turns blending off).
MAX_VIEW_BLEND_TAU_DEG = 360.0

#: Most test-time refinement steps the commands and the server accept (the defaults are 30-60 steps,
#: a few seconds on 2 cores; 1000 steps take minutes, beyond that the value is most likely a typo).
MAX_REFINE_STEPS = 1000


def view_blend_tau_problem(value: float) -> str | None:
    """Why ``value`` is not a view-blending tau (``model/viewblend.py``: 0 = off, else degrees in
    (0, MAX_VIEW_BLEND_TAU_DEG]), or None when it is one. NaN and infinities are refused."""
    import math

    if math.isfinite(value) and 0.0 <= value <= MAX_VIEW_BLEND_TAU_DEG:
        return None
    return f"view_blend_tau_deg must be 0 (off) or a number of degrees in (0, {MAX_VIEW_BLEND_TAU_DEG:g}], got {value!r}"
