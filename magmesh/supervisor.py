"""The launcher: hosts the mesh's Zenoh router, starts every process of a manifest, restarts the ones
that die (with backoff), shows a live status line, and stops everything cleanly.

It is itself a service (role ``supervisor``) with a liveliness token and a status queryable, plus a
control queryable (``magmesh/svc/supervisor/{name}/control``) through which ``magmesh swap`` asks it to
hand a role over to another implementation.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack

from schemas import keys

from . import __version__, zconf

log = logging.getLogger("magmesh.supervisor")

#: a process that ran this long before dying restarts at the shortest backoff again
HEALTHY_AFTER_S = 3.0


@dataclass
class ProcessSpec:
    name: str
    module: str
    vehicle: str | None = None
    vehicles: str | None = None
    settings: dict = field(default_factory=dict)
    enabled: bool = True
    args: list = field(default_factory=list)

    @property
    def is_publisher(self) -> bool:
        return self.module.startswith("sim_publishers.")


@dataclass
class Manifest:
    path: Path
    endpoint: str
    restart_backoff_s: list[float]
    status_period_s: float
    vehicles: dict
    processes: list[ProcessSpec]
    connect: list[str] = field(default_factory=list)  # other routers (other hosts) to link to
    zenoh_config: str | None = None  # a Zenoh JSON5 file for the router (TLS, access control, ...)


def load_manifest(path: str | os.PathLike) -> Manifest:
    p = Path(path)
    with open(p, "rb") as f:
        raw = tomllib.load(f)
    mesh = raw.get("mesh", {})
    procs = []
    names = set()
    for i, entry in enumerate(raw.get("process", [])):
        try:
            spec = ProcessSpec(**entry)
        except TypeError as e:
            raise ValueError(f"{p}: [[process]] #{i + 1}: {e}") from None
        if spec.name in names:
            raise ValueError(f"{p}: process name {spec.name!r} appears twice")
        keys.check_id(spec.name, "process name")
        if spec.vehicle:
            keys.check_id(spec.vehicle)
        names.add(spec.name)
        procs.append(spec)
    zcfg = mesh.get("zenoh_config")
    if zcfg and not Path(zcfg).is_absolute():
        zcfg = str((p.parent / zcfg).resolve())
    return Manifest(p, mesh.get("endpoint", zconf.DEFAULT_ENDPOINT), list(mesh.get("restart_backoff_s", [0.2, 0.5, 1, 2, 5])),
                    float(mesh.get("status_period_s", 1.0)), raw.get("vehicles", {}), procs,
                    list(mesh.get("connect", [])), zcfg)


def _setting_arg(k: str, v: Any) -> str:
    return f"{k}={v if isinstance(v, str) else json.dumps(v)}"


def command_for(spec: ProcessSpec, endpoint: str, manifest_path: Path, impl_override: str | None = None,
                instance: str | None = None) -> list[str]:
    cmd = [sys.executable, "-m", spec.module, "--connect", endpoint, "--instance", instance or spec.name,
           "--manifest", str(manifest_path)]
    if spec.vehicle:
        cmd += ["--vehicle", spec.vehicle]
    if spec.vehicles:
        cmd += ["--vehicles", spec.vehicles]
    for k, v in spec.settings.items():
        cmd += ["--set", _setting_arg(k, v)]
    cmd += [str(a) for a in spec.args]
    if impl_override:
        cmd += ["--impl", impl_override]
    return cmd


class Child:
    """One supervised OS process."""

    def __init__(self, spec: ProcessSpec, cmd: list[str], log_path: Path, backoff: list[float]):
        self.spec = spec
        self.cmd = cmd
        self.log_path = log_path
        self.backoff = backoff
        self.proc: subprocess.Popen | None = None
        self.restarts = 0
        self.fails_in_row = 0
        self.started_at = 0.0
        self.next_start = 0.0
        self.last_exit: int | None = None
        self.last_restart_delay_s: float | None = None
        self.died_at: float | None = None

    def start(self) -> None:
        logf = open(self.log_path, "ab", buffering=0)
        env = dict(os.environ)
        env.setdefault("PYTHONUNBUFFERED", "1")
        self.proc = subprocess.Popen(self.cmd, stdout=logf, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     env=env, cwd=os.getcwd(), start_new_session=True)
        logf.close()
        self.started_at = time.monotonic()
        if self.died_at is not None:
            self.last_restart_delay_s = self.started_at - self.died_at
            self.died_at = None

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def check(self, now: float) -> str | None:
        """Restart a dead child when its backoff has passed; return an event string."""
        if self.proc is None:
            return None
        rc = self.proc.poll()
        if rc is None:
            return None
        if self.died_at is None:
            if now - self.started_at >= HEALTHY_AFTER_S:
                self.fails_in_row = 0  # it ran fine: this is a fault, not a crash loop
            self.died_at = now
            self.last_exit = rc
            delay = self.backoff[min(self.fails_in_row, len(self.backoff) - 1)]
            self.fails_in_row += 1
            self.next_start = now + delay
            return f"{self.spec.name} exited with code {rc}; restarting in {delay:g} s"
        if now >= self.next_start:
            self.restarts += 1
            self.start()
            return f"{self.spec.name} restarted (restart #{self.restarts})"
        return None

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.alive:
            try:
                os.killpg(self.proc.pid, sig)
            except ProcessLookupError:
                pass


class Supervisor:
    def __init__(self, manifest: Manifest, endpoint: str | None = None, log_dir: Path | None = None,
                 name: str = "main", quiet: bool = False):
        self.m = manifest
        self.endpoint = endpoint or manifest.endpoint
        self.name = name
        self.quiet = quiet
        self.log_dir = Path(log_dir or Path(".magmesh") / "logs" / time.strftime("%Y%m%d-%H%M%S"))
        self.children: dict[str, Child] = {}
        self.stop_event = threading.Event()
        self.lock = threading.Lock()
        self.started = time.monotonic()
        self.session = None
        self.last_status: dict[str, dict] = {}
        self.alarm_counts: dict[str, int] = {}
        self.raised: set[str] = set()
        self.events: list[str] = []
        self.swapper = None  # set by magmesh.swap when available
        self.client_config = None  # ProcessSpec -> Zenoh config file of its role (magmesh up --secure)

    # ---- zenoh side -----------------------------------------------------------------------
    def open(self) -> None:
        import zenoh

        if self.m.zenoh_config:
            conf = zconf.build_config(config_file=self.m.zenoh_config)
        else:
            conf = zconf.build_config(mode="router", listen=[self.endpoint], connect=self.m.connect or None)
        self.session = zenoh.open(conf)
        self.token = self.session.liveliness().declare_token(keys.svc_token("supervisor", self.name))
        self.q_status = self.session.declare_queryable(keys.svc_status("supervisor", self.name),
                                                       zenoh.handlers.FifoChannel(16))
        self.q_control = self.session.declare_queryable(keys.svc_control("supervisor", self.name),
                                                        zenoh.handlers.FifoChannel(16))
        self.sub_alarms = self.session.declare_subscriber(keys.alarms_all("*"), zenoh.handlers.FifoChannel(1024))
        for target in (self._serve_status, self._serve_control, self._watch_alarms, self._poll_status):
            threading.Thread(target=target, daemon=True).start()

    def _serve_status(self) -> None:
        while True:
            try:
                q = self.q_status.recv()
            except Exception:
                return
            try:
                q.reply(keys.svc_status("supervisor", self.name), msgpack.packb(self.status(), use_bin_type=True))
            except Exception as e:  # pragma: no cover
                log.warning("status reply failed: %s", e)
            finally:
                q.drop()

    def _serve_control(self) -> None:
        while True:
            try:
                q = self.q_control.recv()
            except Exception:
                return
            try:
                params = msgpack.unpackb(q.payload.to_bytes()) if q.payload is not None else {}
                result = self.control(params)
                q.reply(keys.svc_control("supervisor", self.name), msgpack.packb(result, use_bin_type=True))
            except Exception as e:
                q.reply(keys.svc_control("supervisor", self.name),
                        msgpack.packb({"ok": False, "error": f"{type(e).__name__}: {e}"}, use_bin_type=True))
            finally:
                q.drop()

    def _watch_alarms(self) -> None:
        while True:
            try:
                s = self.sub_alarms.recv()
            except Exception:
                return
            try:
                msg = msgpack.unpackb(s.payload.to_bytes())
                k = str(s.key_expr)
                with self.lock:
                    if msg.get("state") == "raised":
                        self.raised.add(k)
                        self.alarm_counts[k] = self.alarm_counts.get(k, 0) + 1
                    else:
                        self.raised.discard(k)
            except Exception:
                continue

    def _poll_status(self) -> None:
        while not self.stop_event.wait(self.m.status_period_s):
            try:
                got = {}
                for rep in self.session.get(keys.svc_status_all(), timeout=1.0):
                    if rep.ok is None:
                        continue
                    st = msgpack.unpackb(rep.ok.payload.to_bytes())
                    if st.get("role") != "supervisor":
                        got[st.get("instance")] = st
                self.last_status = got
            except Exception:
                continue

    def control(self, params: dict) -> dict:
        op = params.get("op")
        if op == "swap":
            if self.swapper is None:
                from .swap import Swapper

                self.swapper = Swapper(self)
            return self.swapper.swap(params.get("role", ""), params.get("impl", ""),
                                     float(params.get("timeout_s", 20)))
        if op == "restart":
            ch = self.children.get(params.get("name", ""))
            if ch is None:
                return {"ok": False, "error": f"no process named {params.get('name')!r}"}
            ch.stop(signal.SIGKILL)
            return {"ok": True}
        return {"ok": False, "error": f"unknown op {op!r} (known: swap, restart)"}

    def status(self) -> dict:
        now = time.monotonic()
        procs = {}
        for name, ch in list(self.children.items()):
            procs[name] = {"module": ch.spec.module, "alive": ch.alive, "pid": ch.proc.pid if ch.proc else None,
                           "restarts": ch.restarts, "last_exit": ch.last_exit,
                           "last_restart_delay_s": ch.last_restart_delay_s,
                           "uptime_s": round(now - ch.started_at, 2) if ch.alive else 0.0}
        with self.lock:
            raised = sorted(self.raised)
        return {"type": "status", "version": 1, "role": "supervisor", "impl": "supervisor", "instance": self.name,
                "pid": os.getpid(), "magmesh_version": __version__, "uptime_s": round(now - self.started, 2),
                "endpoint": self.endpoint, "manifest": str(self.m.path), "processes": procs,
                "alarms_raised": raised, "log_dir": str(self.log_dir)}

    # ---- process side ---------------------------------------------------------------------
    def add_child(self, spec: ProcessSpec, impl_override: str | None = None, instance: str | None = None,
                  start: bool = True) -> Child:
        name = instance or spec.name
        cmd = command_for(spec, self.endpoint, self.m.path, impl_override, name)
        if self.client_config is not None:  # the secured mesh: each process with its role's certificate
            cmd += ["--config", self.client_config(spec)]
        ch = Child(spec, cmd, self.log_dir / f"{name}.log", self.m.restart_backoff_s)
        if start:
            ch.start()
        with self.lock:
            self.children[name] = ch
        return ch

    def remove_child(self, name: str, sig: int = signal.SIGTERM, wait_s: float = 3.0) -> None:
        with self.lock:
            ch = self.children.pop(name, None)
        if ch is None:
            return
        ch.stop(sig)
        try:
            ch.proc.wait(wait_s)
        except subprocess.TimeoutExpired:
            ch.stop(signal.SIGKILL)
            ch.proc.wait(2)

    def event(self, text: str) -> None:
        log.info(text)
        self.events.append(f"{time.strftime('%H:%M:%S')} {text}")
        del self.events[:-50]

    def line(self) -> str:
        st = self.last_status
        alive = sum(1 for c in list(self.children.values()) if c.alive)
        restarts = sum(c.restarts for c in list(self.children.values()))
        rate_in = sum(v.get("rate_hz", 0) for s in st.values() for v in s.get("in", {}).values())
        rejects = sum(s.get("rejects", 0) for s in st.values())
        drops = sum(s.get("drops_total", 0) for s in st.values())
        with self.lock:
            raised = sorted(k.split("/", 1)[1] for k in self.raised)
        up = time.monotonic() - self.started
        return (f"magmesh up {up:6.0f}s | {alive}/{len(self.children)} processes, {len(st)} services answering"
                f" | in {rate_in:7.0f} msg/s | rejects {rejects} drops {drops} | restarts {restarts}"
                f" | alarms raised: {', '.join(raised) if raised else 'none'}")

    def run(self, duration_s: float | None = None) -> int:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.open()
        for spec in self.m.processes:
            if spec.enabled:
                self.add_child(spec)
        self.event(f"mesh up on {self.endpoint}: {len(self.children)} processes; logs in {self.log_dir}")
        tty = sys.stdout.isatty() and not self.quiet
        if not self.quiet:
            print(f"magmesh {__version__}: Zenoh endpoint {self.endpoint} (any Zenoh client can attach), "
                  f"{len(self.children)} processes, logs in {self.log_dir}. Ctrl-C stops.", flush=True)

        def _sig(signum: int, frame: Any) -> None:
            self.stop_event.set()

        signal.signal(signal.SIGINT, _sig)
        signal.signal(signal.SIGTERM, _sig)
        deadline = time.monotonic() + duration_s if duration_s else None
        last_line = 0.0
        n_events = 0
        try:
            while not self.stop_event.wait(0.05):
                now = time.monotonic()
                for ch in list(self.children.values()):
                    ev = ch.check(now)
                    if ev:
                        self.event(ev)
                if not self.quiet:
                    while n_events < len(self.events):
                        if tty:
                            sys.stdout.write("\r\033[K")
                        print(self.events[n_events], flush=True)
                        n_events += 1
                    period = self.m.status_period_s if tty else 10.0
                    if now - last_line >= period:
                        last_line = now
                        if tty:
                            sys.stdout.write("\r\033[K" + self.line())
                            sys.stdout.flush()
                        else:
                            print(self.line(), flush=True)
                if deadline and now >= deadline:
                    break
        finally:
            if tty:
                print()
            self.shutdown()
        return 0

    def shutdown(self) -> None:
        self.stop_event.set()
        for ch in list(self.children.values()):
            ch.stop(signal.SIGTERM)
        t0 = time.monotonic()
        for ch in list(self.children.values()):
            if ch.proc is None:
                continue
            try:
                ch.proc.wait(max(0.1, 3.0 - (time.monotonic() - t0)))
            except subprocess.TimeoutExpired:
                ch.stop(signal.SIGKILL)
                ch.proc.wait(2)
        if self.session is not None:
            try:
                self.token.undeclare()
            except Exception:
                pass
            self.session.close()
        if not self.quiet:
            print(f"magmesh stopped ({len(self.children)} processes)", flush=True)
