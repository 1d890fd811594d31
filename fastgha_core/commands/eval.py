NAME = "eval"
HELP = "evaluate a model on held-out subjects: PSNR, SSIM, LPIPS, CSIM, AKD (paper §4.4 protocol)"


def add_arguments(parser) -> None:
    parser.add_argument("--model", default="tiny", help="preset name (shipped weights) or a model folder (save_pretrained / a checkpoint); default tiny")
    parser.add_argument("--data", default="synthetic-heldout", help="'synthetic-heldout' or a dataset folder of held-out subjects")
    parser.add_argument("--subjects", type=int, default=None, help="evaluate the first N subjects (synthetic default: 4)")
    parser.add_argument("--first-seed", type=int, default=None, help="synthetic held-out data: start at this seed instead of 1000000 (held-out seeds are 1000000-1009999)")
    parser.add_argument("--json", default=None, help="write the report JSON here (default: OUT/eval.json)")
    parser.add_argument("--out", default="eval_out", help="folder for eval.md, comparison.png (and eval.json); default ./eval_out")
    parser.add_argument("--ablation", default="none", choices=["none", "static", "no-features", "no-prior"], help="none (default): the full model; static: canonical head, no deformation; no-features: deformation with zeroed per-Gaussian features; no-prior: the MLP residual without the expression prior's displacement")
    parser.add_argument("--grid-subject", type=int, default=0, help="with --responses: which subject (index) the picture grid shows")
    parser.add_argument("--responses", action="store_true", help="instead: the expression-response evaluation (single expressions at weight 1, frontal and 30° yaw, dlib landmarks ours vs truth, mouth/eye PSNR); writes OUT/responses.{json,md,png}")
    parser.add_argument("--num-inputs", type=int, default=4, help="input images per subject (default and paper: 4)")
    parser.add_argument("--expressions", type=int, default=4, help="novel expressions per subject (default 4)")
    parser.add_argument("--views", type=int, default=4, help="novel views per expression (default 4)")
    parser.add_argument("--vgg-weights", default=None, help="torchvision VGG16 weights, for LPIPS (with --lpips-weights)")
    parser.add_argument("--lpips-weights", default=None, help="LPIPS linear heads (lpips/weights/v0.1/vgg.pth), for LPIPS (with --vgg-weights)")
    parser.add_argument("--no-faces", action="store_true", help="skip CSIM/AKD even when dlib is installed")
    parser.add_argument("--refine-steps", type=int, default=0, help="test-time refinement steps against the inputs before rendering the targets (0 = off)")
    parser.add_argument("--refine-cameras", action="store_true", help="with --refine-steps: also learn per-view camera corrections (off: the dataset's cameras are exact)")
    parser.add_argument("--surface", default="none", choices=["tracked", "blend", "none"], help="input depth. none (default): the network's per-pixel depth (blend reads within 0.2 dB of it on held-out subjects, tracked 1.5 dB below; docs/model-card.md, \"Held-out results\"); tracked: every input pixel's Gaussian on the head fitted to the input photos through their known cameras (faces extra; falls back to the network's depth per subject, counted in the report); blend: that head on the face only")
    parser.add_argument("--resolution", type=int, default=0, help="side of the target images in pixels (default: the model's render size); inputs are always resized to the model's input size")
    parser.add_argument("--device", default="cpu", help="torch device (default cpu)")
    parser.add_argument("--backend", default="auto", help="rasterizer backend (default auto: gsplat on CUDA, else the CPU rasterizer)")


