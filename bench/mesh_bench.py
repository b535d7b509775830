"""``magmesh bench mesh``: the real mesh processes under N simulated vehicles, against the raw-Zenoh limit.

Pipeline: fleet (N vehicles: 2 magnetometers at 50 Hz, IMU 100 Hz, GNSS 5 Hz) → ingest → dmc_detector
(+ calibration and heading_fuser consuming beside them) → sink. Limit: the same fleet through the same number of
hops (raw → relay → relay → sink) with no decoding or processing. Both in the same run, on the same machine.

Figures: sustained samples/s end to end (raw samples whose DMC epoch reached the sink), latency of the DMC output
(raw publish → dmc received) p50/p99, CPU per stage (% of one core; also by kind of thread: main loop, readers, a
group's coordination, Zenoh's runtime), memory per process, messages lost, and the
ratio pipeline / limit. Every figure is a median over ``--repeat`` runs. *Raw publish* is when the fleet really
put a sample's batch (its put log); the fleet is one process putting every vehicle's batch of a window at once and
falls behind when the stages share its cores, so the p99 from when each batch was due
(``due_latency_ms_p99``) and the fleet's own lag (``fleet_last_put_lag_ms``) are reported beside it.

``wire="v3"`` (the default): the fleet publishes one batch per vehicle per ``window_s`` with binary columns
(``v2``: list columns; both as an on-board agent would), ingest emits fleet frames (``output=frames``, window
``frame_s``) that the stages take, and the limit relays the same batches. ``wire="v1"``: every sample alone on its
key, end to end. Besides, ``v1_ingest`` finds how many vehicles publishing v1 single samples one ingest process
sustains (ingest alone, fleet frames out), and the overload run (:func:`overload_case`) doubles the highest
sustained load and then drops back: no stage may crash, every sample that never came out must be counted by a
stage under a reason, and latency must come back within the goal.
"""

from __future__ import annotations

import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import msgpack
import msgspec
import numpy as np

from magmesh import paths, zconf
from schemas import keys

from .fleet import publish_time, vehicle_ids, window_index

CLK = os.sysconf("SC_CLK_TCK")
#: ingest's fleet-frame window in the paced runs, s. Every window costs each stage process a fixed amount (checks,
#: sorting and encoding at ingest, a frame's handling at every stage after it) on top of its rows: at 10 ms windows
#: and 1,000 vehicles one process per stage took 125-135 % of the two cores (p99 42-70 ms) and two per stage
#: 178-192 % (p99 95-207 ms); at 20 ms, 113 % (58 ms) and 150 % (57 ms) in one pair of runs. 20 ms keeps p99 well
#: inside the 100 ms goal in both set-ups (README, "Elastic roles").
FRAME_WINDOW_S = 0.02


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cpu_s(pid: int) -> float:
    try:
        f = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
        return (int(f[11]) + int(f[12])) / CLK
    except (OSError, IndexError):
        return float("nan")


#: a stage process's threads by what they do (their OS names: magmesh/zconf.os_thread_name; Zenoh's runtime names
#: its own rx-N, tx-N, net-N, acc-N, app-N)
_THREAD_KINDS = (("main", re.compile(r"mm-main$")), ("readers", re.compile(r"mm-read-")),
                 ("group", re.compile(r"mm-(group|frames)$")), ("zenoh", re.compile(r"(rx|tx|net|acc|app)-\d+$")))


def _thread_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds of a process's live threads by kind (:data:`_THREAD_KINDS`, the rest as ``other``)."""
    out: dict[str, float] = {}
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for tid in tids:
        try:
            name = open(f"/proc/{pid}/task/{tid}/comm").read().strip()
            f = open(f"/proc/{pid}/task/{tid}/stat").read().rsplit(")", 1)[1].split()
        except OSError:  # (a thread that ended meanwhile)
            continue
        kind = next((k for k, rx in _THREAD_KINDS if rx.match(name)), "other")
        out[kind] = out.get(kind, 0.0) + (int(f[11]) + int(f[12])) / CLK
    return out


def _threads_pct(t0: dict, t1: dict, wall: float) -> dict:
    """Per stage (a group's members summed), the % of one core each kind of thread took between two
    :func:`_thread_cpu_s` readings per process (a thread started or ended between them counts from its reading)."""
    out: dict[str, dict[str, float]] = {}
    for proc, b in t1.items():
        a = t0.get(proc, {})
        d = out.setdefault(proc.split("#")[0], {})
        for kind, v in b.items():
            d[kind] = round(d.get(kind, 0.0) + 100 * max(0.0, v - a.get(kind, 0.0)) / wall, 1)
    return out


def _rss_mb(pid: int) -> float:
    try:
        for line in open(f"/proc/{pid}/status"):
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def _manifest(n: int, tmp: Path) -> Path:
    """A manifest whose bench vehicles carry the demo car's compensation (the fleet replays that car)."""
    import tomllib

    with open(paths.DEPLOY_DIR / "mesh.toml", "rb") as f:
        car = tomllib.load(f)["vehicles"]["car-1"]
    lines = []
    for v in vehicle_ids(n):
        lines.append(f'[vehicles.{v}]\nkind = "car"\ndeclination_rad = {car.get("declination_rad", 0.0)!r}\n')
        for s, p in car.get("mag_params", {}).items():
            lines.append(f"[vehicles.{v}.mag_params.{s}]\n")
            for k, val in p.items():
                lines.append(f"{k} = {json.dumps(val)}\n")
    path = tmp / "bench.toml"
    path.write_text("".join(lines))
    return path


