"""Elastic roles without a mesh: the manifest's ``instances``, ``magmesh scale`` mistakes, the runtime's
``--group`` flag, the assignment summary, and what a member reads of a dead member's persisted state."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from magmesh import groups
from magmesh.journal import Journal
from magmesh_cli.supervisor import ManifestError, Supervisor, command_for, load_manifest

REPO = Path(__file__).resolve().parent.parent

_GROUP = '[[process]]\nname = "dmc"\nmodule = "services.dmc_detector"\ninstances = {n}\n'


def _manifest(tmp_path, body: str) -> Path:
    p = tmp_path / "mesh.toml"
    p.write_text(body)
    return p


def test_instances_runs_a_group_named_after_the_process(tmp_path):
    m = load_manifest(_manifest(tmp_path, _GROUP.format(n=3)))
    spec = m.processes[0]
    assert spec.instances == 3
    cmd = command_for(spec, "tcp/127.0.0.1:1", m.path, instance="dmc-2")
    assert cmd[cmd.index("--instance") + 1] == "dmc-2" and cmd[cmd.index("--group") + 1] == "dmc"
    plain = load_manifest(_manifest(tmp_path, _GROUP.replace("instances = {n}\n", ""))).processes[0]
    assert plain.instances is None and "--group" not in command_for(plain, "tcp/127.0.0.1:1", m.path)


@pytest.mark.parametrize("body, needle", [
    (_GROUP.format(n=0), "instances must be a whole number from 1 to 64"),
    (_GROUP.format(n=65), "instances must be a whole number from 1 to 64"),
    (_GROUP.format(n='"3"'), "instances must be a int"),
    ('[[process]]\nname = "sim"\nmodule = "sim_publishers.car"\nvehicle = "car-1"\ninstances = 2\n', "not on a publisher"),
    (_GROUP.format(n=2) + '[[process]]\nname = "dmc-2"\nmodule = "services.dmc_detector"\n', "dmc-2 is another process"),
])
def test_instances_mistakes_are_one_paragraph(tmp_path, body, needle):
    with pytest.raises(ManifestError) as e:
        load_manifest(_manifest(tmp_path, body))
    assert needle in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_supervisor_refuses_to_scale_what_is_not_a_group(tmp_path):
    m = load_manifest(_manifest(tmp_path, _GROUP.format(n=2) + '[[process]]\nname = "ingest-1"\n'
                                'module = "services.ingest"\n'))
    sup = Supervisor(m, endpoint="tcp/127.0.0.1:1", log_dir=tmp_path / "logs", quiet=True)
    r = sup.scale("ingest-1", 2)
    assert not r["ok"] and "has no instances = N" in r["error"] and "can be scaled: dmc" in r["error"], r
    r = sup.scale("nope", 2)
    assert not r["ok"] and "is not a process of" in r["error"] and "dmc" in r["error"], r
    for bad in (0, 65, "2", True, 1.5):
        r = sup.scale("dmc", bad)
        assert not r["ok"] and "from 1 to 64" in r["error"], (bad, r)
    assert sup.children == {}  # nothing started by a refused request


@pytest.mark.parametrize("args, needle", [(["dmc", "0"], "from 1 to 64"), (["dmc", "three"], "from 1 to 64"),
                                          (["bad name", "2"], "process name")])
def test_scale_command_mistakes_are_one_paragraph(args, needle):
    r = subprocess.run([sys.executable, "-m", "magmesh", "scale", *args, "--connect", "tcp/127.0.0.1:1"],
                       cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and needle in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_group_flag_needs_a_member_name():
    from magmesh.runtime import make_parser, service_from_args
    from services.dmc_detector.service import ThresholdDmcDetector

    p = make_parser(ThresholdDmcDetector)
    with pytest.raises(SystemExit) as e:
        service_from_args(ThresholdDmcDetector, p.parse_args(["--group", "dmc"]))
    assert "--instance dmc-1" in str(e.value)
    with pytest.raises(SystemExit) as e:
        service_from_args(ThresholdDmcDetector, p.parse_args(["--group", "dmc", "--instance", "other-1"]))
    assert "must be dmc-<n>" in str(e.value)
    svc = service_from_args(ThresholdDmcDetector, p.parse_args(["--group", "dmc", "--instance", "dmc-2"]))
    assert svc.group == "dmc"
    assert service_from_args(ThresholdDmcDetector, p.parse_args(["--instance", "dmc-2"])).group is None


def test_summary_names_unowned_and_doubly_held_vehicles():
    s = groups.summarize({
        "dmc-1": {"vehicles": ["car-2", "car-1"], "releasing": [], "seen": ["car-1", "car-2", "car-3", "car-4"]},
        "dmc-2": {"vehicles": ["car-2"], "releasing": ["car-5"], "seen": ["car-5"]},
        "dmc-3": None,
    })
    assert s["vehicles"] == {"dmc-1": ["car-1", "car-2"], "dmc-2": ["car-2"], "dmc-3": None}
    assert s["unowned"] == ["car-3", "car-4"]  # car-5 is being handed over: it has its holder
    assert s["duplicates"] == ["car-2"]


class _Svc:
    role, ADOPTS_RESTORED_ALARMS = "dmc_detector", True
    instance = "dmc-1"


class _Rt:
    svc, session = _Svc(), None


def _journal(path: Path, values: dict, in_progress: tuple | None = None, sent_after: bool = False) -> None:
    j = Journal(path)
    j.open({})
    for k, v in values.items():
        j.set(k, v)
    if in_progress is not None:
        j.begin(*in_progress, n_sent=5)
        j.sent(6 if sent_after else 5)
    j.mm.flush()


def test_dead_state_takes_the_latest_of_every_dead_member(tmp_path, monkeypatch):
    from magmesh.group_member import GroupMember

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    jd, ad = tmp_path / "journal", tmp_path / "alarms"
    ad.mkdir(parents=True)
    m1, m2 = "magmesh/car-1/clean/mag/1", "magmesh/car-1/clean/mag/2"
    d, a = "magmesh/car-1/dmc", "magmesh/car-1/alarm/dmc"
    # dmc-2 held car-1 first (older seqs), dmc-3 after it; dmc-3 died while handling a mag/2 sample whose
    # output went out: that sample counts as handled
    _journal(jd / "dmc_detector.dmc-2.seq", {"i" + m1: 10, "o" + d: 9, "t" + m1: 4, "o" + "magmesh/car-9/dmc": 99})
    _journal(jd / "dmc_detector.dmc-3.seq", {"i" + m1: 50, "i" + m2: 49, "o" + d: 48, "t" + m1: 7},
             in_progress=("i" + m2, 50), sent_after=True)
    _journal(jd / "dmc_detector.dmc-1.seq", {"o" + d: 1000})  # the member itself (live): never read
    raised = {"state": "raised", "t_s": 5.0, "vehicle": "car-1"}
    (ad / "dmc_detector.dmc-2.json").write_text(json.dumps({"published": {a: "cleared"}, "raised": {},
                                                           "seqs": {a: 1}}))
    (ad / "dmc_detector.dmc-3.json").write_text(json.dumps({"published": {a: "raised"}, "raised": {a: raised},
                                                           "seqs": {a: 2}}))
    g = GroupMember(_Rt(), "dmc")
    g.live = {"dmc-1"}
    st = g._dead_state("car-1")
    assert st["found"]
    assert st["inputs"] == {m1: 50, m2: 50}
    assert st["seqs"] == {d: 48, a: 2} and st["lost"] == {m1: 7}
    assert st["alarms"] == {a: "raised"} and st["raised"] == {a: raised}
    assert not g._dead_state("car-2")["found"]
    g.live = {"dmc-1", "dmc-3"}  # dmc-3 alive again: only dmc-2's older state is someone else's to take
    st = g._dead_state("car-1")
    assert st["inputs"] == {m1: 10} and st["seqs"] == {d: 9, a: 1} and st["alarms"] == {a: "cleared"}
    assert st["raised"] == {}


def test_dead_state_counts_keys_received_but_never_handled_from_their_first_seq(tmp_path, monkeypatch):
    """A member killed with a vehicle's samples still queued (never handled) left only their first-received seq:
    the survivor counts that key's loss from there, unless another dead member handled the key."""
    from magmesh.group_member import GroupMember

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    jd = tmp_path / "journal"
    m1, m2, m3 = (f"magmesh/car-1/clean/mag/{s}" for s in (1, 2, 3))
    _journal(jd / "dmc_detector.dmc-2.seq", {"i" + m1: 20, "f" + m2: 30})
    _journal(jd / "dmc_detector.dmc-3.seq", {"f" + m1: 40, "f" + m2: 25, "f" + m3: 7, "f" + "magmesh/car-9/imu": 3})
    g = GroupMember(_Rt(), "dmc")
    g.live = {"dmc-1"}
    st = g._dead_state("car-1")
    assert st["found"] and st["inputs"] == {m1: 20, m2: 24, m3: 6}


