"""The server's same-person check (``fastgha_core/tracking/identity.py``) on the real photo sets: descriptor distances
within each set and between sets, and what the check adds to the creation time.

    PYTHONPATH=$PWD .venv/bin/python bench/same_person.py [--set studio-4] [--reps 4] [--json out/same_person.json]

Reads the sets from ``../shared/realsets`` (or ``FASTGHA_REALSETS``) and exits cleanly when they are
absent (they are not part of the repository). Distances come from ``IdentityChecker.descriptor`` on
each photo decoded upright (EXIF applied), as the server computes them. The timing runs the creation
job in process (``JobQueue``, the shipped ``tiny`` model, the photos posted without cameras so the
server tracks them), alternating the check on and off, and reports medians: a shared machine makes
single runs noisy. Needs the ``faces`` extra.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/: _bench_cli (tests load this file by path)

from _bench_cli import write_json

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _sets(root: Path) -> dict[str, list[Path]]:
    return {d.name: sorted(d.glob("*.jpg")) for d in sorted(root.iterdir()) if d.is_dir() and any(d.glob("*.jpg"))}


def distances(root: Path, checker) -> dict:
    import numpy as np
    from PIL import Image, ImageOps

    desc = {}
    without = []
    for name, files in _sets(root).items():
        for f in files:
            d = checker.descriptor(np.asarray(ImageOps.exif_transpose(Image.open(f)).convert("RGB")))
            if d is None:
                without.append(f"{name}/{f.name}")
            else:
                desc[f"{name}/{f.name}"] = d
    same, diff = [], []
    for a, b in itertools.combinations(sorted(desc), 2):
        (same if a.split("/")[0] == b.split("/")[0] else diff).append(float(np.linalg.norm(desc[a] - desc[b])))
    return {"photos_with_face": len(desc), "photos_without_face": without, "same_person": [min(same), max(same)], "different_people": [min(diff), max(diff)]}


def creation_times(folder: Path, reps: int) -> dict:
    from fastgha_core import load_model
    from fastgha_core.model.avatar import CanonicalAvatar
    from server.context import ServerContext
    from server.identity import IdentityChecker
    from server.jobs import CreationRequest, JobQueue, Photo
    from server.settings import Settings
    from server.store import AvatarStore
    from server.tracking import PhotoTracker

    model = load_model("tiny", device="cpu")
    tracker = PhotoTracker()
    checker = IdentityChecker(True)
    assert checker.available, checker.reason  # one per app, loaded at start-up as in the server
    photos = [Photo(f.name, f.read_bytes()) for f in sorted(folder.glob("*.jpg"))][:4]

    def once(check: bool) -> tuple[float, dict]:
        tmp = tempfile.mkdtemp()
        ctx = ServerContext(settings=Settings(data_dir=tmp, warmup=False, same_person_check=check))
        ctx.model = model
        ctx.store = AvatarStore(Path(tmp), 10**9, 0, load_fn=CanonicalAvatar.load)
        ctx.identity = checker if check else IdentityChecker(False)

        async def run():
            q = JobQueue(ctx, tracker=tracker, extra_stages=[])
            await q.start()
            try:
                t = time.perf_counter()
                job, _ = q.submit(q.reserve("bench", 1), CreationRequest(list(photos), None, None))
                await q.wait(job)
                return job, time.perf_counter() - t
            finally:
                await q.stop()

        job, dt = asyncio.run(run())
        if job.status != "ready":
            raise SystemExit(f"creation failed: {job.error.code}: {job.error.message}")
        return dt, job.result["same_person"]

    once(True), once(False)  # warm: tracker, numba kernels
    t = {True: [], False: []}
    check_ms = []
    for r in range(reps):
        for c in (True, False):
            dt, sp = once(c)
            t[c].append(dt)
            if c:
                check_ms.append(sp["check_ms"])
            print(f"rep {r}: check {'on ' if c else 'off'} {dt:.2f} s" + (f" (check {sp['check_ms']:.0f} ms)" if c else ""), flush=True)
    on, off = statistics.median(t[True]), statistics.median(t[False])
    return {"set": folder.name, "photos": len(photos), "reps": reps, "median_s_check_on": round(on, 3), "median_s_check_off": round(off, 3),
            "ratio": round(on / off, 3), "median_check_ms": round(statistics.median(check_ms), 1)}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", default="studio-4", help="the real set whose creation is timed (default studio-4)")
    ap.add_argument("--reps", type=int, default=4, help="timed creations per arm (default 4)")
    ap.add_argument("--json", default=None, help="also write the figures here")
    args = ap.parse_args()
    root = Path(os.environ.get("FASTGHA_REALSETS", REPO.parent / "shared" / "realsets"))
    if not root.is_dir():
        print(f"no real sets at {root} (set FASTGHA_REALSETS): nothing to measure")
        return 0
    from fastgha_core.tracking.identity import IdentityChecker

    checker = IdentityChecker(True)
    if not checker.available:
        print(f"the same-person check is unavailable here: {checker.reason}")
        return 0
    out = {"distances": distances(root, checker)}
    print("distances:", json.dumps(out["distances"]))
    out["creation"] = creation_times(root / args.set, args.reps)
    print("creation:", json.dumps(out["creation"]))
    write_json(args.json, out, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