class _Stamp(msgspec.Struct):
    t_s: float


class Sink:
    """Counts outputs and their times in its own thread: each output's sample time ``t_s`` and receive wall time.
    ``batch_stream``: the outputs are batches, and the samples of that stream inside them are what is counted."""

    def __init__(self, session, keyexpr: str, latency: bool, batch_stream: str | None = None):
        import zenoh

        self.sub = session.declare_subscriber(keyexpr, zenoh.handlers.FifoChannel(1_000_000))
        self.n = 0
        self.t_sample: list[float] = []
        self.t_recv: list[float] = []
        self.vehicle: list[int] = []  # each sample's vehicle number (bench-NNNN), -1 if not a bench vehicle
        self._vnum: dict[str, int] = {}
        self.t_last = 0.0
        self.latency = latency
        self.batch_stream = batch_stream
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        unpack = msgpack.unpackb
        stamp = msgspec.msgpack.Decoder(_Stamp).decode
        bs = self.batch_stream
        ts, tr = self.t_sample, self.t_recv
        while True:
            try:
                s = self.sub.recv()
            except Exception:
                return
            now = time.time()
            self.t_last = now
            if bs is not None:
                m = unpack(s.payload.to_bytes())
                st = m["streams"].get(bs)
                if st is None:
                    continue
                self.n += st["n"]
                if self.latency:
                    t = st["t_s"]
                    ts.extend(np.frombuffer(t, "<f8").tolist() if isinstance(t, bytes) else t)
                    tr.extend([now] * st["n"])
                    vi, names = st.get("vi"), m.get("vehicles")
                    if isinstance(vi, bytes) and names is not None:  # a frame's rows: their vehicles
                        nums = [self._num(v) for v in names]
                        self.vehicle.extend([nums[i] for i in np.frombuffer(vi, "<u4").tolist()])
                    else:  # a vehicle's batch
                        self.vehicle.extend([self._num(str(s.key_expr).split("/")[1])] * st["n"])
                continue
            self.n += 1
            if self.latency:
                ts.append(stamp(s.payload.to_bytes()).t_s)
                tr.append(now)
                self.vehicle.append(self._num(str(s.key_expr).split("/")[1]))

    def _num(self, vehicle: str) -> int:
        n = self._vnum.get(vehicle)
        if n is None:
            head, _, tail = vehicle.rpartition("-")
            n = self._vnum[vehicle] = int(tail) if head == "bench" and tail.isdigit() else -1
        return n

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(sample time, receive time, vehicle number) of every output sample so far."""
        ts = np.asarray(self.t_sample, float)
        n = len(ts)
        vn = np.asarray(self.vehicle[:n], np.int64) if len(self.vehicle) >= n else np.full(n, -1, np.int64)
        return ts, np.asarray(self.t_recv[:n], float), vn

    def latencies_ms(self, start_at: float | None, window_s: float | None, measure_from: float | None = None,
                     until: float | None = None, put_log: np.ndarray | None = None) -> tuple:
        """(from raw publish, from sample time, from the batch's due time) in ms of the outputs of samples taken
        from ``measure_from`` on. The v2 fleet puts a window's batch when its last sample's time has come (bench/
        fleet.py publish_time) or later when it falls behind: with ``put_log`` (its put times, windows × vehicles)
        *raw publish* is when the batch really went out, without it when it was due. v1 samples are put when
        taken, so all are the same there."""
        if not self.t_sample:
            return None, None, None
        ts, tr, vn = self.arrays()
        keep = np.ones(len(ts), bool)
        if measure_from is not None and (ts >= measure_from).any():
            keep &= ts >= measure_from
        if until is not None:  # (only the samples taken before it)
            keep &= ts < until
        ts, tr, vn = ts[keep], tr[keep], vn[keep]
        if not len(ts):
            return None, None, None
        age = (tr - ts) * 1000
        if start_at is None:
            return age, age, age
        due = (tr - publish_time(ts, start_at, window_s)) * 1000
        return due - 1000 * put_lag(ts, vn, start_at, window_s, put_log), age, due


def put_lag(ts: np.ndarray, vn: np.ndarray, start_at: float, window_s: float, put_log: np.ndarray | None
            ) -> np.ndarray:
    """Seconds after its due time that each sample's batch was put (``put_log``: windows × vehicles, NaN where
    not known; 0 for those and without a log)."""
    lag = np.zeros(len(ts))
    if put_log is None or not put_log.size:
        return lag
    w = window_index(ts, start_at, window_s)
    ok = (vn >= 0) & (vn < put_log.shape[1]) & (w >= 0) & (w < put_log.shape[0])
    got = put_log[w[ok], vn[ok]].astype(float)
    lag[np.flatnonzero(ok)] = np.where(np.isfinite(got), got, 0.0)
    return lag


def _spawn(args: list[str], port: int, log: Path) -> subprocess.Popen:
    # the benchmark's vehicles must not leave calibration sets or alarm states in the user's state directory, and
    # one run none for the next (a group member stopped while holding vehicles keeps its seq journal for the member
    # taking them: the next run's member of the same name resumed it, and counted the seqs the last run's ingest
    # numbered beyond what it had handled as upstream gaps): a state directory per run (its router's port)
    env = dict(os.environ, PYTHONUNBUFFERED="1", MAGMESH_LOG_LEVEL=os.environ.get("MAGMESH_BENCH_LOG_LEVEL", "WARNING"),
               MAGMESH_STATE_DIR=str(log.parent / "state" / str(port)))
    return subprocess.Popen([sys.executable, *args, "--connect", f"tcp/127.0.0.1:{port}"], cwd=paths.REPO,
                            stdout=open(log, "ab"), stderr=subprocess.STDOUT, env=env, start_new_session=True)


def _stop(procs: dict) -> None:
    for p in procs.values():
        if p.poll() is None:
            p.terminate()
    for p in procs.values():
        try:
            p.wait(5)
        except subprocess.TimeoutExpired:
            p.kill()


def wait_tokens(session, tokens: list[str], timeout: float = 30.0) -> bool:
    """Whether every liveliness token in ``tokens`` is up within ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        live = {str(r.ok.key_expr) for r in session.liveliness().get(keys.svc_all(), timeout=1.0) if r.ok}
        if set(tokens) <= live:
            return True
        time.sleep(0.2)
    return False


