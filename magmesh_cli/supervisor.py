"""The launcher: hosts the mesh's Zenoh router, starts every process of a manifest, restarts the ones
that die (with backoff), shows a live status line, and stops everything cleanly.

It is itself a service (role ``supervisor``) with a liveliness token and a status queryable, plus a
control queryable (``magmesh/svc/supervisor/{name}/control``) through which ``magmesh swap`` asks it to
hand a role over to another implementation.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
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

from magmesh import __version__, groups, zconf
from magmesh.errors import UserError
from schemas import keys

log = logging.getLogger("magmesh_cli.supervisor")

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
    #: run as a role group of this many instances ``<name>-1..N`` sharing the vehicles (``magmesh scale``)
    instances: int | None = None

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
    give_up_after: int = 5  # a process failing this many times in a row on start is given up


class ManifestError(UserError):
    """A mistake in a mesh manifest (or in ``magmesh up`` flags naming its processes): one paragraph, exit 2."""


#: the tables of a manifest, the keys of [mesh] and of each [[process]]
MANIFEST_TABLES = ("mesh", "vehicles", "process")
MESH_KEYS = ("endpoint", "restart_backoff_s", "status_period_s", "give_up_after", "connect", "zenoh_config")
PROCESS_KEYS = tuple(f.name for f in dataclasses.fields(ProcessSpec))
PROCESS_REQUIRED = ("name", "module")
#: a process that fails this many times in a row on start is given up (``[mesh] give_up_after``)
GIVE_UP_AFTER = 5
#: the most instances a group process may run (``instances = N``, ``magmesh scale``)
MAX_INSTANCES = 64


def _did_you_mean(word: str, known) -> str:
    close = difflib.get_close_matches(str(word), list(known), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _type_problem(where: str, key: str, value: Any, want: str) -> str | None:
    ok = {"str": isinstance(value, str), "bool": isinstance(value, bool), "table": isinstance(value, dict),
          "list of str": isinstance(value, list) and all(isinstance(x, str) for x in value),
          "number": isinstance(value, (int, float)) and not isinstance(value, bool),
          "list of numbers": isinstance(value, list) and bool(value)
          and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value),
          "int": isinstance(value, int) and not isinstance(value, bool)}[want]
    return None if ok else f"{where}: {key} must be a {want}, got {type(value).__name__} {value!r:.60}"


_PROCESS_TYPES = {"name": "str", "module": "str", "vehicle": "str", "vehicles": "str", "settings": "table",
                  "enabled": "bool", "args": "list of str", "instances": "int"}
_MESH_TYPES = {"endpoint": "str", "restart_backoff_s": "list of numbers", "status_period_s": "number",
               "give_up_after": "int", "connect": "list of str", "zenoh_config": "str"}


def load_manifest(path: str | os.PathLike) -> Manifest:
    """Read and check the structure of a manifest; every problem is a :class:`ManifestError` naming the file,
    the process and the key (with the known keys), never a traceback. See :func:`check_processes` for the
    deeper check of modules, implementations and settings."""
    p = Path(path)
    if not p.exists():
        raise ManifestError(f"manifest {p}: no such file. Give the path of a mesh manifest (TOML), for example "
                            f"deploy/mesh.toml.")
    if not p.is_file():
        raise ManifestError(f"manifest {p}: not a file (a mesh manifest is one TOML file, e.g. deploy/mesh.toml).")
    try:
        with open(p, "rb") as f:
            raw = tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise ManifestError(f"manifest {p}: not valid TOML: {e}.") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ManifestError(f"manifest {p}: cannot be read: {e}.") from None
    problems: list[str] = []
    for k in raw:
        if k not in MANIFEST_TABLES:
            problems.append(f"unknown table [{k}]{_did_you_mean(k, MANIFEST_TABLES)}; known: "
                            f"{', '.join(MANIFEST_TABLES)}")
    mesh = raw.get("mesh", {})
    if not isinstance(mesh, dict):
        problems.append("[mesh] must be a table")
        mesh = {}
    for k, v in mesh.items():
        if k not in MESH_KEYS:
            problems.append(f"[mesh]: unknown key {k!r}{_did_you_mean(k, MESH_KEYS)}; known: {', '.join(MESH_KEYS)}")
        elif (tp := _type_problem("[mesh]", k, v, _MESH_TYPES[k])) is not None:
            problems.append(tp)
    if isinstance(mesh.get("give_up_after"), int) and mesh["give_up_after"] < 1:
        problems.append("[mesh]: give_up_after must be at least 1")
    vehicles = raw.get("vehicles", {})
    if not isinstance(vehicles, dict) or not all(isinstance(v, dict) for v in vehicles.values()):
        problems.append("[vehicles] must hold one table per vehicle ([vehicles.car-1] ...)")
        vehicles = {}
    for v in vehicles:
        try:
            keys.check_id(v, "vehicle id")
        except keys.KeyError_ as e:
            problems.append(f"[vehicles.{v}]: {e}")
    entries = raw.get("process", [])
    if not isinstance(entries, list):
        problems.append("process must be an array of tables ([[process]] ...)")
        entries = []
    procs = []
    names: set[str] = set()
    for i, entry in enumerate(entries):
        label = f"[[process]] #{i + 1}"
        if not isinstance(entry, dict):
            problems.append(f"{label}: must be a table")
            continue
        if isinstance(entry.get("name"), str):
            label += f" ({entry['name']!r})"
        bad = False
        for k in entry:
            if k not in PROCESS_KEYS:
                problems.append(f"{label}: unknown key {k!r}{_did_you_mean(k, PROCESS_KEYS)}; known: "
                                f"{', '.join(PROCESS_KEYS)}")
                bad = True
            elif (tp := _type_problem(label, k, entry[k], _PROCESS_TYPES[k])) is not None:
                problems.append(tp)
                bad = True
        for k in PROCESS_REQUIRED:
            if k not in entry:
                problems.append(f"{label}: missing key {k!r} (required: {', '.join(PROCESS_REQUIRED)}; known: "
                                f"{', '.join(PROCESS_KEYS)})")
                bad = True
        if bad:
            continue
        spec = ProcessSpec(**entry)
        if spec.instances is not None and (not 1 <= spec.instances <= MAX_INSTANCES or spec.is_publisher
                                           or spec.vehicle):
            problems.append(f"{label}: instances must be a whole number from 1 to {MAX_INSTANCES}, on a service "
                            f"(not on a publisher, nor on a process with one vehicle); got {spec.instances}")
            continue
        try:
            keys.check_id(spec.name, "process name")
            if spec.vehicle:
                keys.check_id(spec.vehicle, "vehicle")
            if spec.vehicles:
                keys.check_pattern(spec.vehicles, "vehicles pattern")
        except keys.KeyError_ as e:
            problems.append(f"{label}: {e}")
            continue
        if spec.name in names:
            problems.append(f"process name {spec.name!r} appears twice")
            continue
        names.add(spec.name)
        procs.append(spec)
    for spec in procs:  # a group's instances are named <name>-1..N: none may be another process's name
        if spec.instances is not None:
            clash = [p.name for p in procs if p is not spec and p.name.startswith(spec.name + "-")
                     and p.name[len(spec.name) + 1:].isdigit()]
            if clash:
                problems.append(f"process {spec.name!r} has instances = {spec.instances}, named {spec.name}-1.."
                                f"{spec.name}-{spec.instances}, but {', '.join(clash)} is another process's name")
    if problems:
        raise ManifestError(_paragraph(p, problems))
    zcfg = mesh.get("zenoh_config")
    if zcfg and not Path(zcfg).is_absolute():
        zcfg = str((p.parent / zcfg).resolve())
    return Manifest(p, mesh.get("endpoint", zconf.DEFAULT_ENDPOINT), list(mesh.get("restart_backoff_s", [0.2, 0.5, 1, 2, 5])),
                    float(mesh.get("status_period_s", 1.0)), vehicles, procs,
                    list(mesh.get("connect", [])), zcfg, int(mesh.get("give_up_after", GIVE_UP_AFTER)))


def _paragraph(path: Path, problems: list[str]) -> str:
    if len(problems) == 1:
        return f"manifest {path}: {problems[0]}."
    return f"manifest {path}: {len(problems)} problems: " + "; ".join(problems) + "."


# ---- what a module runs, without starting it -----------------------------------------------------


@functools.lru_cache(maxsize=64)
def implementations(module: str) -> tuple[dict[str, type], str]:
    """The service classes a ``python -m`` module runs, by implementation name, and the default one.

    Imports ``{module}.__main__`` (its ``if __name__ == "__main__"`` block does not run). A module listing
    several implementations exports ``IMPLEMENTATIONS`` (and ``DEFAULT_IMPL``). Raises ``ImportError`` for a
    module that does not exist and ``ValueError`` for one that runs no magmesh service."""
    import importlib
    import importlib.util

    from magmesh.runtime import Service, SimPublisher

    try:
        found = importlib.util.find_spec(module)
    except (ImportError, ValueError):
        found = None
    if found is None:
        raise ImportError(f"no module named {module!r}")
    try:
        mod = importlib.import_module(f"{module}.__main__")
    except ModuleNotFoundError as e:
        if e.name in (f"{module}.__main__", module):
            raise ImportError(f"module {module!r} cannot be run with python -m (it has no __main__)") from None
        raise ImportError(f"module {module!r} failed to import: {type(e).__name__}: {e}") from None
    except Exception as e:  # noqa: BLE001 - a broken module is a manifest problem, reported with its error
        raise ImportError(f"module {module!r} failed to import: {type(e).__name__}: {e}") from None
    impls = getattr(mod, "IMPLEMENTATIONS", None)
    if isinstance(impls, dict) and impls:
        return dict(impls), getattr(mod, "DEFAULT_IMPL", next(iter(impls)))
    classes = {c.impl: c for c in vars(mod).values()
               if isinstance(c, type) and issubclass(c, Service) and c not in (Service, SimPublisher)}
    if not classes:
        raise ValueError(f"module {module!r} runs no magmesh service")
    return classes, next(iter(classes))


def role_of_spec(spec: ProcessSpec) -> str:
    """The role a process runs (that of its implementation)."""
    impls, default = implementations(spec.module)
    return impls[spec_impl(spec) or default].role


def spec_impl(spec: ProcessSpec) -> str | None:
    """The implementation a process's ``args`` ask for (``--impl NAME``), or None for the module's default."""
    args = [str(a) for a in spec.args]
    impl = None
    for i, a in enumerate(args):
        if a == "--impl" and i + 1 < len(args):
            impl = args[i + 1]
        elif a.startswith("--impl="):
            impl = a.split("=", 1)[1]
    return impl


def check_spec(spec: ProcessSpec, impl: str | None = None) -> tuple[type, str]:
    """Check one process against its module without starting it: module, implementation, settings (names
    and values, against the implementation's settings class) and extra arguments. Returns the service class
    and implementation name; raises ``ValueError`` with the reason."""
    from magmesh.runtime import build_settings, make_parser

    try:
        impls, default = implementations(spec.module)
    except ImportError as e:
        raise ValueError(f"{e}; a module is a Python module run with python -m, e.g. services.dmc_detector "
                         f"or sim_publishers.car") from None
    name = impl or spec_impl(spec) or default
    cls = impls.get(name)
    if cls is None:
        raise ValueError(f"unknown implementation {name!r} of {spec.module}; known: {', '.join(sorted(impls))}")
    try:
        build_settings(cls.Settings, dict(spec.settings))
    except (ValueError, TypeError) as e:
        raise ValueError(f"settings for {spec.module} ({name}): {e}") from None
    extra = [str(a) for a in spec.args]
    if "--impl" in extra:
        i = extra.index("--impl")
        del extra[i:i + 2]
    extra = [a for a in extra if not a.startswith("--impl=")]
    if extra:
        _, unknown = make_parser(cls).parse_known_args(extra)
        if unknown:
            raise ValueError(f"args: {' '.join(unknown)} not understood by python -m {spec.module} (see its --help)")
    return cls, name


def check_processes(m: Manifest, all_processes: bool = False) -> None:
    """Check every enabled process (or all) of a manifest with :func:`check_spec`; one paragraph listing
    every problem (file, process, what is wrong) as a :class:`ManifestError`."""
    problems = []
    for spec in m.processes:
        if not (spec.enabled or all_processes):
            continue
        try:
            check_spec(spec)
        except ValueError as e:
            problems.append(f"process {spec.name!r}: {e}")
    if problems:
        raise ManifestError(_paragraph(m.path, problems))


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
    if spec.instances is not None:
        cmd += ["--group", spec.name]
    cmd += [str(a) for a in spec.args]
    if impl_override:
        cmd += ["--impl", impl_override]
    return cmd


class Child:
    """One supervised OS process."""

    def __init__(self, spec: ProcessSpec, cmd: list[str], log_path: Path, backoff: list[float],
                 name: str | None = None, give_up_after: int = GIVE_UP_AFTER, impl: str | None = None):
        self.spec = spec
        self.name = name or spec.name  # the instance name (a swap's new process is not its spec's name)
        self.impl = impl
        self.give_up_after = give_up_after
        #: restarted by the supervisor when it dies; off for a swap's standby process (the swap watches it)
        self.supervised = True
        self.given_up = False
        self.start_failures = 0  # exits of its own within HEALTHY_AFTER_S of the start, in a row
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
        """Restart a dead child when its backoff has passed; return an event string.

        A child that failed ``give_up_after`` times in a row, each within ``HEALTHY_AFTER_S`` of its start,
        is given up (its last log lines are in the event) and not restarted."""
        if self.proc is None or self.given_up or not self.supervised:
            return None
        rc = self.proc.poll()
        if rc is None:
            return None
        if self.died_at is None:
            if now - self.started_at >= HEALTHY_AFTER_S:
                self.fails_in_row = 0  # it ran fine: this is a fault, not a crash loop
            self.died_at = now
            self.last_exit = rc
            self.fails_in_row += 1
            # a start failure is an exit of its own (a setting, a missing file, a bad module) soon after the
            # start; a process killed by a signal (kill -9, a fault drill) is restarted however often it happens
            if rc >= 0 and now - self.started_at < HEALTHY_AFTER_S:
                self.start_failures += 1
            elif rc >= 0:
                self.start_failures = 0
            if self.start_failures >= self.give_up_after:
                self.given_up = True
                tail = "\n    ".join(self.last_lines()) or "(its log is empty)"
                return (f"{self.name} failed {self.start_failures} times in a row on start (last exit code {rc}); "
                        f"given up. Last lines of {self.log_path}:\n    {tail}")
            delay = self.backoff[min(self.fails_in_row - 1, len(self.backoff) - 1)]
            self.next_start = now + delay
            return f"{self.name} exited with code {rc}; restarting in {delay:g} s"
        if now >= self.next_start:
            self.restarts += 1
            self.start()
            return f"{self.name} restarted (restart #{self.restarts})"
        return None

    def last_lines(self, n: int = 8) -> list[str]:
        """The last ``n`` non-empty lines of the process's log (its error, for a process that failed)."""
        try:
            with open(self.log_path, "rb") as f:
                f.seek(0, os.SEEK_END)
                f.seek(max(0, f.tell() - 16384))
                text = f.read().decode("utf-8", "replace")
        except OSError:
            return []
        return [ln.rstrip()[:400] for ln in text.splitlines() if ln.strip()][-n:]

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
        self.alarms_ignored = 0  # alarm samples whose state the holding instance did not confirm
        self.events: list[str] = []
        self.swapper = None  # set by magmesh_cli.swap when available
        self.keep_going = False  # a process given up stops the mesh unless set (magmesh up --keep-going)
        self.client_config = None  # ProcessSpec -> Zenoh config file of its role (magmesh up --secure)

    # ---- zenoh side -----------------------------------------------------------------------
    def open(self) -> None:
        import zenoh

        if self.m.zenoh_config:
            conf = zconf.build_config(config_file=self.m.zenoh_config)
        else:
            conf = zconf.build_config(mode="router", listen=[self.endpoint], connect=self.m.connect or None)
        try:
            self.session = zenoh.open(conf)
        except Exception as e:  # noqa: BLE001 - e.g. the endpoint is taken: one paragraph, not a traceback
            detail = str(e).split(" at /", 1)[0]
            raise UserError(f"magmesh up: cannot host the Zenoh endpoint {self.endpoint} ({detail}). Is another "
                            f"mesh running there? Choose another with --endpoint (or [mesh] endpoint).", 1) from None
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
                claimed = msg.get("state") if isinstance(msg, dict) else None
                held = self.alarm_held(k)
                with self.lock:
                    if held and k not in self.raised:
                        self.alarm_counts[k] = self.alarm_counts.get(k, 0) + 1
                    if held:
                        self.raised.add(k)
                    else:
                        self.raised.discard(k)
                    if claimed != ("raised" if held else "cleared"):
                        self.alarms_ignored += 1  # a transition its holder does not confirm (forged or stale)
                        log.warning("alarm %s: %r not confirmed by the instance holding it; ignored", k[:200],
                                    str(claimed)[:32])
            except Exception:
                continue

    def alarm_held(self, key: str) -> bool:
        """Whether a live service instance holds ``key`` raised, asked of the instances themselves.

        The supervisor's list of raised alarms follows the holders, not the samples: a transition only makes it
        ask the services' alarm queryables (answered only by an instance holding the role, from its own state),
        so a forged "cleared" (or "raised") from anyone else changes nothing."""
        for rep in self.session.get(key, timeout=1.0, priority=zconf.control_priority()):
            if rep.ok is None:
                continue
            try:
                m = msgpack.unpackb(rep.ok.payload.to_bytes())
            except Exception:
                continue
            if isinstance(m, dict) and m.get("state") == "raised":
                return True
        return False

    def _poll_status(self) -> None:
        while not self.stop_event.wait(self.m.status_period_s):
            try:
                got = {}
                for rep in self.session.get(keys.svc_status_all(), timeout=1.0,
                                            priority=zconf.control_priority()):
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
            return self.swapper.swap(str(params.get("role", "")), str(params.get("impl", "")),
                                     float(params.get("timeout_s", 20)), instance=params.get("instance") or None,
                                     vehicles=params.get("vehicles") or None)
        if op == "scale":
            return self.scale(str(params.get("name", "")), params.get("n"))
        if op == "restart":
            ch = self.children.get(params.get("name", ""))
            if ch is None:
                return {"ok": False, "error": f"no process named {params.get('name')!r}"}
            ch.stop(signal.SIGKILL)
            return {"ok": True}
        return {"ok": False, "error": f"unknown op {op!r} (known: swap, scale, restart)"}

    # ---- role groups (instances = N): see magmesh/group_member.py ----------------------------------
    def group_children(self, name: str) -> list[str]:
        """The instances ``<name>-<k>`` of a group process, in order of k."""
        pre = f"{name}-"
        out = [(int(n[len(pre):]), n) for n in list(self.children)
               if n.startswith(pre) and n[len(pre):].isdigit() and self.children[n].spec.name == name]
        return [n for _, n in sorted(out)]

    def start_group(self, spec: ProcessSpec, n: int) -> list[str]:
        have = self.group_children(spec.name)
        k = max((int(x.rsplit("-", 1)[1]) for x in have), default=0)
        started = []
        for _ in range(n - len(have)):
            k += 1
            started.append(self.add_child(spec, instance=f"{spec.name}-{k}").name)
        return started

    def scale(self, name: str, n: Any, leave_timeout_s: float = 60.0) -> dict:
        """Run ``n`` instances of the group process ``name``: start new ones (each takes its vehicles over from
        the others after warming on them), or let the last ones leave the group (their vehicles handed over the
        same way) and stop them."""
        spec = next((s for s in self.m.processes if s.name == name), None)
        group_names = [s.name for s in self.m.processes if s.instances is not None]
        if spec is None or spec.instances is None:
            what = "is not a process of" if spec is None else "has no instances = N in"
            return {"ok": False, "error": f"{name!r} {what} this mesh's manifest ({self.m.path}); the processes that "
                    f"can be scaled: {', '.join(group_names) or 'none'} (give a [[process]] instances = N to make "
                    f"one a group)"}
        if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_INSTANCES:
            return {"ok": False, "error": f"the number of instances must be a whole number from 1 to "
                                          f"{MAX_INSTANCES}, not {n!r}"}
        have = self.group_children(name)
        t0 = time.monotonic()
        started = self.start_group(spec, n) if n > len(have) else []
        leaving = have[n:]
        handed = {}
        if leaving:
            role = role_of_spec(spec)
            for inst in leaving:
                self._control_instance(role, inst, {"op": "g_leave"})
            deadline = time.monotonic() + leave_timeout_s
            pending = set(leaving)
            while pending and time.monotonic() < deadline:
                for inst in sorted(pending):
                    st = self._control_instance(role, inst, {"op": "g_state"})
                    if st is None and self.children.get(inst) is not None and self.children[inst].alive:
                        continue  # busy: ask again
                    if st is None or (not st.get("owned") and not st.get("releasing")):
                        pending.discard(inst)
                        handed[inst] = st is not None
                time.sleep(0.2)
            for inst in leaving:
                handed.setdefault(inst, False)  # still holding vehicles: the others take them from its journal
                self.remove_child(inst)
        self.event(f"scale {name}: {len(have)} -> {n} instances" + (f" (started {', '.join(started)})" if started
                   else "") + (f" ({', '.join(leaving)} left the group and stopped)" if leaving else ""))
        return {"ok": True, "name": name, "instances": self.group_children(name), "started": started,
                "stopped": leaving, "handed_over": handed, "took_s": round(time.monotonic() - t0, 2)}

    def _control_instance(self, role: str, inst: str, req: dict, timeout: float = 2.0) -> dict | None:
        return zconf.control_request(self.session, role, inst, req, timeout)

    def groups_status(self) -> dict:
        """Per group process: its instances, the vehicles each holds (from their status) and every vehicle a
        member has seen that no member holds (``unowned``: between owners, or nobody serves it)."""
        out = {}
        st = self.last_status
        for spec in self.m.processes:
            if spec.instances is None:
                continue
            insts = self.group_children(spec.name)
            summary = groups.summarize({inst: (st.get(inst) or {}).get("group") for inst in insts})
            out[spec.name] = {"instances": insts, "configured": spec.instances, **summary}
        return out

    def status(self) -> dict:
        now = time.monotonic()
        procs = {}
        for name, ch in list(self.children.items()):
            procs[name] = {"module": ch.spec.module, "alive": ch.alive, "pid": ch.proc.pid if ch.proc else None,
                           "restarts": ch.restarts, "last_exit": ch.last_exit,
                           "last_restart_delay_s": ch.last_restart_delay_s, "given_up": ch.given_up,
                           "uptime_s": round(now - ch.started_at, 2) if ch.alive else 0.0}
        with self.lock:
            raised = sorted(self.raised)
        return {"type": "status", "version": 1, "role": "supervisor", "impl": "supervisor", "instance": self.name,
                "pid": os.getpid(), "magmesh_version": __version__, "uptime_s": round(now - self.started, 2),
                "endpoint": self.endpoint, "manifest": str(self.m.path), "processes": procs,
                "alarms_raised": raised, "alarms_ignored": self.alarms_ignored, "log_dir": str(self.log_dir),
                **({"groups": self.groups_status()} if any(s.instances is not None for s in self.m.processes)
                   else {})}

    # ---- process side ---------------------------------------------------------------------
    def add_child(self, spec: ProcessSpec, impl_override: str | None = None, instance: str | None = None,
                  start: bool = True) -> Child:
        name = instance or spec.name
        cmd = command_for(spec, self.endpoint, self.m.path, impl_override, name)
        if self.client_config is not None:  # the secured mesh: each process with its role's certificate
            cmd += ["--config", self.client_config(spec)]
        ch = Child(spec, cmd, self.log_dir / f"{name}.log", self.m.restart_backoff_s, name=name,
                   give_up_after=self.m.give_up_after, impl=impl_override or spec_impl(spec))
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
        # lost (could not be delivered or recovered) leads; refusals and skips by design are apart from it
        lost = sum(s.get("lost_total", 0) for s in st.values())
        skipped = sum(s.get("skipped_total", 0) for s in st.values())
        with self.lock:
            raised = sorted(k.split("/", 1)[1] for k in self.raised)
        up = time.monotonic() - self.started
        return (f"magmesh up {up:6.0f}s | {alive}/{len(self.children)} processes, {len(st)} services answering"
                f" | lost {lost} | in {rate_in:7.0f} msg/s | rejected {rejects} skipped {skipped}"
                f" | restarts {restarts}"
                f" | alarms raised: {', '.join(raised) if raised else 'none'}")

    def run(self, duration_s: float | None = None) -> int:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.open()
        for spec in self.m.processes:
            if spec.enabled and spec.instances is not None:
                self.start_group(spec, spec.instances)
            elif spec.enabled:
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
                gave_up = False
                for ch in list(self.children.values()):
                    ev = ch.check(now)
                    if ev:
                        self.event(ev)
                        if ch.given_up:
                            gave_up = True
                            if self.quiet:  # the reason reaches the terminal even without the status line
                                print(f"magmesh up: {ev}", file=sys.stderr, flush=True)
                if gave_up and not self.keep_going:
                    self.event("stopping the mesh: a process was given up (magmesh up --keep-going keeps the "
                               "rest running)")
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
                if gave_up and not self.keep_going:
                    break
        finally:
            if tty:
                print()
            self.shutdown()
        given_up = sorted(n for n, c in self.children.items() if c.given_up)
        if given_up:
            print(f"magmesh up: given up on {', '.join(given_up)} (failed on start "
                  f"{self.m.give_up_after} times in a row; see the lines above and the logs in {self.log_dir})",
                  file=sys.stderr, flush=True)
            return 1
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