def run(args) -> int:
    import logging

    from ..cli import CLIError
    from ..model.fastgha import load_model
    from ..train.builders import build_eval_sources, check_expression_space
    from ..train.evaluate import EvalConfig, evaluate, write_report

    log = logging.getLogger(__name__)
    for flag, value, least in (("--subjects", args.subjects, 1), ("--num-inputs", args.num_inputs, 1), ("--expressions", args.expressions, 1),
                               ("--views", args.views, 1), ("--refine-steps", args.refine_steps, 0), ("--grid-subject", args.grid_subject, 0)):  # fmt: skip
        if value is not None and value < least:
            raise CLIError(f"{flag} must be >= {least}, got {value}")
    if args.resolution < 0:
        raise CLIError(f"--resolution must be positive (or 0 for the model's render size), got {args.resolution}")
    if bool(args.vgg_weights) != bool(args.lpips_weights):
        raise CLIError("LPIPS needs both --vgg-weights and --lpips-weights (got only one)")
    from ..cli import check_device
    from ._paths import output_dir, output_file

    output_dir(args.out, "--out")
    if args.json:
        output_file(args.json, "--json")
    check_device(args.device)
    from . import check_model_has_weights

    check_model_has_weights(args.model)
    model = load_model(args.model, device=args.device)
    if args.responses:
        return _run_responses(args, model)
    lpips = None
    if args.vgg_weights:
        from ..train.lpips import load_lpips

        lpips = load_lpips(args.vgg_weights, args.lpips_weights, args.device)
    else:
        log.warning("LPIPS unavailable: give --vgg-weights and --lpips-weights; it is reported as null")
    faces = None
    if not args.no_faces:
        from ..train.faces import load_face_metrics

        faces = load_face_metrics()
    cfg = EvalConfig(num_inputs=args.num_inputs, num_target_timesteps=args.expressions, num_target_views=args.views, ablation=args.ablation, backend=args.backend, resolution=args.resolution, refine_steps=args.refine_steps, refine_cameras=args.refine_cameras, surface=args.surface)
    res = args.resolution or int(model.config.render_size)
    sources = build_eval_sources(args.data, args.subjects, resolution=max(res, int(model.config.input_size)), num_cameras=max(16, args.num_inputs + args.views), first_seed=args.first_seed)
    check_expression_space(sources, model.config.expression_space, args.data)
    report = evaluate(model, sources, cfg, lpips=lpips, faces=faces, out_dir=args.out)
    report["model"] = str(args.model)
    report["data"] = str(args.data)
    md = write_report(report, args.json, args.out)
    print(md)
    print(f"wrote {args.json or args.out + '/eval.json'}, {args.out}/eval.md, {args.out}/comparison.png")
    return 0


def _run_responses(args, model) -> int:
    import json
    from pathlib import Path

    from ..cli import CLIError
    from ..train.builders import build_eval_sources, check_expression_space
    from ..train.responses import ResponseConfig, evaluate_responses, responses_markdown

    if args.ablation not in ("none", "no-prior"):
        raise CLIError(f"--responses supports --ablation none or no-prior, got {args.ablation}")
    try:
        import dlib  # type: ignore  # noqa: F401
    except ImportError:
        raise CLIError("--responses needs dlib's 68 landmarks: install the 'faces' extra") from None
    res = args.resolution or 256
    cfg = ResponseConfig(resolution=res, num_inputs=args.num_inputs, use_prior=args.ablation != "no-prior", backend=args.backend, grid_subject=args.grid_subject)
    sources = build_eval_sources(args.data, args.subjects, resolution=int(model.config.input_size), num_cameras=16, first_seed=args.first_seed)
    check_expression_space(sources, model.config.expression_space, args.data)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = evaluate_responses(model, sources, cfg, out_dir=out)
    report["model"], report["data"], report["ablation"] = str(args.model), str(args.data), args.ablation
    report_path = Path(args.json) if args.json else out / "responses.json"
    report_path.parent.mkdir(parents=True, exist_ok=True)
    report_path.write_text(json.dumps(report, indent=2))
    md = responses_markdown(report)
    (out / "responses.md").write_text(md)
    print(md)
    print(f"wrote {args.json or str(out / 'responses.json')}, {out}/responses.md, {out}/responses.png")
    return 0
