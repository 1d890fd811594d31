"""Benchmarks built on the load test, against a running server on loopback.

``clients`` mode: delivered FPS and latency against the number of concurrent clients::

    python -m client_demo.loadtest_sweep clients --url http://127.0.0.1:8000 --input REQUEST_DIR \
        --clients 1 2 4 8 16 --duration 20 --rate 30 --size 256 --json sweep.json --plot docs/images/loadtest_clients.png

``soak`` mode: one long run while the server's resident memory (``VmRSS`` of ``--pid`` from
``/proc/<pid>/status``) is sampled every ``--rss-every`` seconds::

    python -m client_demo.loadtest_sweep soak --url http://127.0.0.1:8000 --input REQUEST_DIR --pid PID \
        --clients 16 --duration 180 --rate 30 --size 256 --json soak.json --plot soak.png

Prints a Markdown table; the JSON holds the full load-test reports.
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from pathlib import Path

from .client import load_request_dir
from .loadtest import LoadTestConfig, run_loadtest


def _rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise ValueError(f"no VmRSS for pid {pid}")


def _f(v) -> str:
    return "-" if v is None else f"{v:.0f}"


def _row(rep: dict) -> str:
    a = rep["aggregate"]
    lat = a["latency_ms"]
    return (
        f"| {a['clients']} | {a['clients'] * rep['config']['rate_hz']:g} | {a['delivered_fps']:.1f} | {a['delivered_fps_per_client']:.1f} "
        f"| {a['dropped_requests']} | {lat['p50']:.0f} | {lat['p95']:.0f} | {lat['p99']:.0f} | {_f(a.get('server_total_ms', {}).get('p50'))} "
        f"| {_f(a.get('client_loop_lag_ms', {}).get('p95'))} | {a['bytes_per_s'] / 1e6:.2f} | {a['errors']} |"
    )


HEADER = (
    "| clients | requested fps (all) | delivered fps (all) | per client | dropped requests | latency p50 ms | p95 ms | p99 ms "
    "| server total p50 ms | client loop lag p95 ms | MB/s | errors |\n"
    "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("mode", choices=["clients", "soak"])
    p.add_argument("--url", default="http://127.0.0.1:8000")
    p.add_argument("--input", required=True, help="request folder for the avatars")
    p.add_argument("--api-key", default=None)
    p.add_argument("--clients", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    p.add_argument("--duration", type=float, default=20.0)
    p.add_argument("--rate", type=float, default=30.0)
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--pid", type=int, default=None, help="server process id (soak: RSS sampling)")
    p.add_argument("--rss-every", type=float, default=5.0)
    p.add_argument("--json", default=None)
    p.add_argument("--plot", default=None)
    args = p.parse_args(argv)
    images, cams, masks = load_request_dir(args.input)

    def cfg(n: int) -> LoadTestConfig:
        return LoadTestConfig(url=args.url, clients=n, duration_s=args.duration, rate_hz=args.rate, size=args.size, api_key=args.api_key)

    if args.mode == "clients":
        reports = []
        for n in args.clients:
            reports.append(run_loadtest(cfg(n), images, cams, masks, progress=print))
            print(_row(reports[-1]), flush=True)
        print(HEADER)
        for r in reports:
            print(_row(r))
        if args.json:
            Path(args.json).write_text(json.dumps(reports, indent=1))
        if args.plot:
            _plot_clients(reports, args.plot)
        return 0

    if args.pid is None:
        p.error("soak needs --pid (the server process)")
    samples: list[tuple[float, int]] = []
    stop = threading.Event()
    t0 = time.perf_counter()

    def sample() -> None:
        while not stop.is_set():
            samples.append((round(time.perf_counter() - t0, 2), _rss_kib(args.pid)))
            stop.wait(args.rss_every)

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    try:
        rep = run_loadtest(cfg(args.clients[0]), images, cams, masks, progress=print)
    finally:
        stop.set()
        th.join()
        samples.append((round(time.perf_counter() - t0, 2), _rss_kib(args.pid)))
    rep["rss"] = {"t_s": [s[0] for s in samples], "rss_mib": [round(s[1] / 1024, 1) for s in samples]}
    print(HEADER)
    print(_row(rep))
    rss = rep["rss"]["rss_mib"]
    print(f"server RSS: start {rss[0]:.0f} MiB, min {min(rss):.0f}, max {max(rss):.0f}, end {rss[-1]:.0f} MiB ({len(rss)} samples)")
    if args.json:
        Path(args.json).write_text(json.dumps(rep, indent=1))
    if args.plot:
        _plot_soak(rep, args.plot)
    return 0


def _plot_clients(reports: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r["aggregate"]["clients"] for r in reports]
    fps = [r["aggregate"]["delivered_fps"] for r in reports]
    p50 = [r["aggregate"]["latency_ms"]["p50"] for r in reports]
    p95 = [r["aggregate"]["latency_ms"]["p95"] for r in reports]
    cfg, srv = reports[0]["config"], reports[0]["server"]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    a1.plot(n, fps, "o-", label="delivered, all clients")
    a1.plot(n, [f / c for f, c in zip(fps, n)], "s--", label="delivered, per client")
    a1.set_xscale("log", base=2)
    a1.set_xticks(n, [str(c) for c in n])
    a1.set_ylim(0, max(fps) * 1.3)
    a1.set_xlabel("concurrent clients")
    a1.set_ylabel("frames / s")
    a1.legend(loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=2, fontsize="small", frameon=False)
    a1.grid(alpha=0.3)
    a2.plot(n, p50, "o-", label="p50")
    a2.plot(n, p95, "s-", label="p95")
    srv50 = [r["aggregate"].get("server_total_ms", {}).get("p50") for r in reports]
    if all(v is not None for v in srv50):
        a2.plot(n, srv50, "k:", label="server total p50")
    a2.set_xscale("log", base=2)
    a2.set_xticks(n, [str(c) for c in n])
    a2.set_xlabel("concurrent clients")
    a2.set_ylabel("request → frame latency (ms)")
    a2.legend(loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=2, fontsize="small", frameon=False)
    a2.grid(alpha=0.3)
    fig.suptitle(f"model {srv['model']} on {srv['device']}, {cfg['size']}² frames, {cfg['rate_hz']:g} Hz per client, {cfg['duration_s']:g} s runs")
    fig.tight_layout()
    fig.savefig(path, dpi=100, bbox_inches="tight")  # the legends sit below the axes, off the data
    plt.close(fig)


def _plot_soak(rep: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tl = rep["timeline"]
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    a1.plot(tl["t_s"], tl["fps"])
    a1.set_ylabel("delivered frames / s (all)")
    a1.set_title(f"soak: {rep['aggregate']['clients']} streams, {rep['aggregate']['errors']} errors")
    a1.grid(alpha=0.3)
    a2.plot(rep["rss"]["t_s"], rep["rss"]["rss_mib"], "o-", ms=3)
    a2.set_ylabel("server RSS (MiB)")
    a2.set_xlabel("time (s)")
    a2.set_ylim(0, max(rep["rss"]["rss_mib"]) * 1.2)
    a2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
