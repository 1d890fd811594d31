"""Memory probe run in a fresh process by ``fastgha bench recon``: peak RSS with N cached avatars.

``python -m fastgha_core.bench._memprobe MODEL N [N ...]`` prints one JSON line. It builds what a
server process holds: the model, a ``server.store.AvatarStore`` (in a temporary folder) with N
avatars, each animated and rendered once (so its deformation cache is filled).
"""

from __future__ import annotations

import json
import resource
import sys
import tempfile


def _rss_mib() -> float:
    """Current resident set size (MiB) from /proc/self/statm."""
    import os

    with open("/proc/self/statm") as f:
        pages = int(f.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def main(argv: list[str]) -> int:
    import torch

    from fastgha_core.bench._common import bench_avatar, bench_model
    from fastgha_core.model.avatar import CanonicalAvatar
    from fastgha_core.render import render
    from server.frames import FrameRenderer
    from server.store import AvatarStore

    name, counts = argv[0], sorted(int(a) for a in argv[1:])
    model = bench_model(name)
    renderer = FrameRenderer(model, "cpu")
    base = bench_avatar(model, 4)
    expr = model.expression_space.neutral()
    renderer.render(base, expr, renderer.default_camera, 85)  # allocator and kernels warm
    out = {"model": name, "rss_model_mib": _rss_mib(), "gaussians": len(base), "rows": []}
    with tempfile.TemporaryDirectory() as tmp:
        store = AvatarStore(tmp, 1 << 40, 0, load_fn=CanonicalAvatar.load, nbytes_fn=model.serving_nbytes)
        n = 0
        for target in counts:
            while n < target:
                g = base.gaussians
                av = CanonicalAvatar(g.replace(**{k: getattr(g, k).clone() for k in ("means", "quats", "scales", "opacities", "colors", "features")}),
                                     base.model_name, base.expression_space, base.prior, base.num_interior)
                store.put(f"benchavatar{n:011d}", av, {"model": name})
                renderer.render(av, expr, renderer.default_camera, 85)  # fills the deform cache
                n += 1
            out["rows"].append({
                "avatars": n,
                "rss_mib": _rss_mib(),
                "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                "store_bytes": store.cached_bytes,
            })
    del torch, render
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
