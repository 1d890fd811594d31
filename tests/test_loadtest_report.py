"""The load-test tool's latency accounting and plot, against a fake latest-wins server (no network)."""

from __future__ import annotations

import asyncio
import json
import struct
import time
from contextlib import asynccontextmanager

import numpy as np
import pytest

from client_demo.loadtest import LoadTestConfig, _ClientResult, _loop_lag, _requests, _run_client, latency_note, plot_report
from server.protocol import pack_frame


class FakeStream:
    """A latest-wins server on one socket: renders the newest waiting request, ``render_s`` per frame,
    and reports in the header ``total_ms`` = from taking the request to sending (as the real server does)."""

    def __init__(self, render_s: float):
        self.render_s = render_s
        self.inbox: asyncio.Queue = asyncio.Queue()
        self.latest = None
        self.wake = asyncio.Event()
        self.dropped = 0
        self.sent_times: dict[int, float] = {}
        self.taken_at: dict[int, float] = {}
        self.task = None

    async def send(self, msg) -> None:
        if isinstance(msg, str):  # a ping: answered at once, echoing its t
            obj = json.loads(msg)
            assert obj["type"] == "ping"
            await self.inbox.put(json.dumps({"type": "pong", "t": obj["t"]}))
            return
        seq = struct.unpack_from("<I", msg, 4)[0]
        self.sent_times[seq] = time.perf_counter()
        if self.latest is not None:
            self.dropped += 1
        self.latest = seq
        self.wake.set()

    async def _serve(self):
        await self.inbox.put(json.dumps({"type": "ready"}))
        while True:
            await self.wake.wait()
            self.wake.clear()
            seq, self.latest = self.latest, None
            t0 = time.perf_counter()
            self.taken_at[seq] = t0
            await asyncio.sleep(self.render_s)
            header = {"seq": seq, "render_ms": 0.8 * 1e3 * self.render_s, "total_ms": round(1e3 * (time.perf_counter() - t0), 3),
                      "dropped": self.dropped, "width": 16, "height": 16}
            await self.inbox.put(pack_frame(header, b"\xff\xd8jpeg"))

    async def recv(self):
        return await self.inbox.get()


class FakeClient:
    def __init__(self, stream: FakeStream):
        self.stream = stream

    @asynccontextmanager
    async def connect(self, avatar):
        self.stream.task = asyncio.create_task(self.stream._serve())
        try:
            yield self.stream
        finally:
            self.stream.task.cancel()


def test_latency_is_matched_by_seq_and_contains_the_server_time():
    cfg = LoadTestConfig(url="http://127.0.0.1:1", clients=1, duration_s=1.0, rate_hz=40.0, size=16)
    messages = _requests(cfg, "ict53", 53, 0)
    assert len(messages) == 40 and [struct.unpack_from("<I", m, 4)[0] for m in messages] == list(range(40))
    stream = FakeStream(render_s=0.06)  # slower than the 25 ms request period: latest wins, some dropped
    res = _ClientResult(0, "a")

    async def go():
        await _run_client(FakeClient(stream), None, res, cfg, messages, time.perf_counter())

    asyncio.run(go())
    assert res.errors == 0, res.error_messages
    assert res.sent == 40 and res.received + res.dropped + res.unanswered == 40 and res.dropped > 0
    assert len(res.latency_ms) == res.received == len(res.server_total_ms) == len(res.server_render_ms)
    assert len(res.ping_ms) == 1 and res.ping_ms[0] >= 0  # one ping per second of requests, its pong matched
    for lat, srv in zip(res.latency_ms, res.server_total_ms):
        assert lat >= srv - 1e-3  # the server's interval lies inside the client's (send -> frame of that seq)
    # every latency is measured from the send of the very request the frame answers
    answered = sorted(stream.taken_at)
    assert len(answered) == res.received
    for seq, lat in zip(answered, res.latency_ms):
        assert lat >= 1e3 * (stream.taken_at[seq] - stream.sent_times[seq])


