NAME = "track"
HELP = "track photos of one person (MediaPipe Face Mesh landmarks + one joint ICT head fit) into a request folder: crops, cameras.json, masks, expressions.json"


def add_arguments(parser) -> None:
    parser.add_argument("--images", nargs="+", required=True, help="photos of ONE person (PNG/JPEG); a mask <stem>_mask.png beside a photo is used")
    parser.add_argument("--out", required=True, help="request folder to write (created; existing files of the same names are replaced)")
    parser.add_argument("--size", type=int, default=256, help="side of the square crops in pixels (default 256; the model's prepare() resizes)")
    parser.add_argument("--fov", type=float, default=30.0, help="assumed field of view across the longer photo side, degrees (default 30; "
                        "ignored when the photos carry an EXIF 35 mm-equivalent focal length)")
    parser.add_argument("--json", default=None, help="also write a tracking report (poses, landmark errors, expressions) here")


def _read_upright(path):
    """``(rgb [H, W, 3] uint8 upright, EXIF 35 mm-equivalent focal or None)``.

    Until ``fastgha_core.images`` (the project's one decoder) lands, this is the one place the
    track command decodes photos: PIL with ``ImageOps.exif_transpose`` (EXIF orientation applied,
    so K refers to the upright image).
    """
    import numpy as np
    from PIL import Image, ImageOps

    try:
        from ..images import read_image  # type: ignore

        d = read_image(path, max_pixels=64_000_000)
        return d.rgb, d.exif_focal_35mm
    except ImportError:
        pass
    with Image.open(path) as im:
        f35 = im.getexif().get_ifd(0x8769).get(0xA405)  # Exif IFD: FocalLengthIn35mmFilm
        rgb = np.asarray(ImageOps.exif_transpose(im).convert("RGB"))
    return rgb, (float(f35) if f35 else None)


def run(args) -> int:
    import json
    import logging
    from pathlib import Path

    import numpy as np
    from PIL import Image, UnidentifiedImageError

    from ..cameras import cameras_to_json
    from ..cli import CLIError
    from ..expressions import ICT53_NAMES
    from ..tracking import TrackConfig, track_photos
    from ..tracking.faces import FacesUnavailableError

    log = logging.getLogger(__name__)
    if args.size < 16:
        raise CLIError(f"--size must be at least 16, got {args.size}")
    photos, masks, names, focals = [], [], [], []
    for p in map(Path, args.images):
        if not p.is_file():
            raise CLIError(f"{p} does not exist")
        try:
            rgb, f35 = _read_upright(p)
        except (UnidentifiedImageError, OSError) as e:
            raise CLIError(f"{p} is not an image file PIL can read ({type(e).__name__}: {e})") from None
        except ValueError as e:  # fastgha_core.images.ImageDecodeError (too large, unsupported mode)
            raise CLIError(f"{p}: {e}") from None
        photos.append(rgb)
        focals.append(f35)
        mp = p.with_name(p.stem + "_mask.png")
        masks.append(np.asarray(Image.open(mp).convert("L")) if mp.is_file() else None)
        names.append(str(p))
    try:
        res = track_photos(photos, TrackConfig(size=args.size, fov_deg=args.fov), masks=masks, names=names, focal_35mm=focals)
    except FacesUnavailableError as e:
        raise CLIError(str(e)) from None
    except ValueError as e:  # NoFaceError, SeveralFacesError, TinyFaceError, a photo that cannot be placed
        raise CLIError(str(e)) from None
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stems = [f"{i:02d}_{Path(n).stem}" for i, n in enumerate(names)]
    for i, stem in enumerate(stems):
        Image.fromarray(res.crops[i]).save(out / f"{stem}.png")
        Image.fromarray(np.round(res.masks[i] * 255).astype(np.uint8)).save(out / f"{stem}_mask.png")
    (out / "cameras.json").write_text(json.dumps(cameras_to_json(res.cameras)))
    expr = {"space": "ict53", "names": list(ICT53_NAMES), "images": [f"{s}.png" for s in stems], "expressions": res.expressions.round(4).tolist()}
    (out / "expressions.json").write_text(json.dumps(expr))
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
        Path(args.json).write_text(json.dumps(report, indent=1))
    log.info("tracked %d photo(s)", len(names))
    print(f"wrote {out}: {len(names)} crop(s) {args.size}x{args.size} + masks, cameras.json, expressions.json")
    return 0