def test_status_shows_each_members_vehicles_and_those_without_an_owner():
    from magmesh_cli.commands.status import group_assignment, render

    def member(inst, owned, seen):
        return {"role": "dmc_detector", "instance": inst, "answered": True,
                "status": {"role": "dmc_detector", "instance": inst, "impl": "threshold",
                           "vehicles": sorted(seen),  # what it has state for (warming included)
                           "group": {"name": "dmc", "vehicles": owned, "releasing": [], "seen": seen}}}

    services = [member("dmc-1", ["car-1"], ["car-1", "car-2", "car-3"]), member("dmc-2", ["car-2"], ["car-2"])]
    result = {"services": services, "bad_replies": [], "groups": group_assignment(services)}
    assert result["groups"] == {"dmc_detector/dmc": {"vehicles": {"dmc-1": ["car-1"], "dmc-2": ["car-2"]},
                                                     "unowned": ["car-3"], "duplicates": []}}
    text = render(result)
    rows = {ln.split()[1]: ln for ln in text.splitlines() if ln.startswith("dmc_detector")}
    assert "car-1" in rows["dmc-1"] and "car-2" not in rows["dmc-1"] and "car-2" in rows["dmc-2"]
    assert "group dmc_detector/dmc: 2 members, 2 vehicles held; dmc-1: car-1; dmc-2: car-2" in text
    assert "without an owner: car-3" in text


