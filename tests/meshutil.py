"""Helpers for mesh tests: real processes on loopback with unique ports, every wait bounded."""

from __future__ import annotations

import fcntl
import os
import queue
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import msgpack

REPO = Path(__file__).resolve().parent.parent


# Ports are drawn below the kernel's ephemeral range (so no outgoing connection takes one between the check and
# the bind) and reserved across processes with a lock file held open for the life of this process: test runs
# started side by side never get the same port, and a crashed run's reservations vanish with it.
_PORT_RANGE = (20000, 32000)
_PORT_LOCK_DIR = Path(os.environ.get("MAGMESH_TEST_PORT_DIR", "/tmp/magmesh-test-ports"))
_held: dict[int, Any] = {}
_port_rng = random.Random(os.getpid() ^ time.monotonic_ns())


def _reserve(port: int) -> bool:
    _PORT_LOCK_DIR.mkdir(parents=True, exist_ok=True)
    f = open(_PORT_LOCK_DIR / str(port), "a")
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.close()
        return False
    _held[port] = f
    return True


def _bindable(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_port() -> int:
    """A loopback TCP/UDP port that no other test of any concurrent run holds; the one port helper of the tests."""
    for _ in range(2000):
        port = _port_rng.randrange(*_PORT_RANGE)
        if port in _held or not _reserve(port):
            continue
        if _bindable(port):
            return port
        _held.pop(port).close()
    raise RuntimeError(f"no free port in {_PORT_RANGE} after 2000 tries")


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def open_router(port: int):
    import zenoh

    from magmesh import zconf

    return zenoh.open(zconf.build_config(mode="router", listen=[endpoint(port)]))


def open_client(port: int):
    import zenoh

    from magmesh import zconf

    return zenoh.open(zconf.build_config(connect=[endpoint(port)]))


def spawn(module: str, port: int, *args: str, log_path: Path | None = None, env: dict | None = None) -> subprocess.Popen:
    """Start ``python -m module --connect tcp/127.0.0.1:port args...`` as its own process group."""
    e = dict(os.environ)
    e["PYTHONUNBUFFERED"] = "1"
    e.setdefault("MAGMESH_LOG_LEVEL", "INFO")
    e.update(env or {})
    out = open(log_path, "ab") if log_path else subprocess.DEVNULL
    return subprocess.Popen([sys.executable, "-m", module, "--connect", endpoint(port), *args], cwd=REPO,
                            stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=e,
                            start_new_session=True)


def stop(proc: subprocess.Popen, timeout: float = 5.0) -> int | None:
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGINT)
        except ProcessLookupError:
            pass
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5)
    return proc.returncode


class Collector:
    """Subscribe to a key expression and keep every (key, decoded msg) in arrival order."""

    def __init__(self, session: Any, keyexpr: str):
        import zenoh

        self.items: list[tuple[str, Any]] = []
        self.cond = threading.Condition()
        self.sub = session.declare_subscriber(keyexpr, zenoh.handlers.FifoChannel(100_000))
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while True:
            try:
                s = self.sub.recv()
            except Exception:
                return
            b = s.payload.to_bytes()
            try:
                m = msgpack.unpackb(b)
            except Exception:
                m = b
            with self.cond:
                self.items.append((str(s.key_expr), m))
                self.cond.notify_all()

    def wait_for(self, pred, timeout: float) -> list[tuple[str, Any]]:
        """Wait until some item satisfies pred(key, msg); return all matching items (maybe empty)."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                hits = [(k, m) for k, m in self.items if pred(k, m)]
                if hits:
                    return hits
                left = deadline - time.monotonic()
                if left <= 0:
                    return []
                self.cond.wait(min(left, 0.5))

    def matching(self, pred) -> list[tuple[str, Any]]:
        with self.cond:
            return [(k, m) for k, m in self.items if pred(k, m)]


def wait_alive(session: Any, token_key: str, timeout: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if any(r.ok is not None for r in session.liveliness().get(token_key, timeout=1.0)):
            return True
        time.sleep(0.1)
    return False


def query_status(session: Any, key: str, timeout: float = 3.0) -> dict | None:
    for rep in session.get(key, timeout=timeout):
        if rep.ok is not None:
            return msgpack.unpackb(rep.ok.payload.to_bytes())
    return None


__all__ = ["free_port", "endpoint", "open_router", "open_client", "spawn", "stop", "Collector", "wait_alive",
           "query_status", "queue"]
