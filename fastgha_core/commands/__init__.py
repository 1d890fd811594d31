"""One module per ``fastgha`` subcommand (see ``fastgha_core.cli``)."""


def loading(model: str) -> None:
    """Say on stderr that the model is loading: the first load imports the encoders (transformers,
    diffusers) and takes several seconds on a CPU, with nothing else on screen."""
    import sys

    print(f"loading model {str(model)!r} ...", file=sys.stderr, flush=True)


#: Largest view-blending tau (degrees) the commands and the server accept: angles between cameras are at most
#: 180 degrees, so beyond this every weight is above exp(-1/2) and the value only hides a typo (0 turns blending off).
MAX_VIEW_BLEND_TAU_DEG = 360.0


def view_blend_tau_problem(value: float) -> str | None:
    """Why ``value`` is not a view-blending tau (``model/viewblend.py``: 0 = off, else degrees in
    (0, MAX_VIEW_BLEND_TAU_DEG]), or None when it is one. NaN and infinities are refused."""
    import math

    if math.isfinite(value) and 0.0 <= value <= MAX_VIEW_BLEND_TAU_DEG:
        return None
    return f"view_blend_tau_deg must be 0 (off) or a number of degrees in (0, {MAX_VIEW_BLEND_TAU_DEG:g}], got {value!r}"