def test_latency_note_only_when_the_load_generator_is_late():
    assert latency_note({"p50": 1000.0}, {"p95": 5.0}) is None
    note = latency_note({"p50": 100.0}, {"p95": 40.0})
    assert note is not None and "40 ms late" in note and "100 ms" in note
    assert latency_note({"p50": None}, {"p95": 40.0}) is None


def test_loop_lag_samples_until_stopped():
    samples: list[float] = []

    async def go():
        stop = asyncio.Event()
        task = asyncio.create_task(_loop_lag(samples, stop, tick=0.001))
        await asyncio.sleep(0.05)
        time.sleep(0.03)  # block the loop: one sample must see it
        await asyncio.sleep(0.01)
        stop.set()
        await task

    asyncio.run(go())
    assert len(samples) >= 2 and min(samples) >= 0 and max(samples) >= 20.0


def _report(n: int = 20) -> dict:
    t = [i + 0.5 for i in range(n)]
    return {
        "config": {"clients": 16, "rate_hz": 30.0, "size": 256},
        "server": {"model": "tiny", "device": "cpu"},
        "aggregate": {"delivered_fps": 40.0, "errors": 0},
        "timeline": {"t_s": t, "fps": [40.0 + (i % 3) for i in range(n)], "latency_p50_ms": [400.0] * n,
                     "latency_p95_ms": [700.0] * n, "server_total_p50_ms": [380.0] * n},
    }


def test_plot_legends_sit_outside_the_data(tmp_path, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figs = []
    real_close = plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: figs.append(fig))
    path = tmp_path / "load.png"
    plot_report(_report(), str(path))
    assert path.stat().st_size > 0
    (fig,) = figs
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    axes = [ax for ax in fig.axes if ax.get_legend() is not None]
    assert len(axes) == 2
    for ax in axes:
        box, leg = ax.get_window_extent(renderer), ax.get_legend().get_window_extent(renderer)
        assert leg.x0 >= box.x1, (leg, box)  # entirely to the right of the plotting area
    labels = [t.get_text() for t in axes[1].get_legend().get_texts()]
    assert any("server total" in s for s in labels)
    real_close(fig)
    from PIL import Image

    img = np.asarray(Image.open(path))
    assert img.shape[1] > img.shape[0]  # the legend column widened the figure; nothing cropped away


@pytest.mark.parametrize("bad", [0, -1])
def test_requests_follow_the_config(bad):
    cfg = LoadTestConfig(url="http://127.0.0.1:1", clients=2, duration_s=0.5, rate_hz=10.0, size=32)
    a, b = _requests(cfg, "ict53", 53, 0), _requests(cfg, "ict53", 53, 1)
    assert len(a) == len(b) == 5 and a[1] != b[1]  # clients differ in phase
    assert a == _requests(cfg, "ict53", 53, 0)  # deterministic
    with pytest.raises(ValueError):
        LoadTestConfig(url="http://127.0.0.1:1", clients=bad).validate()


def test_closed_loop_keeps_one_request_in_flight():
    cfg = LoadTestConfig(url="http://127.0.0.1:1", clients=1, duration_s=0.5, rate_hz=200.0, size=16, closed_loop=True)
    messages = _requests(cfg, "ict53", 53, 0)
    stream = FakeStream(render_s=0.03)  # slower than the 5 ms request period
    outstanding = []
    real_send = stream.send

    async def send(msg):
        if not isinstance(msg, str):
            outstanding.append(len(stream.sent_times) - len(stream.taken_at))  # requests sent but not yet taken
        await real_send(msg)

    stream.send = send
    res = _ClientResult(0, "a")
    asyncio.run(_run_client(FakeClient(stream), None, res, cfg, messages, time.perf_counter()))
    assert res.errors == 0, res.error_messages
    assert 0 < res.sent < len(messages)  # paced by the frames, not by the 200 Hz clock
    assert res.dropped == 0 and res.received == res.sent and max(outstanding) == 0
