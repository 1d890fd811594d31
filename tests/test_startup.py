"""Server start-up: the MLP precision chosen by a micro-benchmark, start-up progress in the log,
/healthz reporting the choice, and `fastgha serve` refusing a busy port before the slow start-up."""

from __future__ import annotations

import logging
import socket
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from fastgha_core.perf import BF16_MARGIN, choose_mlp_precision, measure_mlp_precision

REPO = Path(__file__).resolve().parents[1]


class FakeClock:
    """A clock that only moves when a fake workload runs."""

    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now

    def work(self, costs_ms):
        it = iter(costs_ms)

        def run():
            self.now += next(it) / 1e3

        return run


def _choose(fp32_costs, bf16_costs, **kw):
    clock = FakeClock()
    return choose_mlp_precision(clock.work(fp32_costs), clock.work(bf16_costs), timer=clock, **kw)


def test_bf16_chosen_when_clearly_faster():
    c = _choose([999] + [10] * 5, [999] + [5] * 5, reps=5)  # first call of each = untimed warm-up
    assert (c.precision, c.reason, c.reps, c.margin) == ("bf16", "measured", 5, BF16_MARGIN)
    assert c.fp32_ms == pytest.approx(10.0) and c.bf16_ms == pytest.approx(5.0)
    assert c.bf16 and c.to_dict()["bf16_ms"] == 5.0


def test_fp32_kept_when_bf16_is_slower_or_only_marginally_faster():
    assert _choose([1, 10, 10, 10], [1, 20, 20, 20], reps=3).precision == "fp32"  # emulated bf16 (no AMX)
    assert _choose([1, 10, 10, 10], [1, 9.8, 9.8, 9.8], reps=3).precision == "fp32"  # 2 % faster < the margin
    assert _choose([1, 10, 10, 10], [1, 9.8, 9.8, 9.8], reps=3, margin=0.99).precision == "bf16"


def test_medians_ignore_a_stall_and_runs_alternate():
    order = []
    clock = FakeClock()
    fp32 = clock.work([1, 10, 10, 500, 10, 10])  # one stall (another process took the core)
    bf16 = clock.work([1, 8, 8, 8, 8, 8])

    def tag(fn, name):
        def f():
            order.append(name)
            fn()

        return f

    c = choose_mlp_precision(tag(fp32, "f"), tag(bf16, "b"), reps=5, timer=clock)
    assert c.fp32_ms == pytest.approx(10.0) and c.bf16_ms == pytest.approx(8.0) and c.precision == "bf16"
    assert order == ["f", "b"] + ["f", "b"] * 5


def test_bf16_that_cannot_run_falls_back_to_fp32():
    def broken():
        raise RuntimeError("no bf16 kernel")

    c = choose_mlp_precision(lambda: None, broken)
    assert c.precision == "fp32" and c.reason.startswith("bf16 failed: RuntimeError: no bf16 kernel") and c.fp32_ms is None


def test_bad_arguments():
    with pytest.raises(ValueError, match="reps must be >= 1, got 0"):
        choose_mlp_precision(lambda: None, lambda: None, reps=0)
    with pytest.raises(ValueError, match="margin must be > 0"):
        choose_mlp_precision(lambda: None, lambda: None, margin=0)


def test_measure_runs_the_real_mlp_tail_in_both_precisions():
    from fastgha_core.config import DeformConfig
    from fastgha_core.model.deform import DeformationMLP

    model = SimpleNamespace(deform=DeformationMLP(8, 5, DeformConfig(hidden_size=16, num_layers=3, pe_freqs=2)))
    c = measure_mlp_precision(model, reps=2, chunk_size=256)
    assert c.reason == "measured" and c.reps == 2 and c.precision in ("fp32", "bf16")
    assert c.fp32_ms > 0 and c.bf16_ms > 0
    assert c.bf16 == (c.bf16_ms <= c.margin * c.fp32_ms)