def test_cut_splits_a_vehicles_outputs_between_holder_and_new_owner():
    import threading

    from magmesh.group_member import GroupMember

    class Rt(_Rt):
        def __init__(self):
            self.last_in_t, self.lock = {"car-1": 100.0}, threading.Lock()
            self.seq, self.alarm_published, self.raised = {"magmesh/car-1/dmc": 41}, {}, {}
            self.drops = {}

    holder, new = GroupMember(Rt(), "dmc"), GroupMember(Rt(), "dmc")
    holder.owned.add("car-1")
    new.warming["car-1"] = "dmc-1"
    k = "magmesh/car-1/dmc"
    for t in (100.0, 100.6):  # outputs computed while warming: kept, published only if at or after the cut
        assert not new.gate(k, "dmc", "car-1", t, {})
    r = holder.control({"op": "g_release", "lead_s": 0.5, "vehicles": ["car-1"]})
    cut = r["releasing"]["car-1"]["cut"]
    assert r["releasing"]["car-1"]["seqs"] == {"magmesh/car-1/dmc": 41}  # what the new owner continues
    assert cut == 100.5 and holder.holds("car-1") and "car-1" not in holder.owned
    assert holder.gate(k, "dmc", "car-1", 100.4, {})  # before the cut: the holder's
    assert not holder.gate(k, "dmc", "car-1", 100.5, {}) and "car-1" in holder.passed
    new._arm("car-1", "dmc-1", cut)
    assert [h[3] for h in new.held] == [100.6] and "car-1" in new.arm and "car-1" not in new.warming
    assert not new.gate(k, "dmc", "car-1", 100.8, {}) and [h[3] for h in new.held] == [100.6, 100.8]
    # the reader threads pass every sample of a vehicle in any of these states, and drop another's
    for g in (holder, new):
        g.seen.update({"car-1", "car-2"})
        assert not g.skips("magmesh/car-1/clean/mag/1")
        assert g.skips("magmesh/car-2/clean/mag/1") and not g.skips("magmesh/car-2/cal/params/1")
        assert not g.skips("magmesh/car-3/clean/mag/1")  # never seen: the loop decides (maybe to take it)


def test_a_restarted_member_taking_back_a_vehicle_nobody_took_counts_the_gap_from_its_own_journal():
    """Killed, restarted before any survivor took its vehicle: it takes the vehicle back itself (no dead member
    left anything), and its own journal's last handled seq (resume_journal) must survive the take, so that the
    first sample after it counts the outage as lost_during_restart, not as nothing."""
    from collections import defaultdict

    from magmesh.group_member import GroupMember

    m1, m2, other = "magmesh/car-1/clean/mag/1", "magmesh/car-1/clean/mag/2", "magmesh/car-2/clean/mag/1"
    rt = _Rt()
    rt.in_seq = {m1: 100, m2: 99, other: 5}
    rt.resumed_in = {m1, m2, other}
    rt.vehicle_state, rt.first_in_t, rt.last_in_t = {}, {"car-1": 1.0}, {"car-1": 2.0}
    rt.recovering, rt.takeover_in = {}, set()
    g = GroupMember(rt, "dmc")
    nothing = {"seqs": {}, "inputs": {}, "lost": {}, "alarms": {}, "raised": {}, "found": False}
    g._failover("car-1", nothing, None)
    assert "car-1" in g.owned
    assert rt.in_seq == {m1: 100, m2: 99, other: 5} and rt.recovering == {"car-1": "lost_during_restart"}
    assert "car-1" not in rt.first_in_t, "the vehicle's times start again"
    # a dead member that handled a key later than this run did: that key's gap is the takeover's
    rt.seq, rt.drops, rt.alarm_published, rt.raised, rt.journal = {}, defaultdict(dict), {}, {}, None
    rt.alarm_adopted = 0
    rt.lock = __import__("threading").Lock()
    rt._persist_alarms = lambda: None
    g.owned.clear()
    later = dict(nothing, inputs={m1: 150, m2: 50}, found=True)
    g._failover("car-1", later, 1.0)
    assert rt.in_seq[m1] == 150 and m1 in rt.takeover_in and m1 not in rt.resumed_in
    assert rt.in_seq[m2] == 99 and m2 in rt.resumed_in and m2 not in rt.takeover_in
