"""`wtbench view` as a real process, without a browser: it serves the viewer page from this machine, Ctrl-C stops
it cleanly (exit 0, no traceback), and bad options are one line naming the option and the fix."""

from __future__ import annotations

import dataclasses
import os
import select
import signal
import socket
import subprocess
import sys
import time
import urllib.request
import warnings

import pytest
import torch
from typer.testing import CliRunner

from benchmarks.cli import app
from benchmarks.runner.runs import RunRequest, execute
from methods.registry import get_method
from worldtree.infra.errors import UserError


def _view(*args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "benchmarks.cli", "view", *args],
        capture_output=True,
        text=True,
        timeout=120,
        **kw,
    )


def _one_error_line(out: subprocess.CompletedProcess, needle: str) -> None:
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], out.stderr


def test_busy_port_is_one_line_before_loading(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        # The run folder is not even read: the port is checked first.
        _one_error_line(_view(str(tmp_path), "--port", str(port)), f"--port {port} is in use")


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--host", "no-such-host.invalid", "--port", "0"], "--host no-such-host.invalid"),
        (["--port", "70000"], "--port 70000: not a port number"),
        (["--port", "0"], "no such run folder"),  # checked once the address is
    ],
)
def test_bad_input_is_a_user_error(tmp_path, args, needle):
    res = CliRunner().invoke(app, ["view", str(tmp_path / "nothing"), *args])
    assert isinstance(res.exception, UserError) and needle in str(res.exception), res.output


@pytest.fixture
def static_run(tmp_path, monkeypatch, write_tiny_scene):
    spec = get_method("static")
    quick = spec.presets["quick"]
    monkeypatch.setitem(spec.presets, "quick", lambda: dataclasses.replace(quick(), init_num_points=200))
    scene = write_tiny_scene(tmp_path / "scenes" / "tiny")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # no LPIPS weights here
        res = execute(
            RunRequest(scene=scene, method="static", runs_dir=tmp_path / "runs", preset="quick", device="cpu",
                       overrides={"steps": 3}, progress=False)
        )  # fmt: skip
    torch.set_num_threads(1)
    return res.folder.root


def test_serves_the_page_and_stops_on_ctrl_c(static_run):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "benchmarks.cli", "view", str(static_run), "--port", "0", "--device", "cpu"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        # As a shell's background job: SIGINT ignored; the viewer still stops on it.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    try:
        url, seen = None, []
        deadline = time.monotonic() + 90
        while url is None and time.monotonic() < deadline and proc.poll() is None:
            ready, _, _ = select.select([proc.stdout], [], [], 1.0)
            if ready:
                line = proc.stdout.readline()
                seen.append(line)
                if line.startswith("viewer of "):
                    url = line.split(" at ", 1)[1].split()[0]
        assert url is not None and url.startswith("http://127.0.0.1:"), "".join(seen) + proc.stderr.read()
        with urllib.request.urlopen(url, timeout=30) as resp:
            page = resp.read().decode("utf-8", "replace")
        assert resp.status == 200 and "<html" in page.lower()
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=90)  # a guard against a hang, generous for loaded machines
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
    assert proc.returncode == 0, err
    assert "viewer stopped" in out and "Traceback" not in err
