NAME = "serve"
HELP = "run the HTTP + WebSocket avatar server (uvicorn); settings from FASTGHA_* env, overridden by flags"


def add_arguments(parser) -> None:
    parser.add_argument("--host", default="127.0.0.1", help="interface to bind (default 127.0.0.1; 0.0.0.0 in containers)")
    parser.add_argument("--port", type=int, default=8000, help="TCP port (default 8000)")
    parser.add_argument("--model", default=None, help='"tiny", "paper" or a model folder (default: FASTGHA_MODEL or tiny)')
    parser.add_argument("--data-dir", default=None, help="where avatars are persisted (default: FASTGHA_DATA_DIR or ./fastgha-data)")
    parser.add_argument("--device", default=None, help='"auto", "cpu" or "cuda" (default: FASTGHA_DEVICE or auto)')
    parser.add_argument(
        "--api-keys-file", default=None,
        help="file of API keys for creating avatars, one per line (default: FASTGHA_API_KEYS_FILE); keeps them out of `ps`",
    )
    parser.add_argument(
        "--api-keys", default=None,
        help="comma-separated API keys (default: FASTGHA_API_KEYS); visible to every local user in `ps`: prefer --api-keys-file",
    )
    parser.add_argument("--no-warmup", action="store_true", help="skip the start-up warm-up")
    parser.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    parser.add_argument("--proxy-headers", action="store_true", help="trust X-Forwarded-* from --forwarded-allow-ips (behind a reverse proxy)")
    parser.add_argument(
        "--forwarded-allow-ips", default=None,
        help="comma-separated proxy addresses whose X-Forwarded-* headers are trusted (default: FASTGHA_FORWARDED_ALLOW_IPS or 127.0.0.1)",
    )


def run(args) -> int:
    import uvicorn

    from server.app import create_app
    from server.settings import Settings

    from ..cli import CLIError

    if not 0 < args.port < 65536:
        raise CLIError(f"--port must be in 1..65535, got {args.port}")
    if args.model is not None:
        from pathlib import Path

        from ..config import PRESETS

        if args.model not in PRESETS and not Path(args.model).is_dir():
            raise CLIError(f"--model must be one of {sorted(PRESETS)} or a model folder, got {args.model!r}")
    overrides = {}
    if args.model is not None:
        overrides["model"] = args.model
    if args.data_dir is not None:
        overrides["data_dir"] = args.data_dir
    if args.device is not None:
        overrides["device"] = args.device
    if args.api_keys is not None:
        overrides["api_keys"] = args.api_keys
        import sys

        print(
            "warning: API keys on the command line (--api-keys) are visible to every local user (ps, /proc); "
            "put them in a file readable only by this user and pass --api-keys-file PATH (or FASTGHA_API_KEYS_FILE)",
            file=sys.stderr,
        )
    if args.api_keys_file is not None:
        overrides["api_keys_file"] = args.api_keys_file
    if args.forwarded_allow_ips is not None:
        overrides["forwarded_allow_ips"] = args.forwarded_allow_ips
    if args.no_warmup:
        overrides["warmup"] = False
    try:
        settings = Settings(**overrides)
    except Exception as e:  # pydantic ValidationError: say which setting is wrong, in one line
        raise CLIError(f"invalid settings: {e}".replace("\n", " ")) from None
    from server.security import uvicorn_options

    if args.proxy_headers and "*" in settings.forwarded_allow_ips.split(","):
        import sys

        print("warning: --forwarded-allow-ips '*' lets any client forge its address and scheme; name the proxy", file=sys.stderr)
    app = create_app(settings)
    uvicorn.run(
        app,
        host=args.host,
        port=args.port,
        log_level=args.log_level,
        proxy_headers=args.proxy_headers,
        forwarded_allow_ips=settings.forwarded_allow_ips,
        timeout_graceful_shutdown=10,
        **uvicorn_options(settings),  # connection deadlines and limits (server/security.py)
    )
    return 0
