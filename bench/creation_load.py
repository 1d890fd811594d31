"""Creation under load: memory of the decompression-amplification attack, and the frame rate of a
running stream while other avatars are being created (issue 18 item 1, issue 17 "creation job").

Starts a real server (``uvicorn --factory server.app:create_app``) from ``--repo`` (default: this
checkout; point it at an older checkout to compare) and measures:

* ``memory``: one 180 KB request carrying eight 22.5 KB greyscale PNGs that each decode to
  4096 x 4096 (the default per-image pixel limit), then three such requests at once. Reported:
  the server's peak resident memory above its idle level for each phase (Linux
  ``/proc/<pid>/status`` ``VmHWM``, reset between phases through ``/proc/<pid>/clear_refs``),
  and the HTTP status of every request.
* ``fps``: one avatar streamed lock-step (one request in flight) for ``--seconds`` while idle,
  then for ``--seconds`` while another client creates avatars back to back from the shipped
  sample, ``--rounds`` times alternately; reported: delivered frames per second of each phase,
  their ratio per round and the median ratio (issue 17's target: within 20 %), and how many
  creations finished meanwhile.
* ``saturated``: the time of one creation on the idle server and of one made 45 s into a
  ``fastgha loadtest`` of 4 open-loop streams (more frames than the cores render).

Usage (numbers go to docs/benchmarks.md)::

    python bench/creation_load.py memory
    python bench/creation_load.py fps --rounds 4 --seconds 8 --size 256
    python bench/creation_load.py fps --sched-idle off            # creation threads at nice 10 only
    python bench/creation_load.py fps --sched-idle off --nice 0   # at normal priority, for comparison
    python bench/creation_load.py saturated [--sched-idle off]    # creation time while streams saturate the cores
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

HERE = Path(__file__).resolve().parent.parent
KEY = "bench-key"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    def __init__(self, repo: Path, data: Path, log: Path, **env_over: str) -> None:
        self.port = _free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        env = dict(os.environ, FASTGHA_DATA_DIR=str(data), FASTGHA_API_KEYS=KEY, FASTGHA_DEVICE="cpu",
                   FASTGHA_STATIC_DIR=str(data / "no-static"), PYTHONPATH=str(repo))  # fmt: skip
        env.update(env_over)
        self.log = open(log, "ab")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "--factory", "server.app:create_app", "--host", "127.0.0.1", "--port", str(self.port)],
            cwd=repo, env=env, stdout=self.log, stderr=subprocess.STDOUT,
        )  # fmt: skip
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited: {log.read_text()[-2000:]}")
            try:
                if httpx.get(self.base + "/healthz", timeout=2).json().get("status") == "ok":
                    return
            except (httpx.HTTPError, ValueError):
                pass
            time.sleep(0.3)
        raise RuntimeError("server did not start")

    def status(self, field: str) -> int:
        """``VmRSS`` / ``VmHWM`` of the server process in bytes."""
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
        raise KeyError(field)

    def reset_peak(self) -> None:
        Path(f"/proc/{self.proc.pid}/clear_refs").write_text("5")  # resets VmHWM to the current RSS

    def stop(self) -> None:
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        self.log.close()


# ---------------------------------------------------------------- memory
def bomb_png(side: int = 4096, level: int = 200) -> bytes:
    """A greyscale PNG of one grey level, ``side`` x ``side``: 22.5 KB at 4096 (deflate at its limit)."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    raw = (b"\x00" + bytes([level]) * side) * side  # filter byte 0 + one row
    ihdr = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)  # 8-bit greyscale
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b"")


def attack_request(side: int = 4096, n: int = 8):
    """Eight PNGs of one grey level (about 16 KB each) decoding to ``side`` x ``side``, and cameras."""
    png = bomb_png(side)
    sys.path.insert(0, str(HERE))
    from fastgha_core.cameras import cameras_to_json, orbit_cameras

    cams = cameras_to_json(orbit_cameras(n, width=side, height=side))
    files = [("images", (f"bomb{i}.png", png, "image/png")) for i in range(n)]
    return files, json.dumps(cams), len(png)


