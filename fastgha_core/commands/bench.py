"""``fastgha bench TARGET [--json PATH]``: run benchmarks from ``fastgha_core/bench/<target>.py``."""

from __future__ import annotations

import importlib
import json
import pkgutil
from pathlib import Path

NAME = "bench"
HELP = "run benchmarks (render, recon, frame, mlp or all) and print/save the results"
TARGETS = ("render", "recon", "frame", "mlp")


def _available() -> list[str]:
    from .. import bench

    found = {m.name for m in pkgutil.iter_modules(bench.__path__) if not m.name.startswith("_")}
    return [t for t in TARGETS if t in found] + sorted(found - set(TARGETS))


def _module(target: str):
    return importlib.import_module(f"fastgha_core.bench.{target}")


def add_arguments(parser) -> None:
    parser.add_argument("target", choices=(*TARGETS, "all"), help="what to benchmark; 'all' runs every available target")
    parser.add_argument("--json", metavar="PATH", type=Path, default=None, help="also write the results as JSON here")
    parser.add_argument("--quick", action="store_true", help="fewer sizes and repeats: a smoke run (render about 10 s, all about 30 s on 2 cores)")
    # options of the individual targets (each module may add its own)
    for target in _available():
        mod = _module(target)
        if hasattr(mod, "add_arguments"):
            mod.add_arguments(parser)


def run(args) -> int:
    from ..cli import CLIError

    available = _available()
    if args.target == "all":
        targets = available
        if not targets:
            raise CLIError("no benchmark targets are available")
    else:
        if args.target not in available:
            raise CLIError(
                f"benchmark target {args.target!r} is not available yet (no module fastgha_core/bench/{args.target}.py); "
                f"available: {', '.join(available) or 'none'}"
            )
        targets = [args.target]
    if args.json is not None:
        from ._paths import output_file

        output_file(args.json, "--json")  # before minutes of timing, not after
    import time

    results: dict = {"summary": {}}
    for i, target in enumerate(targets):
        if len(targets) > 1:
            print(f"\n== [{i + 1}/{len(targets)}] bench {target}{' --quick' if args.quick else ''} ==", flush=True)
        t0 = time.perf_counter()
        res = _module(target).run(args)
        res["elapsed_s"] = round(time.perf_counter() - t0, 1)
        print(f"bench {target}: done in {res['elapsed_s']:.0f} s", flush=True)
        results[target] = res
        for key, value in (res.get("summary") or {}).items():
            results["summary"][f"{target}.{key}" if key in results["summary"] else key] = value
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2))
        print(f"wrote {args.json}")
    return 0
