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
    parser.add_argument(
        "--view-blend-tau-deg", type=float, default=None, metavar="DEG",
        help="view blending of avatars built on a tracked head: weight each input view's Gaussians by exp(-angle difference / DEG); "
        "0 = off; default: FASTGHA_VIEW_BLEND_TAU_DEG, else the model's own (20); at most 360",
    )
    parser.add_argument("--no-warmup", action="store_true", help="skip the start-up warm-up")
    parser.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"], help="uvicorn and server log level (default info)")
    parser.add_argument("--proxy-headers", action="store_true", help="trust X-Forwarded-* from --forwarded-allow-ips (behind a reverse proxy)")
    parser.add_argument(
        "--forwarded-allow-ips", default=None,
        help="comma-separated proxy addresses whose X-Forwarded-* headers are trusted (default: FASTGHA_FORWARDED_ALLOW_IPS or 127.0.0.1)",
    )


def bind_listening_socket(host: str, port: int):
    """A socket bound to ``(host, port)``, made before the slow start-up so that a port in use is
    reported at once (uvicorn would only find out after loading, compiling and warming up).

    Raises ``CLIError`` with one line when the address is in use, not available on this machine, or
    the host does not resolve. IPv6 hosts are accepted (``::1``); the socket is handed to uvicorn."""
    import errno
    import socket

    from ..cli import CLIError

    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as e:
        raise CLIError(f"--host {host!r} does not resolve: {e.strerror}") from None
    family, _, _, _, addr = infos[0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn does: TIME_WAIT leftovers do not block
    if family == socket.AF_INET6:
        sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
    try:
        sock.bind(addr)
    except OSError as e:
        sock.close()
        if e.errno == errno.EADDRINUSE:
            raise CLIError(f"port {port} on {host} is already in use (another server?); stop it or choose another --port") from None
        if e.errno == errno.EACCES:
            raise CLIError(f"no permission to listen on port {port} (ports below 1024 need privileges); choose another --port") from None
        raise CLIError(f"cannot listen on {host}:{port}: {e.strerror}") from None
    sock.set_inheritable(True)
    return sock


def _settings_problems(error: Exception, overrides: dict) -> str:
    """One line per wrong setting of a pydantic ``ValidationError``, named as the user set it (the
    ``--flag`` when it came from the command line, else ``FASTGHA_<NAME>``), with the value given."""
    try:
        errors = error.errors()  # type: ignore[attr-defined]
    except (AttributeError, TypeError):
        return str(error).replace("\n", " ")
    parts = []
    for err in errors:
        field = str(err["loc"][0]) if err.get("loc") else ""
        where = f"--{field.replace('_', '-')}" if field in overrides else f"FASTGHA_{field.upper()}"
        msg = str(err.get("msg", "")).removeprefix("Value error, ")
        parts.append(f"{where}={err['input']!r}: {msg}" if "input" in err and not isinstance(err["input"], dict) else f"{where}: {msg}")
    return "; ".join(parts)


def _check_data_dir(path, named: str) -> None:
    """Create the data folder and write a probe file in it now: an unusable folder is reported in
    one line before the model loads, not as a start-up traceback tens of seconds later."""
    import os
    import tempfile
    from pathlib import Path

    from ..cli import CLIError

    folder = Path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".write-probe-", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise CLIError(
            f"{named} {str(folder)!r} cannot hold avatars ({type(e).__name__}: {e.strerror or e}); give a writable folder"
        ) from None


def _check_model_folder(model: str, named: str) -> None:
    """Read and validate a model folder's config.json now: a wrong field is reported in one line
    (the field and its allowed range, ``FastGHAConfig.validate``) before the slow start-up, not as a
    traceback from the server's start-up tens of seconds later. Preset names are left to the load."""
    from pathlib import Path

    from ..cli import CLIError
    from ..config import PRESETS

    if model in PRESETS:
        return
    if not Path(model).is_dir():
        raise CLIError(f"{named} must be one of {sorted(PRESETS)} or a model folder, got {model!r}")
    from ..model.fastgha import FastGHA

    try:
        FastGHA.read_config(model)
    except ValueError as e:
        raise CLIError(f"{named} {model!r}: {e}") from None


def run(args) -> int:
    import logging

    from ..cli import CLIError

    if not 0 < args.port < 65536:
        raise CLIError(f"--port must be in 1..65535, got {args.port}")
    # bind first: a port in use is reported now, not after the model load, compile and warm-up
    sock = bind_listening_socket(args.host, args.port)
    import uvicorn

    from server.app import create_app
    from server.settings import Settings

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
    if args.view_blend_tau_deg is not None:
        overrides["view_blend_tau_deg"] = args.view_blend_tau_deg
    if args.no_warmup:
        overrides["warmup"] = False
    try:
        settings = Settings(**overrides)
    except Exception as e:  # pydantic ValidationError: say which setting is wrong, in one line
        raise CLIError(f"invalid settings: {_settings_problems(e, overrides)}") from None
    _check_data_dir(settings.data_dir, "--data-dir" if "data_dir" in overrides else "FASTGHA_DATA_DIR")
    _check_model_folder(settings.model, "--model" if "model" in overrides else "FASTGHA_MODEL")
    if settings.device != "auto":
        from ..cli import check_device

        check_device(settings.device, "--device" if "device" in overrides else "FASTGHA_DEVICE")
    from server.security import uvicorn_options

    if args.proxy_headers and "*" in settings.forwarded_allow_ips.split(","):
        import sys

        print("warning: --forwarded-allow-ips '*' lets any client forge its address and scheme; name the proxy", file=sys.stderr)
    host = f"[{args.host}]" if ":" in args.host else args.host
    logging.getLogger("fastgha.serve").info(
        "starting on http://%s:%d; the port answers once the start-up below is done (tens of seconds)", host, args.port
    )
    app = create_app(settings)
    config = uvicorn.Config(
        app,
        log_level=args.log_level,
        proxy_headers=args.proxy_headers,
        forwarded_allow_ips=settings.forwarded_allow_ips,
        timeout_graceful_shutdown=10,
        **uvicorn_options(settings),  # connection deadlines and limits (server/security.py)
    )
    serve_announcing(config, sock, ready_url(args.host, args.port), demo=settings.resolved_static_dir() is not None)
    return 0


def ready_url(host: str, port: int) -> str:
    """Where a browser on this machine reaches a server bound to ``host``: its own address, or for
    the any-address ``0.0.0.0`` / ``::`` (containers), that and loopback's (a browser cannot open
    http://0.0.0.0/ everywhere)."""
    if host in ("0.0.0.0", "", "::"):
        loop = "127.0.0.1" if host != "::" else "[::1]"
        shown = "[::]" if host == "::" else "0.0.0.0"
        return f"http://{shown}:{port}/ (every interface; on this machine http://{loop}:{port}/)"
    return f"http://[{host}]:{port}/" if ":" in host else f"http://{host}:{port}/"


def serve_announcing(config, sock, url: str, demo: bool = True) -> None:
    """Run uvicorn (``config``) on the bound ``sock`` and log ``ready: answering at URL ...`` once it does:
    uvicorn logs no "running on" line for sockets handed to it (``bind_listening_socket`` binds
    before the slow start-up), so the log used to end at "Application startup complete." without
    the address to open. ``demo``: the browser demo is served at ``/``."""
    import logging

    import uvicorn

    class AnnouncingServer(uvicorn.Server):
        async def startup(self, sockets=None) -> None:
            await super().startup(sockets=sockets)
            if self.started and not self.should_exit:
                where = "browser demo at /, API docs at /docs" if demo else "API docs at /docs"
                logging.getLogger("fastgha.serve").info("ready: answering at %s; %s; Ctrl-C stops", url, where)

    AnnouncingServer(config).run(sockets=[sock])