def _post(base: str, files, cams: str) -> int:
    r = httpx.post(base + "/v1/avatars", files=files, data={"cameras": cams}, headers={"X-API-Key": KEY}, timeout=600)
    return r.status_code


def memory(args) -> dict:
    files, cams, png_bytes = attack_request()
    body = sum(len(f[1][1]) for f in files) + len(cams)
    out = {"png_bytes": png_bytes, "request_bytes": body}
    with tempfile.TemporaryDirectory() as d:
        srv = Server(Path(args.repo), Path(d), Path(args.log), FASTGHA_WARMUP="true", FASTGHA_COMPILE="off")
        try:
            time.sleep(2)
            for phase, k in (("one_request", 1), ("three_at_once", 3)):
                base_rss = srv.status("VmRSS")
                srv.reset_peak()
                with cf.ThreadPoolExecutor(k) as ex:
                    codes = list(ex.map(lambda _: _post(srv.base, files, cams), range(k)))
                peak = srv.status("VmHWM")
                out[phase] = {"statuses": codes, "rss_before_mb": round(base_rss / 2**20, 1), "peak_growth_mb": round((peak - base_rss) / 2**20, 1)}
                print(phase, out[phase], flush=True)
                time.sleep(1)
        finally:
            srv.stop()
    return out


# ---------------------------------------------------------------- frame rate during creations
def _sample_request():
    req = HERE / "fastgha_core" / "assets" / "samples"
    folder = sorted(req.glob("*/request"))[0]
    imgs = sorted(p for p in folder.iterdir() if p.suffix == ".jpg")
    files = [("images", (p.name, p.read_bytes(), "image/jpeg")) for p in imgs]
    files += [("masks", (p.stem + "_mask.png", (folder / f"{p.stem}_mask.png").read_bytes(), "image/png")) for p in imgs]
    return files, (folder / "cameras.json").read_text()


def _stream_fps(base: str, av: dict, seconds: float, size: int) -> tuple[float, float]:
    from websockets.sync.client import connect

    sys.path.insert(0, str(HERE))
    from client_demo.client import orbit_camera, unpack_frame

    url = base.replace("http", "ws") + f"/v1/avatars/{av['avatar_id']}/stream?token={av['token']}"
    cam = orbit_camera(0, 0, 1.0, width=size, height=size)
    n, render = 0, []
    with connect(url, max_size=2**26) as ws:
        while json.loads(ws.recv(timeout=120)).get("type") != "ready":
            pass
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            ws.send(json.dumps({"seq": n % 2**32, "expression": {"jawOpen": 0.5 + 0.5 * np.sin(n / 5)}, "camera": cam}))
            while True:
                msg = ws.recv(timeout=120)
                if isinstance(msg, bytes):
                    break
            header, _ = unpack_frame(msg)
            render.append(header["render_ms"])
            n += 1
        dt = time.perf_counter() - t0
    return n / dt, float(np.median(render))