def test_startup_logs_each_step_and_healthz_reports_the_measured_choice(tmp_path, caplog):
    from fastapi.testclient import TestClient

    from server.app import create_app
    from server.settings import Settings

    s = Settings(model="tiny", data_dir=tmp_path, compile="off", warmup=True, warmup_frames=1, mlp_precision="auto")
    caplog.set_level(logging.INFO, logger="server.app")
    with TestClient(create_app(s)) as client:
        health = client.get("/healthz").json()
    msgs = [r.getMessage() for r in caplog.records if r.name == "server.app"]
    steps = [m for m in msgs if m.startswith("start-up ")]
    assert len(steps) == 4, steps
    assert steps[0].startswith("start-up 1/3: loading model 'tiny' on cpu")
    assert steps[1].startswith("start-up 2/3: timing the deformation MLP in fp32 and bf16")
    assert steps[2].startswith("start-up 3/3: warming up: one reconstruction and 1 frames")
    assert steps[3].startswith("start-up done in ")
    assert any(m.startswith("deformation MLP precision: ") for m in msgs)
    mlp = health["mlp"]
    assert mlp["precision"] in ("fp32", "bf16") and mlp["choice"]["precision"] == mlp["precision"]
    assert mlp["choice"]["reason"] == "measured" and mlp["choice"]["fp32_ms"] > 0 and mlp["choice"]["bf16_ms"] > 0


def test_configured_precision_is_not_measured(tmp_path):
    from fastapi.testclient import TestClient

    from server.app import create_app
    from server.settings import Settings

    s = Settings(model="tiny", data_dir=tmp_path, compile="off", warmup=False, mlp_precision="fp32")
    with TestClient(create_app(s)) as client:
        mlp = client.get("/healthz").json()["mlp"]
    assert mlp["precision"] == "fp32" and mlp["choice"] == {"precision": "fp32", "reason": "configured", "fp32_ms": None,
                                                             "bf16_ms": None, "reps": 0, "margin": BF16_MARGIN}


def test_serve_refuses_a_busy_port_before_loading_anything():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        proc = subprocess.run(
            [sys.executable, "-m", "fastgha_core.cli", "serve", "--port", str(port), "--data-dir", "unused"],
            capture_output=True, text=True, timeout=300, cwd=REPO,
        )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert lines == [f"fastgha serve: error: port {port} on 127.0.0.1 is already in use (another server?); stop it or choose another --port"]
    assert "loading model" not in proc.stdout + proc.stderr


def test_bind_listening_socket_reports_unresolvable_hosts():
    from fastgha_core.cli import CLIError
    from fastgha_core.commands.serve import bind_listening_socket

    sock = bind_listening_socket("127.0.0.1", 0)
    try:
        assert sock.getsockname()[0] == "127.0.0.1"
    finally:
        sock.close()
    with pytest.raises(CLIError, match="does not resolve"):
        bind_listening_socket("no-such-host.invalid", 8000)


def test_serve_says_where_it_answers_once_it_does(tmp_path):
    """`fastgha serve` binds its port before the slow start-up, and uvicorn logs no "running on"
    line for a socket handed to it: the log ended at "Application startup complete." without the
    address of the browser demo. Once /healthz answers, the log holds a "ready: URL" line."""
    import re

    from server_process import ServerProcess, make_model_dir

    srv = ServerProcess(make_model_dir(tmp_path / "model"), tmp_path / "data", None, tmp_path / "server.log",
                        serve_cli=True, FASTGHA_WARMUP="false")  # fmt: skip
    try:
        log = srv.log_path.read_text()
    finally:
        srv.stop()
    ready = [ln for ln in log.splitlines() if "ready: " in ln]
    assert len(ready) == 1, log[-3000:]
    assert re.search(rf"ready: answering at http://127\.0\.0\.1:{srv.port}/; browser demo at /, API docs at /docs; Ctrl-C stops", ready[0])
    assert log.index("start-up done") < log.index(ready[0])


def test_the_ready_line_names_an_address_a_browser_can_open():
    from fastgha_core.commands.serve import ready_url

    assert ready_url("127.0.0.1", 8000) == "http://127.0.0.1:8000/"
    assert ready_url("::1", 8001) == "http://[::1]:8001/"
    assert ready_url("0.0.0.0", 8000) == "http://0.0.0.0:8000/ (every interface; on this machine http://127.0.0.1:8000/)"
    assert ready_url("::", 8000) == "http://[::]:8000/ (every interface; on this machine http://[::1]:8000/)"
