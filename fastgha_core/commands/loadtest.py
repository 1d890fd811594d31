"""``fastgha loadtest``: N concurrent WebSocket streams against a server; delivered FPS, drops, latency."""

NAME = "loadtest"
HELP = "load-test a running server: N concurrent streams at a target rate; JSON report and PNG plot (loopback only by default)"


def add_arguments(parser) -> None:
    parser.add_argument("--url", default="http://127.0.0.1:8000", help="server base URL (default http://127.0.0.1:8000)")
    parser.add_argument("--clients", type=int, default=4, help="concurrent WebSocket sessions (1..256, default 4)")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds each client sends requests (<= 3600, default 10)")
    parser.add_argument("--rate", type=float, default=30.0, help="requests per second per client (<= 240, default 30)")
    parser.add_argument("--size", type=int, default=256, help="frame width and height (default 256)")
    parser.add_argument("--shared-avatar", action="store_true", help="all clients stream one avatar (the server caps streams per avatar)")
    parser.add_argument("--input", default=None, help="request folder for the avatar(s) (default: the first shipped sample)")
    parser.add_argument("--json", default=None, help="write the JSON report here")
    parser.add_argument("--plot", default=None, help="write a PNG plot of FPS and latency over time here")
    parser.add_argument("--allow-remote", action="store_true", help="allow a host other than loopback (only servers you own)")
    parser.add_argument("--api-key", default=None, help="API key for creating avatars (default: $FASTGHA_API_KEY, else the first of $FASTGHA_API_KEYS)")
    parser.add_argument("--jpeg-quality", type=int, default=None, help="per-stream JPEG quality (default: the server's)")
    parser.add_argument("--closed-loop", action="store_true",
                        help="one request in flight per stream, the next sent when its frame is back (as the browser demo; at most --rate)")


def _default_request_dir():
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent / "assets" / "samples"
    found = sorted(p for p in root.glob("*/request") if (p / "cameras.json").is_file()) if root.is_dir() else []
    return found[0] if found else None


def _summary(report: dict) -> str:
    agg = report["aggregate"]
    lat = agg["latency_ms"]
    fmt = lambda v: "-" if v is None else f"{v:.1f}"  # noqa: E731
    lines = [
        f"{'client':>6} {'sent':>7} {'frames':>7} {'dropped':>7} {'fps':>7} {'p50 ms':>8} {'p95 ms':>8} {'p99 ms':>8} "
        f"{'srv p50':>8} {'kB/s':>8} {'errors':>6}"
    ]
    for c in report["clients"]:
        cl = c["latency_ms"]
        lines.append(
            f"{c['client']:>6} {c['requests_sent']:>7} {c['frames_received']:>7} {c['dropped_requests']:>7} {c['delivered_fps']:>7.1f} "
            f"{fmt(cl['p50']):>8} {fmt(cl['p95']):>8} {fmt(cl['p99']):>8} {fmt(c.get('server_total_ms', {}).get('p50')):>8} "
            f"{c['bytes_per_s'] / 1e3:>8.1f} {c['errors']:>6}"
        )
    lines.append(
        f"{'all':>6} {agg['requests_sent']:>7} {agg['frames_received']:>7} {agg['dropped_requests']:>7} {agg['delivered_fps']:>7.1f} "
        f"{fmt(lat['p50']):>8} {fmt(lat['p95']):>8} {fmt(lat['p99']):>8} {fmt(agg['server_total_ms']['p50']):>8} "
        f"{agg['bytes_per_s'] / 1e3:>8.1f} {agg['errors']:>6}"
    )
    srv, rnd, out, lag = (agg.get(k, {}) for k in ("server_total_ms", "server_render_ms", "outside_server_ms", "client_loop_lag_ms"))
    lines.append(
        f"latency p50 {fmt(lat['p50'])} ms (request written -> its frame read, matched by seq) = server total p50 {fmt(srv.get('p50'))} ms "
        f"(render p50 {fmt(rnd.get('p50'))} ms) + outside the server p50 {fmt(out.get('p50'))} ms; "
        f"load generator loop lag p95 {fmt(lag.get('p95'))} ms"
    )
    ping = agg.get("ping_rtt_ms", {})
    if ping.get("p50") is not None:
        lines.append(f"ping round trip on the stream sockets p50 {fmt(ping['p50'])} ms (how long the server takes to read what was sent)")
    if agg.get("latency_note"):
        lines.append(f"note: {agg['latency_note']}")
    for m in agg["error_messages"][:5]:
        lines.append(f"error: {m}")
    return "\n".join(lines)


def run(args) -> int:
    import json
    from pathlib import Path

    from client_demo.client import load_request_dir
    from client_demo.loadtest import LoadTestConfig, plot_report, run_loadtest

    from ..cli import CLIError
    from .client import api_key_from, key_hint, unreachable

    from ._paths import output_file

    for option, path in (("--json", args.json), ("--plot", args.plot)):
        if path:
            output_file(path, option)
    cfg = LoadTestConfig(
        url=args.url,
        clients=args.clients,
        duration_s=args.duration,
        rate_hz=args.rate,
        size=args.size,
        shared_avatar=args.shared_avatar,
        api_key=api_key_from(args.api_key),
        allow_remote=args.allow_remote,
        bucket_s=min(1.0, args.duration),
        jpeg_quality=args.jpeg_quality,
        closed_loop=args.closed_loop,
    )
    cfg.validate()  # before touching the network: bounds and the loopback rule
    if args.jpeg_quality is not None and not 1 <= args.jpeg_quality <= 100:
        raise CLIError(f"--jpeg-quality must be in 1..100, got {args.jpeg_quality}")
    req = Path(args.input) if args.input else _default_request_dir()
    if req is None:
        raise CLIError("no shipped sample subject found in fastgha_core/assets/samples; pass --input REQUEST_DIR")
    import logging

    logging.getLogger("httpx").setLevel(logging.WARNING)
    images, cams, masks = load_request_dir(req)
    import httpx

    try:
        report = run_loadtest(cfg, images, cams, masks, progress=print)
    except (OSError, httpx.HTTPError) as e:
        raise CLIError(unreachable(args.url, e)) from None
    except RuntimeError as e:  # an HTTP error answer (e.g. a wrong API key, or a path in --url), as one line
        text = str(e)
        raise CLIError(unreachable(args.url, text) if "/v1/model -> HTTP 404" in text else key_hint(text)) from None
    report["config"]["input"] = str(req)
    print(_summary(report))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(report, indent=1))
        print(f"wrote {args.json}")
    if args.plot:
        Path(args.plot).parent.mkdir(parents=True, exist_ok=True)
        plot_report(report, args.plot)
        print(f"wrote {args.plot}")
    return 1 if report["aggregate"]["errors"] else 0