def fps(args) -> dict:
    files, cams = _sample_request()
    out: dict = {"size": args.size, "seconds": args.seconds, "sched_idle": args.sched_idle, "nice": args.nice}
    with tempfile.TemporaryDirectory() as d:
        srv = Server(Path(args.repo), Path(d), Path(args.log), FASTGHA_CREATION_NICE=str(args.nice), FASTGHA_MAX_QUEUED_JOBS="64",
                     FASTGHA_CREATION_SCHED_IDLE=str(args.sched_idle == "on").lower(),
                     FASTGHA_MAX_JOBS_PER_CLIENT="64")  # fmt: skip
        try:
            r = httpx.post(srv.base + "/v1/avatars", files=files, data={"cameras": cams}, headers={"X-API-Key": KEY}, timeout=600)
            av = r.json()
            _stream_fps(srv.base, av, 3.0, args.size)  # warm
            stop = threading.Event()
            made, times = [0], []

            def creator() -> None:
                while not stop.is_set():
                    t = time.perf_counter()
                    code = _post(srv.base, files, cams)
                    times.append(time.perf_counter() - t)
                    made[0] += code == 201

            rounds = []
            for _ in range(args.rounds):  # idle and busy phases alternate, so that drifting background load hits both
                idle, idle_ms = _stream_fps(srv.base, av, args.seconds, args.size)
                stop.clear()
                th = threading.Thread(target=creator, daemon=True)
                th.start()
                time.sleep(0.5)
                busy, busy_ms = _stream_fps(srv.base, av, args.seconds, args.size)
                stop.set()
                th.join()
                rounds.append({"idle_fps": round(idle, 2), "busy_fps": round(busy, 2), "ratio": round(busy / idle, 3),
                               "idle_render_ms_p50": round(idle_ms, 2), "busy_render_ms_p50": round(busy_ms, 2)})  # fmt: skip
                print(rounds[-1], flush=True)
            med = lambda k: float(np.median([r[k] for r in rounds]))  # noqa: E731
            out.update(rounds=rounds, idle_fps=med("idle_fps"), busy_fps=med("busy_fps"), ratio_median=med("ratio"),
                       creations=made[0], creation_s_median=round(float(np.median(times)), 2) if times else None)  # fmt: skip
            print(out, flush=True)
        finally:
            srv.stop()
    return out


# ---------------------------------------------------------------- creation time on a saturated server
def saturated(args) -> dict:
    """One creation on the idle server, then ``fastgha loadtest`` (4 open-loop streams at 30 Hz on one
    avatar, more than 2 cores render) and, 45 s into it, another creation: both creation times."""
    files, cams = _sample_request()
    out: dict = {"sched_idle": args.sched_idle, "nice": args.nice}
    with tempfile.TemporaryDirectory() as d:
        srv = Server(Path(args.repo), Path(d), Path(args.log), FASTGHA_CREATION_NICE=str(args.nice),
                     FASTGHA_CREATION_SCHED_IDLE=str(args.sched_idle == "on").lower())  # fmt: skip
        try:
            t = time.perf_counter()
            _post(srv.base, files, cams)
            out["creation_idle_s"] = round(time.perf_counter() - t, 1)
            report = Path(d) / "loadtest.json"
            load = subprocess.Popen(
                [sys.executable, "-m", "fastgha_core.cli", "loadtest", "--url", srv.base, "--clients", "4", "--duration", "100",
                 "--shared-avatar", "--api-key", KEY, "--json", str(report)],
                cwd=HERE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )  # fmt: skip
            time.sleep(45)
            t = time.perf_counter()
            out["status_under_load"] = _post(srv.base, files, cams)
            out["creation_under_load_s"] = round(time.perf_counter() - t, 1)
            load.wait(300)
            out["loadtest_delivered_fps"] = json.loads(report.read_text())["aggregate"]["delivered_fps"]
            print(out, flush=True)
        finally:
            srv.stop()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("what", choices=("memory", "fps", "saturated"))
    ap.add_argument("--repo", default=str(HERE), help="checkout whose server/ to run (default: this one)")
    ap.add_argument("--seconds", type=float, default=8.0, help="fps: length of each idle and each busy phase")
    ap.add_argument("--rounds", type=int, default=4, help="fps: idle/busy phase pairs (medians reported)")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--sched-idle", choices=("on", "off"), default="on", help="FASTGHA_CREATION_SCHED_IDLE of the server (a server from before it ignores it)")
    ap.add_argument("--nice", type=int, default=10, help="FASTGHA_CREATION_NICE of the server (used with --sched-idle off)")
    ap.add_argument("--log", default=os.path.join(tempfile.gettempdir(), "fastgha-creation-load.log"))
    ap.add_argument("--json", default=None, help="also write the result here")
    args = ap.parse_args()
    res = {"memory": memory, "fps": fps, "saturated": saturated}[args.what](args)
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
