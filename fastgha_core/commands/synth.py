"""``fastgha synth``: write synthetic subjects in our dataset layout, plus a request folder each."""

NAME = "synth"
HELP = "render synthetic multi-view head captures (ICT-FaceKit) into the dataset layout"


def add_arguments(parser) -> None:
    parser.add_argument("--out", required=True, help="output dataset root (a subject folder an earlier synth run wrote there is replaced; any other folder of that name is refused)")
    parser.add_argument("--subjects", type=int, default=4, help="number of subjects (default 4)")
    parser.add_argument("--timesteps", type=int, default=32, help="timesteps per sequence (default 32)")
    parser.add_argument("--cameras", type=int, default=16, help="cameras per subject (default 16)")
    parser.add_argument("--resolution", type=int, default=256, help="image side in pixels (default 256)")
    parser.add_argument(
        "--seed", type=int, default=None,
        help="seed of the first subject; subject i has seed SEED+i (default: start of the train or held-out range)",
    )
    parser.add_argument("--heldout", action="store_true", help="draw subjects from the held-out seed range")
    parser.add_argument("--image-format", choices=("png", "jpg"), default="png", help="image files (default png)")
    parser.add_argument("--jpeg-quality", type=int, default=95, help="JPEG quality when --image-format jpg (default 95)")
    parser.add_argument("--no-depth", action="store_true", help="do not write depth maps")
    parser.add_argument(
        "--request-views", type=int, default=None,
        help="photos in each subject's request folder (default min(4, timesteps, cameras); 0 = none)",
    )


def run(args) -> int:
    import logging

    from tqdm import tqdm

    from ..cli import CLIError
    from ..data.synth_writer import synth_dataset
    from ..data.synthetic import HELDOUT_SEEDS, TRAIN_SEEDS

    seeds_range = HELDOUT_SEEDS if args.heldout else TRAIN_SEEDS
    first = seeds_range.start if args.seed is None else int(args.seed)
    for name, value, lo in (("--subjects", args.subjects, 1), ("--timesteps", args.timesteps, 1), ("--cameras", args.cameras, 1), ("--resolution", args.resolution, 32)):
        if value < lo:
            raise CLIError(f"{name} must be >= {lo}, got {value}")
    if args.request_views is None:
        args.request_views = min(4, args.timesteps, args.cameras)
    if not 0 <= args.request_views <= min(args.timesteps, args.cameras):
        raise CLIError(f"--request-views must be in [0, min(timesteps, cameras)] = [0, {min(args.timesteps, args.cameras)}], got {args.request_views}")
    last = first + args.subjects - 1
    if first not in seeds_range or last not in seeds_range:
        which = "held-out" if args.heldout else "training"
        raise CLIError(
            f"seeds {first}..{last} leave the {which} range [{seeds_range.start}, {seeds_range.stop}); "
            + ("drop --heldout or " if args.heldout else "use --heldout for evaluation seeds, or ")
            + "choose another --seed"
        )
    from ._paths import output_dir

    output_dir(args.out, "--out")
    total = args.subjects * args.timesteps * args.cameras
    with tqdm(total=total, unit="img", desc="synth") as bar:
        folders = synth_dataset(
            args.out,
            range(first, last + 1),
            timesteps=args.timesteps,
            num_cameras=args.cameras,
            resolution=args.resolution,
            image_format=args.image_format,
            jpeg_quality=args.jpeg_quality,
            depth=not args.no_depth,
            request_views=args.request_views,
            progress=bar.update,
        )
    logging.getLogger(__name__).info("wrote %d subjects to %s", len(folders), args.out)
    return 0
