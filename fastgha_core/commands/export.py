NAME = "export"
HELP = "export an avatar file (.safetensors) as a 3DGS PLY for SuperSplat, gsplat or three.js viewers"


def add_arguments(parser) -> None:
    parser.add_argument("--avatar", required=True, help="avatar file written by `fastgha reconstruct` (.safetensors)")
    parser.add_argument("--ply", required=True, help="output PLY path (standard 3DGS layout, SH degree 0)")
    parser.add_argument(
        "--min-opacity", type=float, default=0.0, help="drop Gaussians with opacity below this value (default: keep all)"
    )


def run(args) -> int:
    from pathlib import Path

    from ..cli import CLIError
    from ..io import load_avatar_file, save_ply

    src, dst = Path(args.avatar), Path(args.ply)
    if not src.is_file():
        raise CLIError(f"avatar file {src} does not exist")
    if dst.suffix.lower() != ".ply":
        raise CLIError(f"--ply must name a .ply file, got {dst}")
    if not 0.0 <= args.min_opacity <= 1.0:
        raise CLIError(f"--min-opacity must lie in [0, 1], got {args.min_opacity}")
    g, meta, _ = load_avatar_file(src)
    n_in = len(g)
    if args.min_opacity > 0:
        g = g.prune(args.min_opacity)
    save_ply(dst, g)
    print(
        f"wrote {dst}: {len(g)} Gaussians (of {n_in}) from model {meta.get('model_name', '?')!r}, "
        f"expression space {meta.get('expression_space', '?')!r}"
    )
    return 0
