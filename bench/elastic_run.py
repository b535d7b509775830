"""One elastic-group run for the mesh tests and ``magmesh eval elastic``: a fleet of simulated cars publishing
clean magnetometer streams, the DMC detector as a group (``instances = N`` under ``magmesh up``), kills and
scalings on a schedule, and everything the mesh carried, checked from outside.

The checks (:func:`check_run`) are made on what subscribers saw:

- each vehicle's ``dmc`` stream: seq never repeats or goes back, epochs never repeat; every seq gap lies on a
  vehicle held by a killed instance at its kill (outputs it had sent that never left it) and every epoch missing
  (a pair of clean samples without a ``dmc`` output) is counted: ``lost_in_takeover`` by the instance that took
  the vehicle over, ``upstream_gap`` (an input gap its holder saw), or one of those seq gaps;
- each vehicle's ``alarm/dmc``: seq contiguous and states alternating (no transition lost or repeated);
- for the vehicles no kill touched (moved only by hand-overs), the alarm transitions equal those of one detector
  fed every epoch offline (the same code, the same samples): a move caused no transition and hid none.

With ``frames`` the fleet publishes raw batches (binary columns, a batch per vehicle per 50 ms) to an ingest
process with ``output = "frames"``: the members take its ``magmesh/fleet/{ingest}/clean`` frames, each cut to the
vehicles it holds. Checked besides (:func:`check_dmc_frames`): each member's ``magmesh/fleet/{member}/dmc`` frames
carry exactly the dmc rows it published (every row of a frame is a published per-vehicle dmc message with the
same seq and time, every published message is in one frame, none in two).
"""

from __future__ import annotations

import json
import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path
from typing import Any

import msgpack

REPO = Path(__file__).resolve().parent.parent
ROLE = "dmc_detector"


def vehicle_ids(n: int) -> list[str]:
    return [f"bench-{i:04d}" for i in range(n)]  # bench/fleet.py's names


def write_manifest(path: Path, n_vehicles: int, instances: int, endpoint: str, frames: bool = False) -> Path:
    """A mesh of one group process (the DMC detector) and the fleet's vehicles, each with the simulated car's
    compensation (bench/fleet.py replays the car simulator's drive, vehicle_seed 7 as car-1); ``frames``: and an
    ingest process emitting fleet frames (20 ms)."""
    with open(REPO / "deploy" / "mesh.toml", "rb") as f:
        car = tomllib.load(f)["vehicles"]["car-1"]
    lines = ["[mesh]", f'endpoint = "{endpoint}"', "status_period_s = 0.5", ""]
    for vid in vehicle_ids(n_vehicles):
        lines += [f"[vehicles.{vid}]", 'kind = "car"', f"declination_rad = {car['declination_rad']!r}"]
        for sensor, t in car["mag_params"].items():
            lines += [f'[vehicles.{vid}.mag_params."{sensor}"]', f"offset_nt = {list(t['offset_nt'])!r}",
                      f"matrix = {list(t['matrix'])!r}", f"field_radius_nt = {t['field_radius_nt']!r}"]
    lines += ["", "[[process]]", 'name = "dmc"', 'module = "services.dmc_detector"', f"instances = {instances}",
              'args = ["--impl", "threshold"]', "settings = {}", ""]
    if frames:
        lines += ["[[process]]", 'name = "ingest"', 'module = "services.ingest"',
                  'settings = { output = "frames", batch_window_s = 0.02 }', ""]
    path.write_text("\n".join(lines))
    return path


