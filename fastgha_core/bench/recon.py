"""``fastgha bench recon``: reconstruction time against the number of input views, and memory.

Reconstruction (paper Table 3 on this machine): ``model.reconstruct(images [V,3,S,S], cameras [V])``
for V = 1..6, median wall time after a warm-up, with the resulting number of Gaussians.

Memory: bytes held per cached avatar (Gaussians with features + the deformation MLP's cached
first-layer term, as the server's ``AvatarStore`` counts them) and the resident set size of a
fresh process holding the model and N avatars (``_memprobe``, run as a subprocess so that this
process's own allocations do not count).
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys

import torch

from ._common import bench_avatar, bench_model, input_views, load_average, positive_int, time_fn

log = logging.getLogger(__name__)

DEFAULT_VIEWS = (1, 2, 3, 4, 5, 6)
DEFAULT_AVATARS = (1, 4, 16)


def add_arguments(parser) -> None:
    parser.add_argument("--recon-model", default="tiny", help="model preset or folder (default tiny)")
    parser.add_argument("--recon-views", default=None, help="comma-separated view counts (default 1,2,3,4,5,6)")
    parser.add_argument("--recon-repeats", type=positive_int, default=None, help="timed repeats per view count (default 5, --quick 1)")
    parser.add_argument("--recon-avatars", default=None, help="comma-separated avatar counts for the memory probe (default 1,4,16)")


def _ints(text: str | None, default: tuple[int, ...], what: str) -> tuple[int, ...]:
    if not text:
        return default
    try:
        vals = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"{what}: expected comma-separated integers, got {text!r}") from None
    if not vals or min(vals) < 1:
        raise ValueError(f"{what}: expected positive integers, got {text!r}")
    return vals


def memory_probe(model_name: str, counts: tuple[int, ...], timeout: float = 600.0) -> dict:
    """Run ``_memprobe`` in a fresh interpreter; its JSON result (or ``{"error": ...}``)."""
    cmd = [sys.executable, "-m", "fastgha_core.bench._memprobe", model_name, *map(str, counts)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)
    except subprocess.TimeoutExpired:
        return {"error": f"memory probe timed out after {timeout:.0f} s"}
    if proc.returncode != 0:
        return {"error": f"memory probe failed (exit {proc.returncode}): {proc.stderr.strip().splitlines()[-1:]}"}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run(args) -> dict:
    quick = bool(getattr(args, "quick", False))
    name = getattr(args, "recon_model", "tiny") or "tiny"
    views = _ints(getattr(args, "recon_views", None), (1, 4) if quick else DEFAULT_VIEWS, "--recon-views")
    repeats = getattr(args, "recon_repeats", None) or (1 if quick else 5)
    counts = _ints(getattr(args, "recon_avatars", None), (1, 2) if quick else DEFAULT_AVATARS, "--recon-avatars")
    model = bench_model(name)
    vmax = int(model.config.max_views)
    if getattr(args, "recon_views", None) and max(views) > vmax:  # the user's list; the default stays within
        raise ValueError(f"--recon-views: model {model.config.name!r} accepts 1..{vmax} views, got {args.recon_views!r}")
    load0 = load_average()
    print(f"reconstruction benchmark: model {model.config.name!r}, input {model.config.input_size}², "
          f"torch threads {torch.get_num_threads()}, {repeats} repeats, median")
    print(f"{'views':>5} {'gaussians':>10} {'wall ms':>9} {'cpu ms':>9}")
    rows = []
    for v in views:
        if v > vmax:
            rows.append({"views": v, "skipped": f"model accepts at most {vmax} views"})
            continue
        images, cams = input_views(model, v)

        def f():
            with torch.inference_mode():
                return model.reconstruct(images, cams)

        t = time_fn(f, repeats)
        av = f()
        n = len(av)
        # "gaussians": all of the avatar's (with the prior's appended shells, mouth interior and lids);
        # "reconstructed": the network's, at most one per input pixel
        rows.append({"views": v, "gaussians": n, "reconstructed": int(av.num_reconstructed), **t.to_dict()})
        print(f"{v:>5} {n:>10} {t.wall_ms:>9.1f} {t.cpu_ms:>9.1f}", flush=True)

    avatar = bench_avatar(model, 4)
    model.animate(avatar, model.expression_space.neutral())  # fills the first-layer cache
    cache = avatar.deform_cache
    per_avatar = {
        "gaussians": len(avatar),
        "gaussian_bytes": int(avatar.nbytes),
        "deform_cache_bytes": int(cache.numel() * cache.element_size()) if cache is not None else 0,
    }
    per_avatar["bytes"] = per_avatar["gaussian_bytes"] + per_avatar["deform_cache_bytes"]
    probe = memory_probe(name, counts)
    if "rows" in probe and len(probe["rows"]) >= 2:
        a, b = probe["rows"][0], probe["rows"][-1]
        probe["rss_mib_per_avatar"] = (b["rss_mib"] - a["rss_mib"]) / max(1, b["avatars"] - a["avatars"])
    print(f"memory: {per_avatar['bytes'] / 2**20:.1f} MiB per cached avatar ({per_avatar['gaussians']} Gaussians: "
          f"{per_avatar['gaussian_bytes'] / 2**20:.1f} MiB + deform cache {per_avatar['deform_cache_bytes'] / 2**20:.1f} MiB)")
    for row in probe.get("rows", []):
        print(f"  {row['avatars']:>3} avatars: RSS {row['rss_mib']:.0f} MiB, peak {row['peak_rss_mib']:.0f} MiB")
    if "error" in probe:
        print(f"  memory probe: {probe['error']}")
    four = next((r for r in rows if r.get("views") == 4 and "wall_ms" in r), None)
    summary = {
        "recon_s_4views": four["wall_ms"] / 1e3 if four else None,
        "bytes_per_avatar": per_avatar["bytes"],
    }
    return {
        "model": model.config.name,
        "input_size": model.config.input_size,
        "rows": rows,
        "memory": {"per_avatar": per_avatar, "process": probe},
        "load_average_start": load0,
        "load_average_end": load_average(),
        "summary": summary,
    }
