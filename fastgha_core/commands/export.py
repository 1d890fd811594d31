NAME = "export"
HELP = "export an avatar file (.safetensors) as a 3DGS PLY for SuperSplat, gsplat or three.js viewers"


def add_arguments(parser) -> None:
    parser.add_argument("--avatar", required=True, help="avatar file written by `fastgha reconstruct` (.safetensors)")
    parser.add_argument(
        "--ply",
        required=True,
        help="output PLY path (standard 3DGS layout, SH degree 0; static: the neutral Gaussians with "
        "unweighted opacities, without the per-frame view blending of the server and `fastgha animate`)",
    )
    parser.add_argument(
        "--min-opacity", type=float, default=0.0, help="drop Gaussians with opacity below this value (default: keep all)"
    )
    parser.add_argument(
        "--axes",
        choices=["colmap", "fastgha"],
        default="colmap",
        help="axis convention of the file: colmap (default; y down like standard 3DGS scenes, shown upright by "
        "SuperSplat/PlayCanvas viewers) or fastgha (our head-centric world: +y up, +z out of the face)",
    )
    parser.add_argument(
        "--keep-outliers", action="store_true", help="keep stray Gaussians far from the head (default: drop them)"
    )
    parser.add_argument(
        "--viewer-settings",
        default=None,
        help="also write a SuperSplat viewer settings.json whose camera frames the head from the front "
        "(use with `splat-transform out.ply out.html --viewer-settings FILE`)",
    )


def run(args) -> int:
    import json
    from pathlib import Path

    from ..cli import CLIError
    from ..io import drop_outliers, load_avatar_file, save_ply, viewer_settings

    src, dst = Path(args.avatar), Path(args.ply)
    if not src.is_file():
        raise CLIError(f"avatar file {src} does not exist")
    if dst.suffix.lower() != ".ply":
        raise CLIError(f"--ply must name a .ply file, got {dst}")
    from ._paths import output_file

    output_file(dst, "--ply")
    if not 0.0 <= args.min_opacity <= 1.0:
        raise CLIError(f"--min-opacity must lie in [0, 1], got {args.min_opacity}")
    g, meta, extra = load_avatar_file(src)
    n_in = len(g)
    faint = ""
    if args.min_opacity > 0:
        g = g.prune(args.min_opacity)
        faint = f"{n_in - len(g)} below --min-opacity {args.min_opacity:g}, "
    dropped = 0
    if not args.keep_outliers:
        g, dropped = drop_outliers(g)
    save_ply(dst, g, axes=args.axes, outliers=False)
    print(
        f"wrote {dst}: {len(g)} Gaussians (of {n_in}; {faint}{dropped} stray dropped), axes {args.axes}, from model "
        f"{meta.get('model_name', '?')!r}, expression space {meta.get('expression_space', '?')!r}"
    )
    views = int(extra["view.dirs"].shape[0]) if "view.dirs" in extra else 0
    if views == 1:  # one view: every blend weight is 1, the frames hold these opacities too
        print("note: this avatar has one input view, so its frames are not view-blended; the PLY is what they show at neutral")
    elif "view.source" in extra:
        print(
            "note: this avatar is view-blended per frame (server, `fastgha animate`); the PLY holds its "
            "unweighted opacities, so a viewer shows every input view's Gaussians at once (docs/model.md)"
        )
    if args.viewer_settings:
        vs = Path(args.viewer_settings)
        vs.parent.mkdir(parents=True, exist_ok=True)
        vs.write_text(json.dumps(viewer_settings(g, axes=args.axes), indent=1))
        print(f"wrote {vs}: view with `npx @playcanvas/splat-transform {dst} {dst.with_suffix('.html')} --viewer-settings {vs}`")
    return 0
