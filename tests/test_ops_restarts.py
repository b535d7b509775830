"""kill -9 of each service of the demo in turn, checked from outside on everything the mesh carried.

The demo manifest (deploy/mesh.toml) runs under ``magmesh up`` as ``./run demo`` starts it, on the test's own
port and state directory. One subscriber on ``magmesh/**`` keeps every sample with its arrival time. For each
service killed (SIGKILL of the pid its status reports; the supervisor restarts it):

- every input sample it missed is counted, exactly: its status names the seq ranges it counted
  ``lost_during_restart`` per input key; their sizes add up to the counter; every sample in them was published
  and reached the mesh between the kill and the restarted instance serving again; every sample that reached the
  mesh while it was surely down (between the kill and its liveliness token coming back) is in them;
- where an output follows its input one to one (raw → clean, clean/mag → cal/mag, magnetometer pairs → dmc,
  GNSS → track), the inputs with no output are exactly the ones counted (and, at ingest, the ones rejected);
- every output stream's seq runs on without a gap or a repeat (the journal continues it), and no service counts
  any other loss (no upstream_gap anywhere);
- every alarm stream alternates raised/cleared with a contiguous seq (no repeated "raised", none skipped), and
  no restart publishes a transition: a restored raised alarm stays raised until the restarted logic decides.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections import defaultdict

import msgpack
import numpy as np
import pytest
from meshutil import REPO, endpoint, free_port, open_client, query_status, stop, wait_alive

from schemas import keys

pytestmark = pytest.mark.mesh

ROLES = {"ingest-1": "ingest", "calibration-1": "calibration", "dmc-1": "dmc_detector",
         "dmc-broad-1": "dmc_detector", "heading-1": "heading_fuser", "geomag-1": "geomag_matcher",
         "track-1": "track_monitor"}


def one_to_one(inst: str, in_keys: list[str]) -> list[tuple[tuple[str, ...], str]]:
    """(input keys, output key) where each input sample (all of them at one t_s) gives one output at its t_s."""
    if inst == "ingest-1":
        return [((k,), k.replace("/raw/", "/clean/")) for k in in_keys if "/raw/" in k]
    if inst == "calibration-1":  # the vehicles with compensation parameters in the demo manifest
        return [((k,), k.replace("/clean/mag/", "/cal/mag/")) for k in in_keys
                if "/clean/mag/" in k and k.split("/")[1] in ("car-1", "broad-1")]
    if inst == "dmc-1":
        return [((keys.clean_mag("car-1", "1"), keys.clean_mag("car-1", "2")), keys.dmc("car-1"))]
    if inst == "dmc-broad-1":
        return [((keys.clean_mag("broad-1", "1"),), keys.dmc("broad-1"))]
    if inst == "track-1":
        return [((keys.clean_gnss("drone-1"),), keys.track("drone-1"))]
    return []


def frame_rows_keys(in_keys: list[str], tap) -> list[str]:
    """A fleet frame input (the DMC detector's dmc frames) stands for its rows, numbered per vehicle key: the
    per-vehicle keys the frames carried (the detector puts the same rows, same seqs, there), and restart gaps are
    counted on those."""
    out = [k for k in in_keys if not k.startswith("magmesh/fleet/")]
    data = tap.snapshot()
    for k in in_keys:
        if not k.startswith("magmesh/fleet/"):
            continue
        kind = k.rsplit("/", 1)[1]
        assert kind == "dmc", f"{k}: the check knows the per-vehicle keys of dmc frames only"
        vehicles = {v for _, m in data.get(k, []) for v in m["vehicles"]}
        assert vehicles, f"{k} taken but no frame seen on the mesh"
        out += [keys.dmc(v) for v in sorted(vehicles) if keys.dmc(v) not in out]
    return out


class Tap:
    """Every sample on magmesh/** (decoded) with its arrival time (monotonic s)."""

    def __init__(self, session):
        import zenoh

        self.by_key: dict[str, list[tuple[float, dict]]] = defaultdict(list)
        self.lock = threading.Lock()
        self.sub = session.declare_subscriber("magmesh/**", zenoh.handlers.FifoChannel(1_000_000))
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        while True:
            try:
                s = self.sub.recv()
            except Exception:
                return
            now = time.monotonic()
            try:
                m = msgpack.unpackb(s.payload.to_bytes())
            except Exception:
                continue
            if isinstance(m, dict) and "seq" in m:
                with self.lock:
                    self.by_key[str(s.key_expr)].append((now, m))

    def since(self, key: str, t: float) -> list[dict]:
        with self.lock:
            return [m for a, m in self.by_key.get(key, []) if a >= t]

    def snapshot(self) -> dict[str, list[tuple[float, dict]]]:
        with self.lock:
            return {k: list(v) for k, v in self.by_key.items()}


def status(client, inst: str, tries: int = 20) -> dict:
    for _ in range(tries):
        st = query_status(client, keys.svc_status(ROLES[inst], inst))
        if st is not None:
            return st
        time.sleep(0.5)
    raise AssertionError(f"{inst} does not answer status")


def kill_and_wait(client, tap: Tap, inst: str) -> dict:
    """SIGKILL ``inst``; wait for its token to go and come back and for each of its steady outputs to flow."""
    role = ROLES[inst]
    deadline = time.monotonic() + 120
    while True:  # serving: some steady output (a loaded machine starts slowly)
        before = status(client, inst)
        outs = [k for k, c in before["out"].items() if c["n"] >= 5 and "/alarm/" not in k and "/params/" not in k
                and not k.endswith("/rejects")]
        if outs or time.monotonic() > deadline:
            break
        time.sleep(1.0)
    assert outs, f"{inst} has no steady output to watch: {before['out']}"
    in_keys = frame_rows_keys(list(before["in"]), tap)
    t_kill = time.monotonic()
    os.kill(before["pid"], signal.SIGKILL)
    while time.monotonic() - t_kill < 5 and any(
            r.ok for r in client.liveliness().get(keys.svc_token(role, inst), timeout=0.5)):
        time.sleep(0.01)
    assert wait_alive(client, keys.svc_token(role, inst), 90), f"{inst} did not come back after kill -9"
    t_back = time.monotonic()
    deadline = t_back + 90
    while time.monotonic() < deadline and not all(tap.since(k, t_back) for k in outs):
        time.sleep(0.1)
    assert all(tap.since(k, t_back) for k in outs), f"{inst} came back but does not publish all of {outs}"
    t_serving = time.monotonic()
    return dict(inst=inst, pid=before["pid"], in_keys=in_keys, outs=outs, all_outs=list(before["out"]),
                t_kill=t_kill, t_back=t_back, t_serving=t_serving)


def run_demo(tmp_path, victims: list[str], only: str | None, settle_s: float = 4.0) -> dict:
    port = free_port()
    cmd = [sys.executable, "-m", "magmesh", "up", str(REPO / "deploy" / "mesh.toml"), "--endpoint", endpoint(port),
           "--duration", "1200", "--log-dir", str(tmp_path / "logs"), "--quiet"]
    if only:
        cmd += ["--only", only]
    sup = subprocess.Popen(cmd, cwd=REPO, stdout=open(tmp_path / "up.log", "ab"), stderr=subprocess.STDOUT,
                           start_new_session=True, env={**os.environ, "MAGMESH_STATE_DIR": str(tmp_path / "state")})
    client = open_client(port)
    kills = []
    try:
        tap = Tap(client)
        names = only.split(",") if only else list(ROLES)
        watched = [n for n in names if n in ROLES]
        for inst in watched:
            assert wait_alive(client, keys.svc_token(ROLES[inst], inst), 120), f"{inst} never came up"
        for inst in victims:
            time.sleep(settle_s)  # serving steadily (and the previous victim's outage well behind)
            kills.append(kill_and_wait(client, tap, inst))
        time.sleep(settle_s)  # the last samples pass through
        final, started = {}, {}
        for inst in watched:
            t_q = time.monotonic()
            final[inst] = status(client, inst)
            started[inst] = t_q - final[inst]["uptime_s"]  # when the running process's runtime began
        sup_status = query_status(client, keys.svc_status("supervisor", "main"))
        data = tap.snapshot()
    finally:
        stop(sup, 15)
        client.close()
    return dict(kills=kills, final=final, started=started, sup=sup_status, data=data)


def lost(st: dict, key: str) -> int:
    return int(((st.get("drops") or {}).get(key) or {}).get("lost_during_restart", 0))


def check(res: dict) -> list[str]:
    data, final = res["data"], res["final"]
    report: list[str] = []
    # every stream's seq runs on across the restarts: never a repeat; a gap only in an output of a killed
    # instance, at its kill (puts still in flight when the process died), and counted by every consumer
    out_gaps: dict[str, int] = defaultdict(int)
    for k, items in data.items():
        for (a0, m0), (a1, m1) in zip(items, items[1:], strict=False):
            d = m1["seq"] - m0["seq"]
            assert d >= 1, (f"{k}: seq repeated or went back ({m0['seq']} then {m1['seq']}; arrived {a0:.2f} and "
                            f"{a1:.2f}, t_s {m0.get('t_s')} and {m1.get('t_s')}, param_id {m0.get('param_id')} and "
                            f"{m1.get('param_id')}; kills: {[(kl['inst'], round(kl['t_kill'], 2)) for kl in res['kills']]})")
            if d == 1:
                continue
            at = [kl["inst"] for kl in res["kills"]
                  if k in kl["all_outs"] and a0 <= kl["t_kill"] + 0.5 and a1 >= kl["t_kill"]]
            assert at, (f"{k}: seq {m0['seq']} then {m1['seq']}, not at the kill of its publisher (a loss on the "
                        f"mesh, or on this test's own link when the machine is overloaded; arrived "
                        f"{a0:.2f}..{a1:.2f}; kills: {[(kl['inst'], round(kl['t_kill'], 2)) for kl in res['kills']]})")
            out_gaps[k] += d - 1
            report.append(f"{k.split('/', 1)[1]}: {d - 1} sample(s) in flight lost at the kill of {at[0]}")
    # no loss other than by the restarts, anywhere; the outputs lost in flight counted by their consumers
    for inst, st in final.items():
        other = {r: n for r, n in (st.get("lost") or {}).items() if r not in ("lost_during_restart", "upstream_gap")
                 and n}
        assert not other, f"{inst} counts loss not from a restart: {other}"
        assert not st.get("upstream_gaps"), f"{inst}: upstream gaps {st.get('upstream_gaps')}"
        link = 0
        for k in st["in"]:
            got = int(((st.get("drops") or {}).get(k) or {}).get("upstream_gap", 0))
            # every gap the mesh carried is counted; more only when this instance's own link lost samples (a
            # starved process's session reconnecting on a loaded machine): counted, so not silent
            assert got >= out_gaps.get(k, 0), f"{inst}: {k} upstream_gap {got}, seen on the mesh {out_gaps.get(k, 0)}"
            link += got - out_gaps.get(k, 0)
        if link:
            report.append(f"{inst}: {link} input samples missed on its own link, counted upstream_gap")
    restarts = {n: p["restarts"] for n, p in res["sup"]["processes"].items()}
    for inst in final:
        assert restarts[inst] == sum(1 for k in res["kills"] if k["inst"] == inst), (inst, restarts)
    for kill in res["kills"]:
        inst = kill["inst"]
        st = final[inst]
        gaps = st.get("restart_gaps") or {}
        total_counted = 0
        seen_missing = 0
        for k in kill["in_keys"]:
            items = data.get(k, [])
            by_seq = {m["seq"]: (a, m) for a, m in items}
            ranges = gaps.get(k, [])
            counted = {s for a, b in ranges for s in range(a, b + 1)}
            assert len(counted) == sum(b - a + 1 for a, b in ranges) == lost(st, k), (inst, k, ranges, lost(st, k))
            total_counted += len(counted)
            for s in sorted(counted):
                assert s in by_seq, f"{inst} counted {k} seq {s} lost, but it was never published"
                a = by_seq[s][0]
                # (long before the kill too: samples it had received but not handled, a backlog on a loaded
                # machine; the one-to-one checks below show they were not handled)
                assert a <= kill["t_serving"] + 2.0, (
                    f"{inst} counted {k} seq {s} lost, but it arrived {a - kill['t_kill']:+.2f} s from the kill "
                    f"(back serving at {kill['t_serving'] - kill['t_kill']:+.2f} s)")
            # published after the kill and before the new process's runtime began (it subscribes after that);
            # arrival at this test's own subscriber may lag publication by up to 1.5 s on a loaded machine
            surely = {m["seq"] for a, m in items if kill["t_kill"] + 1.5 <= a <= res["started"][inst]}
            seen_missing += len(surely)
            assert surely <= counted, (f"{inst}: {k} samples published while it was down are not counted lost: "
                                      f"{sorted(surely - counted)[:10]} (counted {ranges})")
        assert total_counted > 0, f"{inst}: the kill made it miss nothing: nothing checked"
        report.append(f"{inst}: down {kill['t_back'] - kill['t_kill']:.1f} s (serving again after "
                      f"{kill['t_serving'] - kill['t_kill']:.1f} s); {total_counted} input samples missed, counted "
                      f"{sum(lost(st, k) for k in kill['in_keys'])} lost_during_restart")
        # one-to-one outputs: the inputs without an output are exactly the counted (and rejected) ones
        rejected_t = defaultdict(set)
        for k, items in data.items():
            if k.endswith("/rejects"):
                for _, m in items:
                    if m.get("service") == inst:
                        rejected_t[m["key"]].add(m["t_s"])
        for ins, out in one_to_one(inst, kill["in_keys"]):
            outs = {m["t_s"] for _, m in data.get(out, [])}
            assert outs, f"no {out} at all"
            lo, hi = min(outs), max(outs)
            t_in = [{m["t_s"] for _, m in data.get(k, []) if lo <= m["t_s"] <= hi} for k in ins]
            both = set.intersection(*t_in)
            missing = both - outs
            expected = set()
            for k in ins:
                counted = {s for a, b in (gaps.get(k) or []) for s in range(a, b + 1)}
                expected |= {m["t_s"] for _, m in data.get(k, []) if m["seq"] in counted} | rejected_t[k]
            expected &= both
            # inputs missed on the instance's own link (counted upstream_gap beyond the mesh's gaps): by count
            extra = [int(((st.get("drops") or {}).get(k) or {}).get("upstream_gap", 0)) - out_gaps.get(k, 0)
                     for k in ins]
            # an output lost in flight at the kill is of an input counted lost_during_restart (killed between
            # the journal and the put) or of one counted handled (the put was queued but never left): either way
            lo, hi = max(extra), out_gaps.get(out, 0) + sum(extra)
            report.append(f"  {' + '.join(k.split('/', 2)[2] for k in ins)} -> {out.split('/', 2)[2]}: "
                          f"{len(missing)} without output: {len(expected)} counted lost_during_restart or rejected, "
                          f"{out_gaps.get(out, 0)} outputs lost in flight, {max(extra)} counted upstream_gap")
            assert expected <= missing and lo <= len(missing - expected) <= hi, (
                f"{inst} {ins} -> {out}: {len(missing)} inputs without output, {len(expected)} counted, "
                f"{out_gaps.get(out, 0)} outputs lost in flight, {extra} upstream_gap; not counted: "
                f"{sorted(missing - expected)[:8]}, counted but output: {sorted(expected - missing)[:8]}")
    # alarms: alternate, contiguous, and none from a restart
    for k, items in data.items():
        if "/alarm/" not in k:
            continue
        msgs = [m for _, m in items]
        states = [m["state"] for m in msgs]
        assert all(a != b for a, b in zip(states, states[1:], strict=False)), f"{k}: repeated transition {states}"
        restart_made = [m for m in msgs if "restart" in m.get("reason", "")]
        assert not restart_made, f"{k}: a restart published a transition the condition did not cause: {restart_made}"
        times = [a for a, _ in items]
        around = [sum(1 for a in times if kill["t_kill"] - 10 <= a < kill["t_kill"]) for kill in res["kills"]]
        after = [sum(1 for a in times if kill["t_kill"] <= a < kill["t_serving"] + 10) for kill in res["kills"]]
        report.append(f"{k.split('/', 1)[1]}: {len(states)} transitions ({', '.join(states[:6])}"
                      f"{', ...' if len(states) > 6 else ''}); in the 10 s before / after each kill: "
                      f"{list(zip(around, after, strict=False))}")
    return report


def test_kill_calibration_and_heading_fuser_loses_nothing_silently(tmp_path):
    res = run_demo(tmp_path, ["calibration-1", "heading-1"], only="sim-car-1,ingest-1,calibration-1,dmc-1,heading-1")
    lines = check(res)
    print("\n" + "\n".join(lines))


@pytest.mark.slow
def test_kill_every_service_of_the_demo_in_turn(tmp_path):
    res = run_demo(tmp_path, list(ROLES), only=None, settle_s=6.0)
    lines = check(res)
    print("\n" + "\n".join(lines))
    assert np.isfinite([k["t_serving"] for k in res["kills"]]).all()