def _start_stage(procs: dict, tokens: list, members: dict, role: str, args: list[str], name: str, k: int, port: int,
                 log: Path) -> None:
    """Start one stage: one process ``name`` (``k`` = 1, under the key ``role`` of ``procs``), or ``k`` members
    ``name-1..k`` of a group (``--group name``: the vehicles shared by rendezvous, magmesh/group_member.py),
    under the keys ``role#i``."""
    insts = [name] if k <= 1 else [f"{name}-{i}" for i in range(1, k + 1)]
    members[role] = insts
    for i, inst in enumerate(insts, 1):
        grp = ["--group", name] if k > 1 else []
        procs[role if k <= 1 else f"{role}#{i}"] = _spawn(["-m", *args[:1], "--instance", inst, *grp, *args[1:]],
                                                          port, log if k <= 1 else log.with_suffix(f".{i}.log"))
        tokens.append(keys.svc_token(role, inst))


def wait_groups(session, members: dict, timeout: float = 60.0) -> bool:
    """Whether every group member answers ready, seeing all the members of its group, within ``timeout`` s (its
    first rounds done: a vehicle's first sample is then taken at once by the member the rule names)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        ok = True
        for role, insts in members.items():
            if len(insts) <= 1:
                continue
            for inst in insts:
                g = _status(session, role, inst).get("group") or {}
                if not g.get("ready") or sorted(g.get("members", [])) != sorted(insts):
                    ok = False
        if ok:
            return True
        time.sleep(0.3)
    return False


def _by_stage(d: dict) -> dict:
    """Per-process figures summed per stage (a group's members ``role#i`` under ``role``)."""
    out: dict = {}
    for k, v in d.items():
        out[k.split("#")[0]] = round(out.get(k.split("#")[0], 0.0) + v, 1)
    return out


def _status(session, role: str, inst: str) -> dict:
    for r in session.get(keys.svc_status(role, inst), timeout=3.0):
        if r.ok:
            return msgpack.unpackb(r.ok.payload.to_bytes())
    return {}


#: seconds a paced run publishes before latency and CPU are measured. Meeting 500 vehicles at once is a start-up
#: backlog the stages work off in about 6 s on 2 cores (p99 per 2 s of sample time: 950, 519, 407, then 119 ms
#: and steady 74-166 ms); 5 s of warm-up left its tail in the measured window (p99 1,260 ms over an 8 s run
#: against 133 ms over 30 s). The warm-up's own latency is reported as ``startup_p99_ms``.
WARMUP_S = 10.0


def run_case(kind: str, n: int, duration_s: float, max_mode: bool, stages: tuple[str, ...], tmp: Path,
             wire: str = "v3", window_s: float = 0.05, frame_s: float = FRAME_WINDOW_S, warmup_s: float | None = None,
             extra: int = 0, extra_s: float = 0.0, instances: int = 1, sink: str = "frames") -> dict:
    """One run: ``kind`` is "pipeline", "limit" or "ingest" (ingest alone, fleet frames out). ``window_s``: each
    v2 vehicle's batch window; ``frame_s``: ingest's frame window (the pipeline with v2 runs on fleet frames).
    ``warmup_s`` (paced runs; default :data:`WARMUP_S`, 0 at saturation): the fleet publishes that long first —
    the stages meet every vehicle, declare its keys and settle — and latency and CPU are measured after it; every
    sample of the warm-up still counts for loss, and its latency is reported apart (``startup_p99_ms``).
    ``extra``/``extra_s`` (the overload case): a second fleet of ``extra`` more
    vehicles publishes beside the first for the first ``extra_s`` seconds (warm-up included), then stops; the
    result then also holds ``phases``: p99 latency of the samples taken while both fleets ran and of those taken
    in the last half of the time after. ``instances`` (pipeline and ingest runs): each stage runs as a group of
    that many members sharing the vehicles (CPU and memory summed per stage, losses over every member).
    ``sink`` (pipeline runs on frames): ``"frames"`` counts the DMC's outputs in its fleet frames (``magmesh/fleet/
    */dmc``), as a fleet-wide consumer takes them; the per-vehicle ``dmc`` keys are then watched by nobody and not
    put (magmesh/runtime.py ``_Watch``). ``"keys"`` subscribes to every vehicle's ``dmc`` key (``magmesh/*/dmc``):
    25,000 more messages a second at 500 vehicles, put, routed and decoded."""
    if warmup_s is None:
        warmup_s = 0.0 if max_mode else WARMUP_S
    import zenoh

    port = _free_port()
    router = zenoh.open(zconf.build_config(mode="router", listen=[f"tcp/127.0.0.1:{port}"]))
    man = _manifest(n + extra, tmp)
    procs: dict[str, subprocess.Popen] = {}
    fleets: dict[str, subprocess.Popen] = {}  # the load generators (stopped with the stages if the run is cut short)
    tokens: list[str] = []
    members: dict[str, list[str]] = {}  # stage -> its instances
    batch_stream = None
    # as fast as possible the stages run behind by design: nothing is shed there (shed_after_s = 0), so the run
    # measures what the stages carry, not what they would drop to stay current
    no_shed = ["--set", "shed_after_s=0"] if max_mode else []
    ingest_args = ["services.ingest", *no_shed]
    if kind == "ingest" or wire in ("v2", "v3"):
        ingest_args += ["--set", "output=frames", "--set", f"batch_window_s={frame_s}"]
    if kind == "ingest":
        _start_stage(procs, tokens, members, "ingest", ingest_args, "b-ingest", instances, port, tmp / "ingest.log")
        sink_key, batch_stream = keys.fleet_frames("clean"), "mag/2"  # (a frame's rows of stream mag/2)
    elif kind == "pipeline":
        _start_stage(procs, tokens, members, "ingest", ingest_args, "b-ingest", instances, port, tmp / "ingest.log")
        for role, name, log in (("dmc_detector", "b-dmc", "dmc"), ("calibration", "b-cal", "cal"),
                                ("heading_fuser", "b-heading", "heading")):
            if role == "dmc_detector" or role in stages:
                _start_stage(procs, tokens, members, role, [f"services.{role}", "--manifest", str(man), *no_shed],
                             name, instances, port, tmp / f"{log}.log")
        sink_key = keys.dmc("*")
        if _sink(sink, wire) == "frames":  # the DMC's fleet frames, as the services beside it take them
            sink_key, batch_stream = keys.fleet_frames("dmc"), "dmc"
    else:
        procs["relay1"] = _spawn(["-m", "bench.relay", "--from", "raw", "--to", "clean", "--instance", "r1"], port,
                                 tmp / "relay1.log")
        procs["relay2"] = _spawn(["-m", "bench.relay", "--from", "clean", "--to", "benchout", "--instance", "r2"],
                                 port, tmp / "relay2.log")
        tokens += [keys.svc_token("relay", "r1"), keys.svc_token("relay", "r2")]
        sink_key = "magmesh/*/benchout/mag/2"
        if wire in ("v2", "v3"):
            sink_key, batch_stream = f"magmesh/*/benchout/{keys.BATCH}", "mag/2"
    try:
        if not wait_tokens(router, tokens):
            raise RuntimeError(f"{kind}: services did not come up (logs in {tmp})")
        if instances > 1 and not wait_groups(router, members):
            raise RuntimeError(f"{kind}: the groups of {instances} did not form (logs in {tmp})")
        sink = Sink(router, sink_key, latency=not max_mode, batch_stream=batch_stream)
        time.sleep(0.5)
        start_at = time.time() + 2.0 + (n / 500)  # the fleet declares a publisher per vehicle first
        cpu0 = {}
        fleet_args = ["-m", "bench.fleet", "--vehicles", str(n), "--duration", str(duration_s + warmup_s), "--start-at",
                      str(start_at), "--wire", "v1" if kind == "ingest" else wire, "--window", str(window_s)] + (
                          ["--max"] if max_mode else [])
        logs = [tmp / f"fleet-puts-{port}.npy", tmp / f"fleet2-puts-{port}.npy"]  # each batch's put time
        put_args = ["--put-log", str(logs[0])] if (wire in ("v2", "v3") and kind != "ingest" and not max_mode) else []
        fleet = subprocess.Popen([sys.executable, *fleet_args, *put_args, "--connect", f"tcp/127.0.0.1:{port}"],
                                 cwd=paths.REPO,
                                 stdout=subprocess.PIPE, stderr=open(tmp / "fleet.log", "ab"), text=True)
        fleets["fleet"] = fleet
        fleet2 = None
        if extra:
            a2 = list(fleet_args)
            a2[a2.index("--vehicles") + 1], a2[a2.index("--duration") + 1] = str(extra), str(extra_s)
            if put_args:
                a2 += ["--put-log", str(logs[1])]
            fleet2 = subprocess.Popen([sys.executable, *a2, "--first", str(n), "--connect",
                                       f"tcp/127.0.0.1:{port}"], cwd=paths.REPO, stdout=subprocess.PIPE,
                                      stderr=open(tmp / "fleet2.log", "ab"), text=True)
            fleets["fleet2"] = fleet2
        while time.time() < start_at + warmup_s:
            time.sleep(0.01)
        cpu0 = {k: _cpu_s(p.pid) for k, p in procs.items()}
        thr0 = {k: _thread_cpu_s(p.pid) for k, p in procs.items()}
        cpu0["fleet"] = _cpu_s(fleet.pid)
        cpu0["router+sink"] = _cpu_s(os.getpid())  # this process: the Zenoh router and the counting sink
        t_start = time.time()
        rss = {}
        time.sleep(duration_s * 0.8)
        rss = {k: _rss_mb(p.pid) for k, p in procs.items()}
        cpu_fleet = _cpu_s(fleet.pid)
        out, _ = fleet.communicate(timeout=duration_s + warmup_s + 120)
        fl = json.loads(out.strip().splitlines()[-1])
        if fleet2 is not None:
            out2, _ = fleet2.communicate(timeout=extra_s + 120)
            fl2 = json.loads(out2.strip().splitlines()[-1])
            fl = dict(fl, sent={k: v + fl2["sent"][k] for k, v in fl["sent"].items()}, total=fl["total"] + fl2["total"],
                      rate=fl["rate"] + fl2["total"] / max(extra_s, 1e-9) * (extra_s / (duration_s + warmup_s)),
                      offered_rate=fl["offered_rate"] + fl2["offered_rate"] * extra_s / (duration_s + warmup_s))
        expected = fl["sent"]["mag"] // 2  # one DMC epoch (or relayed mag/2) per magnetometer pair
        # drain: wait for every output, or until nothing has arrived for 10 s (at most 180 s)
        deadline = time.time() + 180
        while sink.n < expected and time.time() < deadline:
            time.sleep(0.5)
            if time.time() - max(sink.t_last, t_start + duration_s) > 10:
                break
        drained = sink.n >= expected
        t_end = sink.t_last
        cpu1 = {k: _cpu_s(p.pid) for k, p in procs.items()}
        thr1 = {k: _thread_cpu_s(p.pid) for k, p in procs.items()}
        cpu1["router+sink"] = _cpu_s(os.getpid())
        wall = max(t_end - t_start, 1e-6)
        statuses = {}  # per stage, the status of each member
        for role, insts in members.items():
            statuses[role] = [_status(router, role, inst) for inst in insts]
        drops = {}  # what any stage lost or refused (a skip by design — a stream a stage does not use — is neither)
        for name, sts in statuses.items():
            for st in sts:
                for cat in ("lost", "rejected"):
                    for r, c in (st.get(cat) or {}).items():
                        if c:
                            drops[f"{name}:{cat}:{r}"] = drops.get(f"{name}:{cat}:{r}", 0) + c
        lost = max(0, expected - sink.n) + sum(drops.values())
        if statuses.get("ingest") and all(statuses["ingest"]):
            # samples received: in_total counts batches besides their samples
            ing_in = sum(st.get("in_total", 0) - st.get("batches_in", 0) for st in statuses["ingest"])
            lost += max(0, fl["total"] - ing_in)
        # latency only means something when paced: from the batch's publication (the goal's measure) and from
        # the sample's own time (which adds the vehicle's batching window)
        v2_fleet = wire in ("v2", "v3") and kind != "ingest"
        put_log = _put_log(logs, n, extra) if put_args else None
        lat, age, due = sink.latencies_ms(fl.get("start_at") if v2_fleet else None, window_s,
                                          (fl.get("start_at") or start_at) + warmup_s, put_log=put_log) \
            if not max_mode else (None, None, None)
        startup = None  # p99 of the samples taken during the warm-up: how long meeting the fleet holds it back
        if not max_mode and warmup_s > 0:
            lat_w, _, _ = sink.latencies_ms(fl.get("start_at") if v2_fleet else None, window_s, None,
                                            until=(fl.get("start_at") or start_at) + warmup_s, put_log=put_log)
            if lat_w is not None and len(lat_w):
                startup = round(float(np.percentile(lat_w, 99)), 2)
        # over the measured window only (the warm-up's samples are out of it, as wall is)
        samples_done = (fl["total"] * min(1.0, sink.n / max(expected, 1))
                        * duration_s / max(duration_s + warmup_s, 1e-9))
        alive = {k: p.poll() is None for k, p in procs.items()}
        phases = None
        if extra and not max_mode:
            t0 = fl.get("start_at") or start_at
            t_over, t_end_pub = t0 + extra_s, t0 + duration_s + warmup_s
            ts, tr, vn = sink.arrays()
            if v2_fleet:
                lat_all = (tr - publish_time(ts, fl["start_at"], window_s)
                           - put_lag(ts, vn, fl["start_at"], window_s, put_log)) * 1000
            else:
                lat_all = (tr - ts) * 1000
            over = (ts >= t0) & (ts < t_over)
            tail = ts >= t_over + (t_end_pub - t_over) / 2

            def _p99(x):
                return round(float(np.percentile(x, 99)), 2) if len(x) else None

            phases = {"overload_p99_ms": _p99(lat_all[over]), "overload_outputs": int(over.sum()),
                      "recovered_p99_ms": _p99(lat_all[tail]), "recovered_outputs": int(tail.sum())}
        return {
            "kind": kind, "vehicles": n, "max_mode": max_mode, "duration_s": duration_s, "warmup_s": warmup_s,
            "wire": wire,
            "window_s": window_s if (wire in ("v2", "v3") or kind == "ingest") else None,
            "offered_samples_s": fl["offered_rate"], "published_samples_s": round(fl["rate"], 1),
            "sustained_samples_s": round(samples_done / wall, 1),
            "outputs": sink.n, "expected_outputs": expected, "drained": drained, "lost": int(lost), "drops": drops,
            "latency_ms_p50": round(float(np.percentile(lat, 50)), 2) if lat is not None else None,
            "latency_ms_p99": round(float(np.percentile(lat, 99)), 2) if lat is not None else None,
            "age_ms_p99": round(float(np.percentile(age, 99)), 2) if age is not None else None,
            # from the moment each batch was due rather than put: adds the fleet's own lag (below)
            "due_latency_ms_p99": round(float(np.percentile(due, 99)), 2) if due is not None else None,
            "startup_p99_ms": startup,
            # how late the fleet itself put each window's last batch (one process putting every vehicle's batch at
            # once): part of every latency above, the load generator's and not the pipeline's
            "fleet_last_put_lag_ms": fl.get("last_put_lag_ms"),
            "vehicle_window_s": window_s if v2_fleet else None,
            "frame_window_s": frame_s if (kind == "pipeline" and wire in ("v2", "v3")) else None,
            "cpu_pct": _by_stage({k: 100 * (cpu1[k] - cpu0[k]) / wall for k in (*procs, "router+sink")})
                       | {"fleet": round(100 * (cpu_fleet - cpu0["fleet"]) / (duration_s * 0.8), 1)},
            # the same per stage by kind of thread: the main loop (decoding, the stage's work, publishing), the
            # input readers, a group's coordination, Zenoh's own runtime, the rest
            "cpu_threads_pct": _threads_pct(thr0, thr1, wall),
            "rss_mb": _by_stage(rss),
            "instances": instances,
            "alive": alive,
            **({"extra_vehicles": extra, "extra_s": extra_s, "phases": phases} if extra else {}),
        }
    finally:
        _stop(fleets)
        _stop(procs)
        try:
            router.close()
        except Exception:  # noqa: BLE001 - (a close that timed out must not hide why the run ended)
            pass


def _put_log(paths_: list[Path], n: int, extra: int) -> np.ndarray | None:
    """The fleets' put logs side by side (windows × vehicles; the second fleet's vehicles numbered from ``n``)."""
    parts = [np.load(p) if p.exists() else None for p in paths_]
    if parts[0] is None:
        return None
    if not extra or parts[1] is None:
        return parts[0]
    out = np.full((max(parts[0].shape[0], parts[1].shape[0]), n + extra), np.nan, np.float32)
    out[:parts[0].shape[0], :n] = parts[0]
    out[:parts[1].shape[0], n:n + extra] = parts[1]
    return out


def _sink(sink: str, wire: str) -> str:
    """Where a run counts the DMC's outputs: v1 runs have no fleet frames, so always on the per-vehicle keys."""
    return sink if wire in ("v2", "v3") else "keys"


def _median_case(kind, n, duration_s, max_mode, stages, repeat, tmp, wire="v3", window_s=0.05, frame_s=FRAME_WINDOW_S,
                 instances=1, warmup_s=None, sink="frames") -> dict:
    runs = [run_case(kind, n, duration_s, max_mode, stages, tmp, wire, window_s, frame_s, instances=instances,
                     warmup_s=warmup_s, sink=sink) for _ in range(repeat)]
    out = dict(runs[0])
    for k in ("sustained_samples_s", "published_samples_s", "latency_ms_p50", "latency_ms_p99", "age_ms_p99",
              "due_latency_ms_p99", "startup_p99_ms"):
        vals = [r[k] for r in runs if r.get(k) is not None]
        out[k] = round(statistics.median(vals), 2) if vals else None
    lags = [r["fleet_last_put_lag_ms"] for r in runs if r.get("fleet_last_put_lag_ms")]
    if lags:
        out["fleet_last_put_lag_ms"] = {q: round(statistics.median(x[q] for x in lags), 2) for q in ("p50", "p99")}
    out["lost"] = max(r["lost"] for r in runs)
    out["runs"] = len(runs)
    return out


def overload_case(n: int, duration_s: float, stages: tuple[str, ...], tmp: Path, wire: str = "v3",
                  window_s: float = 0.05, frame_s: float = FRAME_WINDOW_S, p99_ms: float = 100.0, sink: str = "frames") -> dict:
    """Twice ``n`` vehicles (the highest sustained load) for a 5 s warm-up and ``duration_s``, then ``n`` alone
    for ``max(10, 1.5 × duration_s)`` s: every stage must live through it, every sample that never came out must
    be counted by a stage under a reason, and the latency of the samples taken in the last half of the calm must
    be back within the goal."""
    warm = 5.0
    calm = max(10.0, 1.5 * duration_s)
    r = run_case("pipeline", n, duration_s + calm, False, stages, tmp, wire, window_s, frame_s, warmup_s=warm,
                 extra=n, extra_s=warm + duration_s, sink=sink)
    missing = max(0, r["expected_outputs"] - r["outputs"])
    counted = sum(r["drops"].values())
    ph = r.get("phases") or {}
    rp = ph.get("recovered_p99_ms")
    r["overload"] = {
        "vehicles": n, "peak_vehicles": 2 * n, "overload_s": warm + duration_s, "calm_s": calm,
        "crashed": sorted(k for k, ok in r["alive"].items() if not ok),
        "missing_outputs": missing, "counted_drops": counted, "by_reason": r["drops"],
        "uncounted": max(0, missing - counted),
        "overload_p99_ms": ph.get("overload_p99_ms"), "recovered_p99_ms": rp,
        "recovered": bool(all(r["alive"].values()) and rp is not None and rp <= p99_ms),
    }
    return r


def available_stages() -> tuple[str, ...]:
    import importlib.util

    st = ["ingest", "dmc_detector"]
    for name in ("calibration", "heading_fuser"):
        if importlib.util.find_spec(f"services.{name}.service") is not None:
            st.append(name)
    return tuple(st)


def _sustained(r: dict, p99_ms: float) -> bool:
    return bool(r["lost"] == 0 and r["latency_ms_p99"] is not None and r["latency_ms_p99"] <= p99_ms
                and r["published_samples_s"] >= 0.95 * r["offered_samples_s"]
                and r["outputs"] >= 0.999 * r["expected_outputs"])


def bench(vehicles: list[int], duration_s: float = 15.0, repeat: int = 1, stages: tuple[str, ...] | None = None,
          limit_vehicles: int | None = None, progress=None, wire: str = "v3", window_s: float = 0.05,
          p99_ms: float = 100.0, v1_ingest: bool = True, frame_s: float = FRAME_WINDOW_S, overload: bool = True,
          overload_vehicles: int | None = None, instances: tuple[int, ...] = (1,), warmup_s: float = WARMUP_S,
          sink: str = "frames") -> dict:
    """The whole bench. ``warmup_s``: of every paced run (see :func:`run_case`). ``instances``: the scaling table
    is run once per count, each stage a group of that many members (1: one process per stage); ``scaling`` and
    ``max_vehicles`` are the first count's, ``by_instances`` has every count's. Saturation, the v1 ingest case
    and the overload run use the first count. ``sink``: see :func:`run_case`."""
    stages = stages or available_stages()
    tmp = Path(tempfile.mkdtemp(prefix="magmesh-bench-"))
    say = progress or (lambda s: None)
    # throughput at saturation: the same load, pipeline vs no-processing limit, same run
    n_sat = limit_vehicles or max(10, min(vehicles))
    say(f"saturation: pipeline, {n_sat} vehicles, as fast as possible ({wire})")
    pipe_max = _median_case("pipeline", n_sat, duration_s, True, stages, repeat, tmp, wire, window_s, frame_s,
                            sink=sink)
    say(f"saturation: limit (same hops, no processing), {n_sat} vehicles ({wire})")
    lim_max = _median_case("limit", n_sat, duration_s, True, stages, repeat, tmp, wire, window_s, frame_s)
    # the instance counts side by side: each vehicle count is run for every instance count before the next, so a
    # machine that slows down (or speeds up) within the bench weighs on every count alike
    rows_k: dict[int, list[dict]] = {k: [] for k in instances}
    for n in vehicles:
        for k in instances:
            say(f"paced at sensor rates: pipeline, {n} vehicles ({wire})"
                + (f", {k} instance{'s' if k > 1 else ''} per stage" if k > 1 or len(instances) > 1 else ""))
            r = _median_case("pipeline", n, duration_s, False, stages, repeat, tmp, wire, window_s, frame_s,
                             instances=k, warmup_s=warmup_s, sink=sink)
            r["sustained"] = _sustained(r, p99_ms)
            rows_k[k].append(r)
    by_k = {}
    for k, rows in rows_k.items():
        ok_k = [r["vehicles"] for r in rows if r["sustained"]]
        by_k[str(k)] = {"scaling": rows, "max_vehicles": max(ok_k) if ok_k else 0}
    table = by_k[str(instances[0])]["scaling"]
    ok = [r["vehicles"] for r in table if r["sustained"]]
    ratio = pipe_max["sustained_samples_s"] / max(lim_max["sustained_samples_s"], 1e-9)
    ingest_rows = []
    if v1_ingest:
        for n in vehicles:  # one ingest process under v1 single-sample vehicles, until it no longer keeps up
            say(f"v1 single-sample vehicles through one ingest: {n}")
            r = _median_case("ingest", n, duration_s, False, ("ingest",), repeat, tmp, "v1", window_s, frame_s,
                             warmup_s=warmup_s)
            r["sustained"] = _sustained(r, p99_ms)
            ingest_rows.append(r)
            if not r["sustained"]:
                break
    ok_ing = [r["vehicles"] for r in ingest_rows if r["sustained"]]
    over = None
    if overload:  # twice the highest sustained load, then back
        n_over = overload_vehicles or (max(ok) if ok else min(vehicles))
        say(f"overload: {2 * n_over} vehicles, then {n_over} ({wire})")
        over = overload_case(n_over, duration_s, stages, tmp, wire, window_s, frame_s, p99_ms, sink)["overload"]
    return {
        "stages": list(stages),
        "wire": wire,
        "sink": _sink(sink, wire),
        "window_s": window_s,
        "frame_window_s": frame_s,
        "p99_goal_ms": p99_ms,
        "saturation": {"pipeline": pipe_max, "limit": lim_max},
        "ratio_to_limit": round(ratio, 3),
        "scaling": table,
        "max_vehicles": max(ok) if ok else 0,
        "by_instances": by_k,
        "v1_ingest": ingest_rows,
        "v1_ingest_max_vehicles": max(ok_ing) if ok_ing else 0,
        "overload": over,
        "logs": str(tmp),
    }


def _row(r: dict) -> str:
    cpu = ", ".join(f"{k} {v:.0f}" for k, v in r["cpu_pct"].items())
    rss = ", ".join(f"{k} {v:.0f}" for k, v in r["rss_mb"].items())
    p50 = "-" if r["latency_ms_p50"] is None else f"{r['latency_ms_p50']:.1f}"
    p99 = "-" if r["latency_ms_p99"] is None else f"{r['latency_ms_p99']:.1f}"
    su = "-" if r.get("startup_p99_ms") is None else f"{r['startup_p99_ms']:.0f}"
    due = "-" if r.get("due_latency_ms_p99") is None else f"{r['due_latency_ms_p99']:.1f}"
    lag = r.get("fleet_last_put_lag_ms")
    lag = "-" if not lag else f"{lag['p50']:.0f} / {lag['p99']:.0f}"
    return (f"| {r['vehicles']} | {r['offered_samples_s']} | {r['published_samples_s']:.0f} | "
            f"{r['sustained_samples_s']:.0f} | {p50} | {p99} | {due} | {lag} | {su} | {r['lost']} | {cpu} | {rss} | "
            f"{'yes' if r['sustained'] else 'no'} |")


def format_text(res: dict) -> str:
    p, lim = res["saturation"]["pipeline"], res["saturation"]["limit"]
    head = ["| vehicles | offered samples/s | published | sustained end to end | p50 ms | p99 ms | p99 from due ms "
            "| fleet put lag p50 / p99 ms | warm-up p99 ms | lost | CPU % per stage | RSS MB | sustained |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    wire = res.get("wire", "v1")
    lines = [f"stages: {' → '.join(res['stages'])}; DMC outputs counted on "
             + ("its fleet frames" if res.get("sink") == "frames" else "every vehicle's dmc key") + f"; wire {wire}"
             + (f" (a batch per vehicle per {res['window_s'] * 1000:g} ms"
                + (", binary columns)" if wire == "v3" else ")") if wire in ("v2", "v3") else ""),
             f"saturation ({p['vehicles']} vehicles, as fast as possible): pipeline {p['sustained_samples_s']:.0f} "
             f"samples/s, no-processing limit {lim['sustained_samples_s']:.0f} samples/s → ratio "
             f"{res['ratio_to_limit']:.2f}"]
    goal = res.get("p99_goal_ms", 50.0)
    by_k = res.get("by_instances") or {"1": {"scaling": res["scaling"], "max_vehicles": res["max_vehicles"]}}
    if len(by_k) == 1:
        lines += ["", *head]
    for k, t in by_k.items():
        if len(by_k) > 1:
            lines += ["", f"{k} instance{'s' if k != '1' else ''} per stage:", "", *head]
        lines += [_row(r) for r in t["scaling"]]
        if t["scaling"] and t["scaling"][-1].get("cpu_threads_pct"):  # (the largest count: where a set-up fails)
            r = t["scaling"][-1]
            per = [f"{stage} " + ", ".join(f"{k} {v:.0f}" for k, v in sorted(kinds.items(), key=lambda x: -x[1])
                                           if round(v) >= 1) for stage, kinds in r["cpu_threads_pct"].items()]
            lines.append(f"\nCPU % by kind of thread at {r['vehicles']} vehicles: " + "; ".join(per))
    lines.append(f"\nmax vehicles sustained (zero loss, p99 ≤ {goal:g} ms): "
                 + ("; ".join(f"{t['max_vehicles']} with {k} instance{'s' if k != '1' else ''} per stage"
                              for k, t in by_k.items()) if len(by_k) > 1 else str(res["max_vehicles"])))
    if res.get("v1_ingest"):
        lines += ["", "v1 single-sample vehicles through one ingest (fleet frames out):", "", *head]
        lines += [_row(r) for r in res["v1_ingest"]]
        lines.append(f"\nv1 vehicles one ingest sustains: {res['v1_ingest_max_vehicles']}")
    o = res.get("overload")
    if o:
        reasons = ", ".join(f"{k} {v}" for k, v in sorted(o["by_reason"].items())) or "none"
        lines += ["", f"overload: {o['peak_vehicles']} vehicles for {o['overload_s']:g} s, then {o['vehicles']} for "
                  f"{o['calm_s']:g} s — crashed: {', '.join(o['crashed']) or 'none'}; outputs missing "
                  f"{o['missing_outputs']}, counted by stages {o['counted_drops']} ({reasons}), uncounted "
                  f"{o['uncounted']}; p99 {o['overload_p99_ms']} ms under overload, {o['recovered_p99_ms']} ms in the "
                  f"calm's last half → {'recovered' if o['recovered'] else 'NOT recovered'}"]
    return "\n".join(lines)
