NAME = "track"
HELP = "track photos of one person (MediaPipe Face Mesh landmarks + one joint ICT head fit) into a request folder: crops, cameras.json, masks, expressions.json, head.json"
QUIET_NATIVE_LOGS = True  # MediaPipe's C++ start-up lines are dropped from stderr (fastgha_core/commands/_stderr.py)


def add_arguments(parser) -> None:
    parser.add_argument("--images", nargs="+", required=True, help="photos of ONE person (JPEG, PNG or any other format Pillow reads, e.g. WebP; the server takes JPEG and PNG); a mask <stem>_mask.png beside a photo is used")
    parser.add_argument("--out", required=True, help="request folder to write (created; the crops of an earlier track run into it are replaced; a folder holding other photos is refused)")
    parser.add_argument("--size", type=int, default=256, help="side of the square crops in pixels (default 256; the model's prepare() resizes)")
    parser.add_argument("--fov", type=float, default=30.0, help="assumed field of view across the longer photo side, degrees (default 30; "
                        "ignored when the photos carry an EXIF 35 mm-equivalent focal length)")
    parser.add_argument("--json", default=None, help="also write a tracking report (poses, landmark errors, expressions) here")


def _same_person(photos, names) -> None:
    """Refuse photos of different people, as the server does (``tracking/identity.py``: dlib face
    descriptors, photos without a frontal face not compared; nothing checked without dlib): one head
    is fitted to all photos, so a mixed set gives a head of nobody. ``CLIError`` naming the photos."""
    if len(photos) < 2:
        return
    from ..cli import CLIError
    from ..tracking.identity import DifferentPeopleError, IdentityChecker

    checker = IdentityChecker()
    if not checker.available:
        return
    try:
        checker.check(list(names), [checker.descriptor(p) for p in photos])
    except DifferentPeopleError as e:
        raise CLIError(f"{e} (fastgha track fits one head to all the photos)") from None


def _mask_beside(photo):
    """The path of ``photo``'s own mask, ``<stem>_mask.png`` beside it (``--images``' help)."""
    from pathlib import Path

    photo = Path(photo)
    return photo.with_name(photo.stem + "_mask.png")


def _earlier_run_files(out, sources) -> list:
    """Crops and masks an earlier ``fastgha track`` run wrote into ``out`` (listed in its
    expressions.json), to be replaced. ``CLIError`` when ``out`` holds other photos: ``reconstruct``
    takes every photo of a request folder as a view, so they would not match the new cameras.json."""
    import json
    from pathlib import Path

    from ..cameras import IMAGE_SUFFIXES
    from ..cli import CLIError

    out = Path(out)
    if not out.is_dir():
        return []
    listed: list[str] = []
    try:
        listed = [str(n) for n in json.loads((out / "expressions.json").read_text()).get("images", [])]
    except (OSError, ValueError, AttributeError):
        pass
    ours = set()
    for name in listed:
        stem = Path(name).stem
        ours |= {f"{stem}.png", f"{stem}_mask.png"}
    inputs = {p.resolve() for p in sources if p.exists()}
    inputs |= {_mask_beside(p).resolve() for p in sources}
    others = sorted(
        p.name for p in out.iterdir()
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and (p.name not in ours or p.resolve() in inputs)
    )  # fmt: skip
    if others:
        given = [n for n in others if (out / n).resolve() in inputs]
        why = "the photos to track are in it" if given else "they are not crops of an earlier `fastgha track` run"
        raise CLIError(
            f"--out {out} already holds photos ({', '.join(others[:3])}{', ...' if len(others) > 3 else ''}; {why}): "
            "`fastgha reconstruct` would take them as views; give an empty or new folder"
        )
    return [out / n for n in sorted(ours) if (out / n).is_file()]


def _without_their_masks(paths: list) -> list:
    """``paths`` without the files named ``<stem>_mask.png`` of another path's photo ``<stem>.<ext>``
    (beside it): those are that photo's mask (``--images``' help), which a shell glob such as
    ``folder/*.png`` picks up with the photos. A ``*_mask.png`` whose photo is not given stays."""
    from pathlib import Path

    masks_of_given = {_mask_beside(p) for p in paths}
    return [p for p in paths if Path(p) not in masks_of_given]


