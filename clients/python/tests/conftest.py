"""Fixtures: mpiflow servers on free loopback ports.

Two kinds of server run the same tests:
- "real": the Rust `mpiflow serve` ($MPIFLOW_BIN, default <repo>/target/release/mpiflow). When
  MPIFLOW_BIN is set (tools/test.sh sets it) a missing binary is an error; otherwise the real
  tests are skipped when it has not been built.
- "fake" (only with MPIFLOW_TEST_FAKE=1): tests/fake_server.py, a small Python stand-in with the
  same API and command line, for working on the client without the Rust build. CI runs the
  real server only.
"""
from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import List, Optional

import pytest

HERE = Path(__file__).resolve().parent
CLIENT_ROOT = HERE.parent
REPO = CLIENT_ROOT.parent.parent
sys.path.insert(0, str(CLIENT_ROOT))  # the package in the tree (also when not installed)

import mpiflow  # noqa: E402

START_TIMEOUT = float(os.environ.get("MPIFLOW_TEST_START_TIMEOUT", "180"))


_REAL: List[Optional[Path]] = []


def real_binary() -> Optional[Path]:
    """The real server binary when it is built and has `serve`; None (skip) otherwise, unless
    MPIFLOW_BIN names it explicitly, when a missing or `serve`-less binary is an error."""
    if _REAL:
        return _REAL[0]
    env = os.environ.get("MPIFLOW_BIN")
    path = Path(env) if env else REPO / "target" / "release" / "mpiflow"
    found: Optional[Path] = None
    problem = f"{path} is not an executable file"
    if path.is_file() and os.access(path, os.X_OK):
        r = subprocess.run([str(path), "serve", "--help"], capture_output=True, text=True, timeout=60)
        if r.returncode == 0:
            found = path
        else:
            problem = f"{path} has no working `serve` subcommand: {r.stderr.strip()[:200]}"
    if found is None and env:
        raise RuntimeError(f"MPIFLOW_BIN: {problem}")
    _REAL.append(found)
    return found


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """One server process. `address` is HOST:PORT from its printed line."""

    def __init__(self, kind: str, addr: str = "127.0.0.1:0", extra: Optional[List[str]] = None,
                 client_kw: Optional[dict] = None):
        self.kind = kind
        self.extra = list(extra or [])
        # Client arguments that reach this server (TLS) for the readiness wait.
        self.client_kw = dict(client_kw or {})
        self.bind = addr
        self.proc: Optional[subprocess.Popen] = None
        self.address: Optional[str] = None
        self.log = tempfile.NamedTemporaryFile(prefix=f"mpiflow-{kind}-", suffix=".log", delete=False)
        # A crop small enough to keep the tests quick, and the sample size behind it.
        self.crop = (160, 120) if kind == "real" else (32, 24)

    def argv(self) -> List[str]:
        if self.kind == "real":
            exe = real_binary()
            assert exe is not None
            return [str(exe), "serve", "--addr", self.bind, "--metrics-addr", "127.0.0.1:0", *self.extra]
        return [sys.executable, str(HERE / "fake_server.py"), "serve", "--addr", self.bind,
                "--delay", "0.02", *self.extra]

    def start(self, timeout: float = START_TIMEOUT) -> "Server":
        self.proc = subprocess.Popen(
            self.argv(), stdout=subprocess.PIPE, stderr=self.log, stdin=subprocess.DEVNULL,
            text=True, cwd=str(REPO),
        )
        lines: "queue.Queue[Optional[str]]" = queue.Queue()

        def pump(out):
            for line in out:
                lines.put(line)
            lines.put(None)

        threading.Thread(target=pump, args=(self.proc.stdout,), daemon=True).start()
        deadline = time.monotonic() + timeout
        while True:
            try:
                line = lines.get(timeout=max(0.01, deadline - time.monotonic()))
            except queue.Empty:
                self.stop()
                raise RuntimeError(f"{self.kind} server printed no address in {timeout:.0f} s\n{self.tail()}")
            if line is None:
                raise RuntimeError(f"{self.kind} server exited ({self.proc.wait()})\n{self.tail()}")
            if line.startswith("mpiflow serving on "):
                self.address = line.strip().rsplit(" ", 1)[1]
                break
        # The first run after the bind keeps the port for restarts.
        self.bind = self.address
        c = mpiflow.Client(self.address, wait=False, **self.client_kw)
        try:
            c.wait_ready(max(1.0, deadline - time.monotonic()))
        except mpiflow.NotReadyError as e:
            raise RuntimeError(f"{e}\n{self.tail()}") from None
        finally:
            c.close()
        return self

    def tail(self, n: int = 30) -> str:
        try:
            return "\n".join(Path(self.log.name).read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""

    def kill(self, sig: int = signal.SIGKILL) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def stop(self) -> None:
        self.kill(signal.SIGTERM)

    def restart(self) -> "Server":
        self.kill()
        return self.start()


def _kinds() -> List[str]:
    # the fake stand-in only on request (client development without the Rust build)
    return ["fake", "real"] if os.environ.get("MPIFLOW_TEST_FAKE") == "1" else ["real"]


@pytest.fixture(scope="session", params=_kinds())
def kind(request) -> str:
    if request.param == "real" and real_binary() is None:
        pytest.skip("target/release/mpiflow not built (set MPIFLOW_BIN)")
    return request.param


@pytest.fixture(scope="session")
def server(kind):
    s = Server(kind).start()
    yield s
    s.stop()


@pytest.fixture
def spawn(kind):
    """A factory of extra servers of the current kind, all stopped at the end of the test."""
    started: List[Server] = []

    def make(**kw) -> Server:
        s = Server(kind, **kw).start()
        started.append(s)
        return s

    yield make
    for s in started:
        s.kill()


@pytest.fixture
def client(server):
    c = mpiflow.Client(server.address, timeout=60)
    yield c
    c.close()
