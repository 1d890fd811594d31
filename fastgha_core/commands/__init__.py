"""One module per ``fastgha`` subcommand (see ``fastgha_core.cli``)."""


def loading(model: str) -> None:
    """Say on stderr that the model is loading: the first load imports the encoders (transformers,
    diffusers) and takes several seconds on a CPU, with nothing else on screen."""
    import sys

    print(f"loading model {str(model)!r} ...", file=sys.stderr, flush=True)