def run(args) -> int:
    import json
    import logging
    import sys
    from pathlib import Path

    import numpy as np
    from PIL import Image

    from ..cameras import cameras_to_json
    from ..cli import CLIError
    from ..expressions import ICT53_NAMES
    from ..images import ImageDecodeError, read_image, read_mask
    from ..tracking import TrackConfig, track_photos
    from ..tracking.faces import FacesUnavailableError

    log = logging.getLogger(__name__)
    if args.size < 16:
        raise CLIError(f"--size must be at least 16, got {args.size}")
    if not 1 <= args.fov <= 150:
        raise CLIError(f"--fov must be in [1, 150] degrees, got {args.fov}")
    from ._paths import output_dir, output_file

    out = output_dir(args.out, "--out")
    if args.json:
        output_file(args.json, "--json")
    given = [Path(n) for n in args.images]
    images = _without_their_masks(given)
    if len(images) < len(given):  # `--images folder/*.png` also matches the masks beside the photos
        skipped = [str(p) for p in given if p not in images]
        print(f"not tracked (the mask of a photo given with it, used as that photo's mask): {', '.join(skipped)}", file=sys.stderr, flush=True)
    earlier = _earlier_run_files(out, images)
    photos, masks, names, focals = [], [], [], []
    for p in images:
        if p.is_dir():
            raise CLIError(f"--images {p} is a folder; give the photo files (e.g. {p}/*.jpg)")
        if not p.is_file():
            raise CLIError(f"{p} does not exist")
        mp = _mask_beside(p)
        try:  # upright (EXIF orientation applied) 8-bit pixels whatever the file's mode
            decoded = read_image(p)
            masks.append(read_mask(mp) if mp.is_file() else None)
        except ImageDecodeError as e:
            raise CLIError(str(e)) from None
        photos.append(decoded.rgb)
        focals.append(decoded.exif_focal_35mm)
        names.append(str(p))
    _same_person(photos, names)

    print(f"tracking {len(names)} photo(s): finding the face and landmarks, fitting one head ...", file=sys.stderr, flush=True)
    try:
        res = track_photos(photos, TrackConfig(size=args.size, fov_deg=args.fov), masks=masks, names=names, focal_35mm=focals)
    except FacesUnavailableError as e:
        raise CLIError(str(e)) from None
    except ValueError as e:  # NoFaceError, SeveralFacesError, TinyFaceError, a photo that cannot be placed
        raise CLIError(str(e)) from None
    out.mkdir(parents=True, exist_ok=True)
    stems = [f"{i:02d}_{Path(n).stem}" for i, n in enumerate(names)]
    written = {f"{s}{suffix}" for s in stems for suffix in (".png", "_mask.png")}
    stale = sorted(p for p in earlier if p.name not in written)
    for p in stale:  # crops of an earlier run into this folder: reconstruct would take them as views
        p.unlink(missing_ok=True)
    if stale:
        log.info("removed %d file(s) an earlier `fastgha track` run wrote into %s", len(stale), out)
    for i, stem in enumerate(stems):
        Image.fromarray(res.crops[i]).save(out / f"{stem}.png")
        Image.fromarray(np.round(res.masks[i] * 255).astype(np.uint8)).save(out / f"{stem}_mask.png")
    (out / "cameras.json").write_text(json.dumps(cameras_to_json(res.cameras)))
    expr = {"space": "ict53", "names": list(ICT53_NAMES), "images": [f"{s}.png" for s in stems], "expressions": res.expressions.round(4).tolist()}
    (out / "expressions.json").write_text(json.dumps(expr))
    # the tracked head (shared identity): `fastgha reconstruct` puts every pixel's Gaussian on it
    # and each crop's photo (its padding is not background: HeadSurface.frames)
    from ..model.surface import HeadSurface

    frames = HeadSurface.from_tracking(res).frames
    head = {"model": "ict_facekit", "identity": res.fit.identity.round(5).tolist(), "frames": {f"{s}.png": frames[i].round(5).tolist() for i, s in enumerate(stems)}}
    (out / "head.json").write_text(json.dumps(head))
    if args.json:
        from ..tracking.realsets import head_angles_deg

        report = {
            "images": names,
            "landmarks": res.layout,
            "focal_px": [float(res.fit.K[i][0, 0]) for i in range(len(names))],
            "focal_source": "exif_35mm" if any(f is not None for f in focals) else f"default fov {args.fov} deg",
            "identity": res.fit.identity.round(4).tolist(),
            "photos": [
                {
                    "image": names[i],
                    "crop": f"{stems[i]}.png",
                    "landmark_rms_px": float(res.fit.rms_px[i]),
                    "landmark_residuals_px": np.linalg.norm(res.residuals[i], axis=1).round(2).tolist(),
                    "yaw_pitch_roll_deg": [round(a, 2) for a in head_angles_deg(res.fit.rotations[i])],
                    "head_rotation": res.fit.rotations[i].tolist(),
                    "head_translation_m": res.fit.translations[i].tolist(),
                    "K_photo": res.fit.K[i].tolist(),
                    "mask": "given" if res.mask_given[i] else "estimated",
                    "expression": res.expressions[i].round(4).tolist(),
                }
                for i in range(len(names))
            ],
        }
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(report, indent=1))
    log.info("tracked %d photo(s)", len(names))
    print(f"wrote {out}: {len(names)} crop(s) {args.size}x{args.size} + masks, cameras.json, expressions.json, head.json")
    if args.json:
        print(f"wrote the tracking report to {args.json}")
    return 0