def magmesh(*args: str, timeout: float = 180.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "magmesh", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


def statuses(client, timeout: float = 3.0) -> dict[str, dict]:
    from schemas import keys

    out = {}
    for rep in client.get(keys.svc_status(ROLE, "*"), timeout=timeout):
        if rep.ok is not None:
            st = msgpack.unpackb(rep.ok.payload.to_bytes(), strict_map_key=False)
            out[st["instance"]] = st
    return out


def group_view(client) -> tuple[dict[str, list[str]], dict[str, dict]]:
    """(instance → vehicles it holds, statuses) as the group's live members report them."""
    sts = statuses(client)
    return {i: list(st["group"]["vehicles"]) for i, st in sts.items() if "group" in st}, sts


def wait_settled(client, vehicles: list[str], members: list[str], timeout: float) -> tuple[bool, dict, float]:
    """Wait until exactly ``members`` answer and each vehicle is held by one of them, the one the rendezvous rule
    names, with nothing in flight; (settled, view, seconds waited)."""
    from magmesh import groups

    t0 = time.monotonic()
    view: dict = {}
    while time.monotonic() - t0 < timeout:
        view, sts = group_view(client)
        if sorted(view) == sorted(members):
            held = [v for vs in view.values() for v in vs]
            busy = any(st["group"]["warming"] or st["group"]["taking"] or st["group"]["releasing"]
                       for st in sts.values() if "group" in st)
            if not busy and sorted(held) == sorted(vehicles) and all(
                    groups.owner(v, members) == m for m, vs in view.items() for v in vs):
                return True, view, time.monotonic() - t0
        time.sleep(0.3)
    return False, view, time.monotonic() - t0


def kill_member(client, inst: str) -> tuple[float, list[str], float]:
    """SIGKILL ``inst``; (wall time of the kill, the vehicles it held, monotonic time of the kill)."""
    view, sts = group_view(client)
    st = sts[inst]
    os.kill(st["pid"], signal.SIGKILL)
    return time.time(), list(view.get(inst, [])), time.monotonic()


def wait_taken(client, vehicles: list[str], dead: str, timeout: float = 30.0) -> float:
    """Seconds until every vehicle of a killed member is held by a live member (inf if not in time)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        view, _ = group_view(client)
        held = {v for m, vs in view.items() if m != dead for v in vs}
        if set(vehicles) <= held:
            return time.monotonic() - t0
        time.sleep(0.1)
    return float("inf")


def reference_transitions(clean: dict[str, list[dict]], manifest: Path, start_t: dict[str, float]) -> dict:
    """The alarm transitions of one DMC detector (the service's own code, threshold implementation) fed every
    clean sample of each vehicle from ``start_t[vehicle]`` on, in the order the mesh carried them."""
    from schemas import keys
    from services.dmc_detector.service import ThresholdDmcDetector

    with open(manifest, "rb") as f:
        vconf = tomllib.load(f).get("vehicles", {})

    class _Rt:
        mode = "active"
        alarm_adopted = 0  # alarm states never come from elsewhere here

        def __init__(self, svc):
            self.svc, self.alarm_published, self.raised, self.vehicle_state, self.out = svc, {}, {}, {}, []

        def publish(self, key, msg_type, vehicle, t_s, fields):
            return {}

        def publish_rows(self, msg_type, keys_, vehicles, t_s, cols, mirror=None):
            return [0] * len(keys_)

        def raised_alarm(self, key):
            return dict(self.raised.get(key) or {})

        def publish_alarm(self, key, vehicle, t_s, fields):
            if self.alarm_published.get(key, "cleared") == fields["state"]:
                return None
            self.alarm_published[key] = fields["state"]
            if fields["state"] == "raised":
                self.raised[key] = {"t_s": t_s, **fields}
            else:
                self.raised.pop(key, None)
            self.out.append((vehicle, round(t_s, 6), fields["state"]))
            return {}

        def count_drop(self, *a, **k):
            pass

        def count_join_loss(self, *a, **k):
            pass

        def reject(self, *a, **k):
            pass

        def state_for(self, v):
            if v not in self.vehicle_state:
                self.vehicle_state[v] = self.svc.new_vehicle(v)
            return self.vehicle_state[v]

    svc = ThresholdDmcDetector(None, "reference", "*", vconf)
    rt = _Rt(svc)
    svc._rt = rt
    for v, msgs in clean.items():
        t0 = start_t.get(v)
        if t0 is None:
            continue
        for m in msgs:
            if m["t_s"] < t0:
                continue
            info = keys.parse(keys.clean_mag(v, m["sensor"]))
            svc.on_message(info, m, rt.state_for(v))
    out: dict[str, list] = {}
    for v, t, s in rt.out:
        out.setdefault(v, []).append((t, s))
    return out


def check_run(data: list[tuple[str, Any]], final: dict[str, dict], kills: list[dict], manifest: Path,
              vehicles: list[str]) -> dict:
    """The figures of a run and the problems found (an empty ``problems`` list is a pass)."""
    from schemas import keys

    problems: list[str] = []
    dmc: dict[str, list[dict]] = {v: [] for v in vehicles}
    alarms: dict[str, list[dict]] = {v: [] for v in vehicles}
    clean: dict[str, list[dict]] = {v: [] for v in vehicles}
    for k, m in data:
        if not isinstance(m, dict) or m.get("vehicle") not in dmc:
            continue
        if k == keys.dmc(m["vehicle"]):
            dmc[m["vehicle"]].append(m)
        elif k == keys.alarm(m["vehicle"], "dmc"):
            alarms[m["vehicle"]].append(m)
        elif "/clean/mag/" in k:
            clean[m["vehicle"]].append(m)
    # the test's own subscriber must have every clean sample, or nothing below can be decided
    for v in vehicles:
        for s in ("1", "2"):
            seqs = [m["seq"] for m in clean[v] if m["sensor"] == s]
            if not seqs or seqs != list(range(seqs[0], seqs[0] + len(seqs))):
                problems.append(f"the test's subscriber lost clean/mag/{s} samples of {v}")
    killed_vehicles = {v for k in kills for v in k["vehicles"]}
    lost = {}  # per vehicle: lost_in_takeover (max over the two sensors' keys) over every live member
    lost_sum = {}  # per vehicle: the same, summed over the two keys
    up_v = {}  # per vehicle: input seq gaps the detector saw on the vehicle's samples (upstream_gap)
    for v in vehicles:
        per_key = [max((int(((st.get("drops") or {}).get(keys.clean_mag(v, s)) or {}).get("lost_in_takeover", 0))
                        for st in final.values()), default=0) for s in ("1", "2")]
        lost[v] = max(per_key)
        lost_sum[v] = sum(per_key)
        up_v[v] = max(sum(int(((st.get("drops") or {}).get(keys.clean_mag(v, s)) or {}).get("upstream_gap", 0))
                          for st in final.values()) for s in ("1", "2"))
    upstream = sum(int(d.get("upstream_gap", 0)) for st in final.values() for k, d in (st.get("drops") or {}).items()
                   if "/clean/mag/" in k)
    seq_missing = {}
    duplicates = 0
    epochs_missing = {}
    for v in vehicles:
        ms = dmc[v]
        if not ms:
            problems.append(f"no dmc output for {v}")
            continue
        seqs = [m["seq"] for m in ms]
        ts = [m["t_s"] for m in ms]
        back = sum(1 for a, b in zip(seqs, seqs[1:], strict=False) if b <= a)
        duplicates += back + sum(1 for a, b in zip(ts, ts[1:], strict=False) if b <= a)
        seq_missing[v] = sum(b - a - 1 for a, b in zip(seqs, seqs[1:], strict=False) if b > a + 1)
        t_dmc = set(ts)
        pairs = {m["t_s"] for m in clean[v] if m["sensor"] == "1"} & {m["t_s"] for m in clean[v] if m["sensor"] == "2"}
        epochs_missing[v] = sum(1 for t in pairs if ts[0] <= t <= ts[-1] and t not in t_dmc)
        if seq_missing[v] and v not in killed_vehicles:
            problems.append(f"{v}: {seq_missing[v]} dmc seq missing, but no kill touched it")
        # every missing epoch counted: by the new owner of a dead member's vehicle (lost_in_takeover), as an input
        # gap the holder saw (upstream_gap), or as an output the killed process never got out (a seq gap)
        # one outage misses both samples of each epoch (one more when the kill split a pair): exact for a vehicle one
        # kill touched; with several outages each has its own split, so the count lies between max and sum
        n_kills = sum(1 for k in kills if v in k["vehicles"])
        extra = up_v[v] + seq_missing[v]
        ok = epochs_missing[v] == lost[v] + extra if n_kills <= 1 else \
            lost[v] + extra <= epochs_missing[v] <= lost_sum[v] + extra
        if not ok:
            problems.append(f"{v}: {epochs_missing[v]} epochs missing, counted lost_in_takeover {lost[v]} + "
                            f"upstream_gap {up_v[v]} + {seq_missing[v]} sent by a killed instance but never out of it")
    if duplicates:
        problems.append(f"{duplicates} dmc outputs repeated or out of order")
    lost_tr = repeated_tr = 0
    for v in vehicles:
        a = alarms[v]
        seqs = [m["seq"] for m in a]
        lost_tr += sum(b - x - 1 for x, b in zip(seqs, seqs[1:], strict=False) if b > x + 1)
        states = [m["state"] for m in a]
        repeated_tr += sum(1 for x, b in zip(states, states[1:], strict=False) if x == b)
        repeated_tr += sum(1 for x, b in zip(seqs, seqs[1:], strict=False) if b <= x)
    if lost_tr or repeated_tr:
        problems.append(f"alarm transitions: {lost_tr} lost, {repeated_tr} repeated")
    # (only the vehicles compared: the offline detector is the costly part of a long run)
    ref = reference_transitions(clean, manifest, {v: dmc[v][0]["t_s"] for v in vehicles
                                                  if dmc[v] and v not in killed_vehicles})
    changed = []
    compared = 0
    for v in vehicles:
        if v in killed_vehicles or not dmc[v]:
            continue
        got = [(round(m["t_s"], 6), m["state"]) for m in alarms[v]]
        want = ref.get(v, [])
        compared += len(want)
        if got != want:
            changed.append(f"{v}: mesh {got} vs one detector {want}")
    if changed:
        problems.append("alarm transitions differ from one detector fed every epoch: " + "; ".join(changed)[:2000])
    return {"problems": problems, "seq_missing": sum(seq_missing.values()), "duplicates": duplicates,
            "epochs_missing": sum(epochs_missing.values()), "lost_in_takeover": sum(lost.values()),
            "upstream_gap": upstream, "upstream_gap_per_vehicle": {v: n for v, n in up_v.items() if n},
            "lost_alarm_transitions": lost_tr, "repeated_alarm_transitions": repeated_tr,
            "alarm_transitions": sum(len(a) for a in alarms.values()),
            "reference_transitions_compared": compared, "transitions_changed_by_moves": len(changed),
            "dmc_outputs": sum(len(x) for x in dmc.values())}


def output_lag(items: list[tuple[str, Any, float]]) -> dict:
    """How far the dmc outputs trailed the fleet: arrival at the subscriber minus the sample time (the fleet
    stamps each sample with the wall clock when it publishes it), in seconds: p50, p99, max and the last 10 s of
    outputs' p50 (a group that keeps up stays at tens of ms; one falling behind grows through the run)."""
    import numpy as np

    lag = np.array([t - m["t_s"] for _k, m, t in items if isinstance(m, dict) and "t_s" in m], float)
    if not lag.size:
        return {"lag_s_p50": None, "lag_s_p99": None, "lag_s_max": None, "lag_s_last10_p50": None}
    t_arr = np.array([t for _k, m, t in items if isinstance(m, dict) and "t_s" in m], float)
    tail = lag[t_arr >= t_arr.max() - 10.0]
    return {"lag_s_p50": round(float(np.percentile(lag, 50)), 3), "lag_s_p99": round(float(np.percentile(lag, 99)), 3),
            "lag_s_max": round(float(lag.max()), 3), "lag_s_last10_p50": round(float(np.percentile(tail, 50)), 3)}


def dump(path: Path, obj: Any) -> None:
    path.write_text(json.dumps(obj, default=str, indent=1))


def free_port() -> int:
    """A loopback port free now (the tests use tests/meshutil.free_port and pass it in)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Collector:
    """Every sample on a key expression, decoded (``raw``: its payload bytes), with its arrival time (wall
    clock)."""

    def __init__(self, session: Any, keyexpr: str, raw: bool = False):
        import zenoh

        self.raw = raw
        self.items: list[tuple[str, Any, float]] = []
        self.sub = session.declare_subscriber(keyexpr, zenoh.handlers.FifoChannel(1_000_000))
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while True:
            try:
                s = self.sub.recv()
            except Exception:  # noqa: BLE001 - the session closed
                return
            if self.raw:
                self.items.append((str(s.key_expr), s.payload.to_bytes(), time.time()))
                continue
            try:
                m = msgpack.unpackb(s.payload.to_bytes(), strict_map_key=False)
            except Exception:  # noqa: BLE001
                m = None
            self.items.append((str(s.key_expr), m, time.time()))


def frame_rows(items: list[tuple[str, bytes, float]]) -> tuple[list[tuple[str, dict]], list[str]]:
    """Fleet frames as the per-vehicle messages of their rows, ``(per-vehicle key, message)``, and the problems
    met (a frame that does not decode, frames of one publisher missing)."""
    from magmesh.frames import stream_key
    from schemas import frame as fleetframe

    out: list[tuple[str, dict]] = []
    problems: list[str] = []
    last: dict[str, int] = {}
    for k, payload, _t in items:
        try:
            fr = fleetframe.decode(payload, where=k)
        except Exception as e:  # noqa: BLE001 - reported, the run goes on
            problems.append(f"a frame on {k} does not decode: {e}")
            continue
        if k in last and fr.seq != last[k] + 1:
            problems.append(f"frames on {k} went from seq {last[k]} to {fr.seq}")
        last[k] = fr.seq
        for name, st in fr.streams.items():
            g_vi, starts, ends = st.groups()
            for i, a, b in zip(g_vi.tolist(), starts.tolist(), ends.tolist(), strict=True):
                v = fr.vehicles[i]
                key = stream_key(fr.kind, v, name)
                out.extend((key, m) for m in st.messages(v, a, b))
    return out, problems


def check_dmc_frames(frames: list[tuple[str, bytes, float]], dmc: list[tuple[str, dict]], kills: list[dict]) -> dict:
    """Each member's dmc frames mirror the dmc rows it published: every frame row is a published per-vehicle
    message (same vehicle, seq, time), every published message is in exactly one frame row. A message of a
    vehicle a killed member held may lack its frame (the member died between the two puts)."""
    from schemas import frame as fleetframe

    published = {(m["vehicle"], m["seq"]): m["t_s"] for _k, m in dmc if isinstance(m, dict)}
    seen: dict[tuple[str, int], str] = {}
    twice = foreign = 0
    shards: dict[str, set[str]] = {}
    problems: list[str] = []
    for k, payload, _t in frames:
        fr = fleetframe.decode(payload, where=k)
        st = fr.streams.get("dmc")
        if st is None:
            continue
        vis = st.vi.tolist()
        for i, (sq, t) in enumerate(zip(st.seq.tolist(), st.t_s.tolist(), strict=True)):
            v = fr.vehicles[vis[i]]
            shards.setdefault(fr.shard, set()).add(v)
            if (v, sq) in seen:
                twice += 1
                continue
            seen[(v, sq)] = fr.shard
            if published.get((v, sq)) != t:
                foreign += 1
    missing = [x for x in published if x not in seen]
    killed = {v for e in kills for v in e["vehicles"]}
    unexplained = [x for x in missing if x[0] not in killed]
    if twice:
        problems.append(f"{twice} dmc rows in two frames")
    if foreign:
        problems.append(f"{foreign} dmc frame rows that are no published dmc message (vehicle, seq, time)")
    if unexplained:
        problems.append(f"{len(unexplained)} published dmc messages in no frame, of vehicles no kill touched: "
                        f"{unexplained[:5]}")
    return {"problems": problems, "dmc_frame_rows": len(seen), "dmc_rows_in_two_frames": twice,
            "dmc_frame_rows_not_published": foreign, "dmc_published_not_in_frames": len(missing),
            "dmc_frame_shards": {s: len(vs) for s, vs in sorted(shards.items())}}


def run_scenario(work: Path, n_vehicles: int, instances: int, steps: list[tuple], duration_s: float,
                 port: int | None = None, seed: int = 1, settle_timeout_s: float = 90.0,
                 end_after_steps_s: float | None = None, save_data: bool = False, frames: bool = False,
                 split_state: bool = False) -> dict:
    """Run the fleet and the group under ``magmesh up`` and play ``steps``: ``("kill",)`` (SIGKILL a member that
    holds vehicles, chosen with ``seed``; the supervisor restarts it and it rejoins; ``("kill", "spare")``: the
    member holding the fewest vehicles no kill has touched yet, so that some are left whose alarm transitions can be
    compared with one detector's), ``("scale", n)``
    (``magmesh scale dmc n``), ``("wait", s)``. The fleet publishes for ``duration_s``, or stops
    ``end_after_steps_s`` after the last step (``save_data``: what the subscribers saw also goes to
    ``work/seen.msgpack``). ``frames``: the fleet goes through ingest as fleet frames (see the module's
    docstring). ``split_state``: no supervisor; the members are started by hand, each with a state directory of
    its own (``work/host-{i}``), as instances on different hosts would be: a killed member's journal and alarm
    file are not where the survivors look; once its vehicles are taken over it is started again on its "host"
    (as a supervisor there would). Returns everything seen and measured."""
    import zenoh

    from magmesh import zconf
    from schemas import keys

    work.mkdir(parents=True, exist_ok=True)
    port = port or free_port()
    ep = f"tcp/127.0.0.1:{port}"
    manifest = write_manifest(work / "mesh.toml", n_vehicles, instances, ep, frames=frames)
    env = {**os.environ, "MAGMESH_STATE_DIR": str(work / "state"), "PYTHONUNBUFFERED": "1"}
    rng = random.Random(seed)
    vehicles = vehicle_ids(n_vehicles)
    load_start = [round(x, 2) for x in os.getloadavg()]  # the machine's load (1, 5, 15 min), for the conditions
    members = [f"dmc-{i}" for i in range(1, instances + 1)]
    router = None
    procs: dict[str, subprocess.Popen] = {}

    def start_member(m: str) -> None:
        procs[m] = subprocess.Popen(
            [sys.executable, "-m", "services.dmc_detector", "--impl", "threshold", "--group", "dmc", "--instance",
             m, "--manifest", str(manifest), "--connect", ep], cwd=REPO,
            env={**env, "MAGMESH_STATE_DIR": str(work / f"host-{m}")},
            stdout=open(work / "logs" / f"{m}.log", "ab"), stderr=subprocess.STDOUT, start_new_session=True)

    if split_state:
        import zenoh

        from magmesh import zconf

        router = zenoh.open(zconf.build_config(mode="router", listen=[ep]))
        (work / "logs").mkdir(exist_ok=True)
        for m in members:
            start_member(m)
        sup = None
    else:
        sup = subprocess.Popen([sys.executable, "-m", "magmesh", "up", str(manifest), "--quiet", "--log-dir",
                                str(work / "logs"), "--duration", str(duration_s + 300)], cwd=REPO, env=env,
                               stdout=open(work / "up.log", "ab"), stderr=subprocess.STDOUT, start_new_session=True)
    fleet = None
    events: list[dict] = []
    problems: list[str] = []
    client = None
    try:
        deadline = time.monotonic() + 30
        while client is None:
            try:
                client = zenoh.open(zconf.build_config(connect=[ep]))
            except Exception:  # noqa: BLE001 - the router is not up yet
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.3)
        data = [Collector(client, keys.dmc("*")), Collector(client, keys.alarm("*", "dmc"))]
        if frames:
            data += [Collector(client, keys.fleet_frames("clean"), raw=True),
                     Collector(client, keys.fleet_frames("dmc"), raw=True)]
        else:
            data.append(Collector(client, "magmesh/*/clean/mag/*"))
        t0 = time.monotonic()
        while time.monotonic() - t0 < settle_timeout_s and (sorted(group_view(client)[0]) != members or (
                frames and not any(r.ok for r in client.liveliness().get(keys.svc_token("ingest", "ingest"),
                                                                         timeout=2.0)))):
            time.sleep(0.3)
        # v1 single samples straight on clean/ (as ingest would publish them), or raw batches through ingest
        how = ["--wire", "v3", "--window", "0.05"] if frames else ["--stream", "clean"]
        fleet = subprocess.Popen([sys.executable, "-m", "bench.fleet", "--connect", ep, "--vehicles",
                                  str(n_vehicles), "--duration", str(duration_s), *how], cwd=REPO,
                                 env=env, stdout=open(work / "fleet.json", "wb"),
                                 stderr=open(work / "fleet.log", "ab"), start_new_session=True)
        ok, view, took = wait_settled(client, vehicles, members, settle_timeout_s)
        events.append({"step": "start", "settled": ok, "settle_s": round(took, 2), "assignment": view})
        if not ok:
            problems.append(f"the {instances} instances did not settle on the fleet in {settle_timeout_s:g} s: {view}")
        for step in steps:
            if step[0] == "wait":
                time.sleep(float(step[1]))
            elif step[0] == "kill":
                view, _ = group_view(client)
                holding = sorted(m for m, vs in view.items() if vs)
                if not holding:
                    problems.append(f"no member answered holding a vehicle: no kill ({view})")
                    continue
                inst = rng.choice(holding)
                if len(step) > 1 and step[1] == "spare":
                    touched = {v for e in events if e["step"] == "kill" for v in e["vehicles"]}
                    inst = min(holding, key=lambda m: (len(set(view[m]) - touched), m != inst))
                t_kill, held, m_kill = kill_member(client, inst)
                taken = wait_taken(client, held, inst)
                # outputs resuming for every vehicle it held, as subscribers saw them
                deadline = time.time() + 30
                resumed: dict[str, float] = {}
                start = max(0, len(data[0].items) - 100_000)
                while time.time() < deadline and len(resumed) < len(held):
                    for _k, m, t_arr in data[0].items[start:]:
                        v = m.get("vehicle") if isinstance(m, dict) else None
                        if v in held and v not in resumed and t_arr > t_kill and m["t_s"] > t_kill:
                            resumed[v] = t_arr - t_kill
                    time.sleep(0.05)
                takeover = max(resumed.values()) if len(resumed) == len(held) and held else float("inf")
                if split_state:  # started again on its own "host", with its own state directory
                    procs[inst].wait(10)
                    start_member(inst)
                ok, view, took = wait_settled(client, vehicles, members, settle_timeout_s)
                events.append({"step": "kill", "instance": inst, "vehicles": held, "t_wall": t_kill,
                               "taken_s": round(taken, 3), "takeover_s": round(takeover, 3),
                               "rejoined_settled": ok, "settle_s": round(took, 2)})
                if not ok:
                    problems.append(f"after the kill of {inst} the group did not settle again: {view}")
            elif step[0] == "scale":
                n = int(step[1])
                r = magmesh("scale", "dmc", str(n), "--connect", ep, "--json")
                try:
                    res = json.loads(r.stdout)
                except ValueError:
                    res = {"ok": False, "error": r.stdout + r.stderr}
                members = [f"dmc-{i}" for i in range(1, n + 1)] if res.get("ok") else members
                ok, view, took = wait_settled(client, vehicles, members, settle_timeout_s)
                events.append({"step": "scale", "n": n, "reply": res, "settled": ok, "settle_s": round(took, 2),
                               "assignment": view})
                if not res.get("ok") or not ok or res.get("instances") != members:
                    problems.append(f"scale to {n}: reply {res}, settled {ok}: {view}")
        if end_after_steps_s is not None:
            time.sleep(end_after_steps_s)
            os.killpg(fleet.pid, signal.SIGKILL)
        fleet.wait(duration_s + 120)
        time.sleep(3.0)  # the last samples pass through
        final = statuses(client)
        status_cli = magmesh("status", "--connect", ep, "--json", timeout=60)
        sup_status = None
        for rep in client.get(keys.svc_status("supervisor", "main"), timeout=3.0):
            if rep.ok is not None:
                sup_status = msgpack.unpackb(rep.ok.payload.to_bytes(), strict_map_key=False)
    finally:
        if fleet is not None and fleet.poll() is None:
            os.killpg(fleet.pid, signal.SIGKILL)
        for p in [sup, *procs.values()]:
            if p is None or p.poll() is not None:
                continue
            os.killpg(p.pid, signal.SIGINT)
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)
        if client is not None:
            client.close()
        if router is not None:
            router.close()
    items = [(k, m) for c in data if not c.raw for k, m, _ in c.items]
    frame_problems: list[str] = []
    if frames:  # the clean samples as per-vehicle messages, from the frames that carried them
        rows, frame_problems = frame_rows(data[2].items)
        items += rows
    if save_data:  # everything the subscribers saw, for a look afterwards (msgpack: key, message, arrival)
        dump(work / "final_status.json", {"final": final, "events": events, "supervisor": sup_status})
        with open(work / "seen.msgpack", "wb") as f:
            for c in data:
                for it in c.items:
                    f.write(msgpack.packb(it, use_bin_type=True))
    kills = [e for e in events if e["step"] == "kill"]
    figures = check_run(items, final, kills, manifest, vehicles)
    figures.update(output_lag(data[0].items))
    figures["frames"] = frames
    if frames:
        ff = check_dmc_frames(data[3].items, [(k, m) for k, m, _ in data[0].items], kills)
        figures["problems"] += frame_problems + ff.pop("problems")
        figures.update(ff)
    try:
        status_json = json.loads(status_cli.stdout)
    except ValueError:
        status_json = {"error": status_cli.stdout + status_cli.stderr}
    return {"events": events, "problems": problems + figures.pop("problems"), "figures": figures, "final": final,
            "status_cli": status_json, "supervisor": sup_status, "manifest": str(manifest),
            "load_avg": {"start": load_start, "end": [round(x, 2) for x in os.getloadavg()]},
            "fleet": _fleet_report(work / "fleet.json")}


def _fleet_report(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None  # stopped before it reported
