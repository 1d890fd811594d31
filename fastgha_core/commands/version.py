NAME = "version"
HELP = "print the FastGHA version and the versions of its key dependencies"


def add_arguments(parser) -> None:
    parser.add_argument("--all", action="store_true", help="also print torch, numba and python versions")


def run(args) -> int:
    from .. import __version__

    print(f"fastgha {__version__}")
    if args.all:
        import platform

        import numba
        import torch

        print(f"python {platform.python_version()}  torch {torch.__version__}  numba {numba.__version__}")
    return 0
