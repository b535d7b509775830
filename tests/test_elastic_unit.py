"""Elastic roles without a mesh: the manifest's ``instances``, ``magmesh scale`` mistakes, the runtime's
``--group`` flag, the assignment summary, and what a member reads of a dead member's persisted state."""

from __future__ import annotations

import json
import subprocess
import sys
from collections import deque
from pathlib import Path

import pytest

from magmesh import groups
from magmesh.frames import SeqTable
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


class _Smp:
    """A received sample: its payload's bytes and its key."""

    def __init__(self, payload: bytes, key: str = ""):
        self.payload, self.b, self.key_expr = self, payload, key

    def to_bytes(self) -> bytes:
        return self.b


class _Sub:
    """A watch channel holding ``items`` (``try_recv`` as Zenoh's handlers)."""

    def __init__(self, items):
        self.items = list(items)

    def try_recv(self):
        return self.items.pop(0) if self.items else None


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
    rt.in_seq = SeqTable()  # (what the runtime keeps)
    rt.in_seq.update({m1: 100, m2: 99, other: 5})
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


def test_the_evals_offline_reference_runs_the_detector_of_the_mesh(tmp_path):
    """The elastic eval compares the mesh's alarm transitions with one DMC detector fed every epoch offline: that
    detector runs the service's own code, whose runtime calls (rows, adopted alarm states) the offline runtime
    must answer (it stopped answering them when the detector moved to the fleet core: every eval run failed)."""
    from bench.elastic_run import reference_transitions, vehicle_ids, write_manifest
    from bench.fleet import load_drive

    d = load_drive(60.0)
    v = vehicle_ids(1)[0]
    msgs = [{"type": "mag", "version": 1, "vehicle": v, "t_s": round(i * 0.02, 6), "seq": i, "sensor": s,
             "b_nt": d.mag_b_nt[s][i].tolist()} for i in range(1500) for s in ("1", "2")]  # 30 s
    man = write_manifest(tmp_path / "mesh.toml", 1, 3, "tcp/127.0.0.1:1")
    got = reference_transitions({v: msgs}, man, {v: 0.0})[v]
    assert len(got) >= 2 and [s for _, s in got[:2]] == ["raised", "cleared"], got  # the drive's bridge and trucks


def _fleet_transitions(warmup_s: float, horizon_s: float = 15.0, step_s: float = 0.37):
    """For new owners starting at many times T0 of a simulated drive (3 laps), how many decide differently from
    the holder (one detector fed from the start) in the ``horizon_s`` after a cut at T0 + ``warmup_s``: the
    service's fleet core, both from fresh state, the new owner adopting nothing."""
    import tomllib

    import numpy as np

    from bench.fleet import load_drive
    from services.dmc_detector import fleet as dfl
    from services.dmc_detector.core import CompassParams
    from services.dmc_detector.service import Settings

    d = load_drive(60.0)
    with open(REPO / "deploy" / "mesh.toml", "rb") as f:
        car = tomllib.load(f)["vehicles"]["car-1"]
    pa, pb = (CompassParams.from_mapping(car["mag_params"][s], param_id="manifest") for s in ("1", "2"))
    b1, b2 = (np.concatenate([d.mag_b_nt[s]] * 3) for s in ("1", "2"))
    t = np.arange(len(b1)) * 0.02
    starts = np.arange(1.0, t[-1] - warmup_s - horizon_s, step_s)
    det = dfl.FleetDetector(Settings(), capacity=len(starts) + 1)
    slots = []
    for _ in range(len(starts) + 1):
        s = det.add()
        det.set_params(s, pa, pb, float(car["declination_rad"]), 0.0)
        slots.append(s)
    ref, news = slots[0], slots[1:]
    # each slot's epochs in time order (the slots are independent: one block after another)
    blocks = [np.arange(len(t))] + [np.flatnonzero((t >= t0) & (t <= t0 + warmup_s + horizon_s)) for t0 in starts]
    rs = np.concatenate([np.full(len(b), s, np.int32) for s, b in zip(slots, blocks, strict=True)])
    ri_a = np.concatenate(blocks)
    out = det.step(rs, t[ri_a], b1[ri_a], b2[ri_a])

    def trans(s, lo, hi):
        m = (out.slot == s) & (out.transition != 0) & (out.t_s >= lo - 1e-9) & (out.t_s <= hi)
        return list(zip(np.round(out.t_s[m], 3).tolist(), out.transition[m].tolist(), strict=True))

    differ = sum(trans(s, t0 + warmup_s, t0 + warmup_s + horizon_s) != trans(ref, t0 + warmup_s, t0 + warmup_s +
                                                                               horizon_s)
                 for s, t0 in zip(news, starts, strict=True))
    return differ, len(starts), len(trans(ref, 0.0, t[-1]))


def test_a_new_owner_warms_long_enough_to_decide_as_the_holder_from_the_cut_on():
    """A hand-over's new owner starts from nothing when it begins warming; from the cut on it publishes what its
    own logic decides. The DMC detector's decisions depend on its feature windows (0.7 s) and its alarm latch
    (raised after 0.3 s invalid, cleared after 3 s valid): with the former 3 s warm-up some new owners cleared
    an alarm later than the holder would have (seen in the scale run: 3.6 s late). The group's warm-up, and the
    least span from a new owner's first input to the cut, must cover that, on every start time of a drive."""
    from magmesh.group_member import WARMUP_S, GroupMember

    differ, starts, n_ref = _fleet_transitions(WARMUP_S)
    assert n_ref >= 10 and starts > 300
    assert differ == 0, f"{differ} of {starts} new owners decided differently after a {WARMUP_S} s warm-up"
    assert _fleet_transitions(3.0)[0] > 0  # (the check sees the difference the former warm-up made)
    # the holder never cuts before the new owner's first input plus the warm-up, however far behind it is
    import threading

    class Rt(_Rt):
        def __init__(self):
            self.last_in_t, self.lock = {"car-1": 100.0}, threading.Lock()
            self.seq, self.alarm_published, self.raised, self.drops = {}, {}, {}, {}

    holder = GroupMember(Rt(), "dmc")
    assert holder.warmup_s == WARMUP_S
    holder.owned.add("car-1")
    r = holder.control({"op": "g_release", "lead_s": 0.5, "vehicles": ["car-1"], "from": "dmc-2",
                        "not_before": 103.0})
    assert r["releasing"]["car-1"]["cut"] == 103.0 and r["releasing"]["car-1"]["to"] == "dmc-2"


class _RoundRt(_Rt):
    """What a coordination round and the hand-over steps touch of the runtime."""

    def __init__(self):
        import threading
        from collections import defaultdict

        self.lock = threading.Lock()
        self.last_in_t, self.first_in_t = {}, {}
        self.seq, self.alarm_published, self.raised, self.drops = {}, {}, {}, defaultdict(dict)
        self.in_seq, self.resumed_in, self.takeover_in, self.recovering = SeqTable(), set(), set(), {}
        self.vehicle_state, self.journal, self.alarm_adopted = {}, None, 0
        self.reconcile_pending, self.released = {}, []

    def _persist_alarms(self):
        pass

    def _release_held(self, items):
        self.released.extend(items)
        return len(items)


def _member(name: str, members: list[str], answers: dict) -> tuple:
    """A ready member ``name`` whose rounds see ``members``' tokens and get ``answers`` to its queries; what it
    posts to its loop is collected (run with ``_run``)."""
    from magmesh.group_member import GroupMember

    class Svc(_Svc):
        instance = name

    rt = _RoundRt()
    rt.svc = Svc()
    g = GroupMember(rt, "dmc")
    g.ready, g.live, g.members = True, set(members), sorted(members)
    g._live_members = lambda: set(g._tokens_now)
    g._tokens_now = set(members)
    g._query = lambda inst, req, timeout=1.0: answers.get(inst, {}).get(req["op"])
    posted: list = []
    g._post = posted.append
    g._call = lambda fn, timeout=5.0: fn()
    return g, rt, posted


def _run(posted: list) -> None:
    while posted:
        posted.pop(0)()


def _dmc1_beside_dmc2(n: int) -> tuple:
    """dmc-1 in a group with dmc-2, which answers holding its share of ``n`` cars by the rule; dmc-1 holds the rest.
    Returns (member, runtime, posted, cars, dmc-2's cars, answers)."""
    from magmesh import groups

    cars = [f"car-{i}" for i in range(n)]
    theirs = sorted(v for v in cars if groups.owner(v, ["dmc-1", "dmc-2"]) == "dmc-2")
    answers = {"dmc-2": {"g_state": {"ok": True, "owned": theirs, "releasing": {}, "taking": []}}}
    g, rt, posted = _member("dmc-1", ["dmc-1", "dmc-2"], answers)
    g.seen.update(cars)
    g.owned.update(v for v in cars if v not in theirs)
    return g, rt, posted, cars, theirs, answers


def test_a_member_whose_liveliness_token_lapsed_but_answers_stays_a_member(tmp_path, monkeypatch):
    """Seen in the 30-car kill run: a member's token went for a while (its session under load) although it kept
    serving; another member took all its vehicles as a dead member's, and both published them for 6 s (2,463 dmc
    outputs repeated, 24 alarm transitions repeated). A member is gone only when it does not answer either."""
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    g, rt, posted, cars, theirs, answers = _dmc1_beside_dmc2(20)
    g._tokens_now = {"dmc-1"}  # dmc-2's token went
    g._round()
    assert "dmc-2" in g.live and g.stats["liveliness_lapses"] == 1
    _run(posted)
    assert not (set(theirs) & g.owned), "a member that answers was taken for dead"
    answers.clear()  # now it does not answer either: gone, its vehicles taken once their input reaches dmc-1
    g.heard_t.clear()
    g._round()
    _run(posted)
    assert "dmc-2" not in g.live and not (set(theirs) & g.owned), "taken before any of its input came"
    for v in theirs[1:]:
        assert g.skips(f"magmesh/{v}/clean/mag/1")
    g._round()
    _run(posted)
    assert set(theirs[1:]) <= g.owned and theirs[0] not in g.owned and g.stats["unrecovered"] == len(theirs) - 1


def test_a_hand_over_to_a_member_that_went_before_taking_the_vehicle_is_taken_back(tmp_path, monkeypatch):
    """The holder published a vehicle until the cut and then nothing; the new owner was killed (or restarted)
    before taking it: the vehicle stayed with nobody. The holder keeps its outputs from the cut on until the new
    owner confirms, and takes the vehicle back (with those outputs) when the new owner goes without having
    published any; a second member asking for a vehicle already promised gets nothing."""
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    answers = {"dmc-2": {"g_state": {"ok": True, "owned": [], "releasing": {}, "taking": ["car-1"]}}}
    g, rt, posted = _member("dmc-1", ["dmc-1", "dmc-2"], answers)
    rt.last_in_t["car-1"], rt.seq["magmesh/car-1/dmc"] = 100.0, 41
    g.owned.add("car-1")
    g.seen.add("car-1")
    r = g.control({"op": "g_release", "lead_s": 0.5, "vehicles": ["car-1"], "from": "dmc-2"})
    cut = r["releasing"]["car-1"]["cut"]
    r3 = g.control({"op": "g_release", "lead_s": 0.5, "vehicles": ["car-1"], "from": "dmc-3"})
    assert r3["releasing"]["car-1"]["to"] == "dmc-2"  # (dmc-3 arms only on a release to itself)
    k = "magmesh/car-1/dmc"
    assert g.gate(k, "dmc", "car-1", cut - 0.1, {"n": 1}) and g.holds("car-1")
    assert not g.gate(k, "dmc", "car-1", cut, {"n": 2}) and not g.gate(k, "dmc", "car-1", cut + 0.1, {"n": 3})
    # past the cut the new owner's alarm transitions count: the holder no longer answers alarm queries for it
    assert not g.holds("car-1")
    assert not g.admits("magmesh/car-1/clean/mag/1")  # past the cut: its journal says what it published or kept
    g._round()  # dmc-2 still takes it
    _run(posted)
    assert "car-1" in g.release and not rt.released
    answers["dmc-2"]["g_state"]["taking"] = []  # restarted: it does not take car-1 any more
    g._round()
    _run(posted)
    assert "car-1" in g.owned and "car-1" not in g.release and g.stats["reclaimed"] == 1
    assert [x[4]["n"] for x in rt.released] == [2, 3], "the outputs from the cut on are published by the holder"
    assert g.gate(k, "dmc", "car-1", cut + 0.2, {})


def test_the_owner_taking_a_new_vehicle_holds_it_before_it_is_seen(tmp_path, monkeypatch):
    """Seen at the start of a run: the first sample of a new vehicle made its owner take it, but the vehicle was
    marked seen before it was held, and a reader thread looking at that instant dropped the second sample as
    another member's (one epoch missing, an input gap). The vehicle is held before it is seen."""
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    g, rt, posted = _member("dmc-1", ["dmc-1"], {})
    g.complete = True
    missed = []

    class Seen(set):
        def add(self, v):  # a reader thread checks the vehicle's next sample right after this
            set.add(self, v)
            missed.append(g.skips(f"magmesh/{v}/clean/mag/1"))

    g.seen = Seen()
    assert g.admits("magmesh/car-1/clean/mag/1")
    assert missed == [False] and "car-1" in g.owned


def test_counts_that_move_with_a_handed_over_vehicle_leave_the_holders_journal(tmp_path):
    """A holder's drop counts of a vehicle go to the new owner with the hand-over; they must also leave the
    holder's journal, or a restart of the holder brings them back and they are counted twice."""
    from magmesh.journal import Journal

    g, rt, posted = _member("dmc-1", ["dmc-1", "dmc-2"], {})
    j = Journal(tmp_path / "j.seq")
    j.open({})
    rt.journal = j
    m1, other = "magmesh/car-1/clean/mag/1", "magmesh/car-2/clean/mag/1"
    rt.drops[m1], rt.drops[other] = {"upstream_gap": 3, "lost_in_takeover": 2}, {"upstream_gap": 1}
    for c, n in (("u", 3), ("t", 2), ("i", 50)):
        j.set(c + m1, n)
    j.set("u" + other, 1)
    rt.last_in_t["car-1"] = 10.0
    g.owned.add("car-1")
    hand = g.control({"op": "g_release", "vehicles": ["car-1"], "from": "dmc-2"})["releasing"]["car-1"]
    assert hand["drops"][m1] == {"upstream_gap": 3, "lost_in_takeover": 2}  # what the new owner adds to its own
    g.control({"op": "g_done", "vehicles": ["car-1"]})
    left = Journal(tmp_path / "j.seq").load()
    assert "u" + m1 not in left and "t" + m1 not in left and left["u" + other] == 1 and left["i" + m1] == 50
    assert m1 not in rt.drops and rt.drops[other] == {"upstream_gap": 1}


def test_a_vehicles_counts_survive_a_kill_of_the_member_that_took_them_and_are_counted_once(tmp_path,
                                                                                          monkeypatch):
    """A vehicle's drop counts carried in by a hand-over are journalled (a kill of the new owner then keeps
    them); the survivor taking the vehicle over from the dead member's journal takes them with it; and the dead
    member, restarted, forgets what its journal restored of them once it warms on the vehicle again (the
    hand-over brings them back): every count once. (Seen before: an upstream gap of 53 samples carried into a
    member by a hand-over was lost with that member's kill -9.)"""
    from magmesh.journal import Journal

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    m1 = "magmesh/car-1/clean/mag/1"
    g, rt, posted = _member("dmc-1", ["dmc-1", "dmc-2"], {})
    jpath = tmp_path / "journal" / "dmc_detector.dmc-1.seq"
    jpath.parent.mkdir(parents=True)
    rt.journal = Journal(jpath)
    rt.journal.open({})
    g.warming["car-1"] = "dmc-2"
    g._arm("car-1", "dmc-2", 10.0)
    g._takeover("car-1", {"seqs": {"magmesh/car-1/dmc": 40}, "drops": {
        m1: {"upstream_gap": 53, "lost_during_restart": 2, "lost_in_takeover": 6, "unpaired": 1}}})
    rt.journal.mm.flush()
    left = Journal(jpath).load()
    assert (left["u" + m1], left["l" + m1], left["t" + m1]) == (53, 2, 6)  # journalled as they came

    # dmc-1 killed: dmc-2 takes car-1 over from its journal, counts included
    g2, rt2, _ = _member("dmc-2", ["dmc-2"], {})
    g2.live = {"dmc-2"}
    dead = g2._dead_state("car-1")
    assert dead["counts"] == {m1: {"upstream_gap": 53, "lost_during_restart": 2}} and dead["lost"] == {m1: 6}
    g2._failover("car-1", dead, None)
    assert rt2.drops[m1] == {"upstream_gap": 53, "lost_during_restart": 2, "lost_in_takeover": 6}

    # dmc-1 restarted: its journal restores the counts; warming on car-1 again, it forgets them (the hand-over
    # from dmc-2 carries them)
    g3, rt3, _ = _member("dmc-1", ["dmc-1", "dmc-2"], {})
    rt3.journal = Journal(jpath)
    rt3.journal.open({k: v for k, v in Journal(jpath).load().items() if not k.startswith("~")})
    rt3.drops[m1] = {"upstream_gap": 53, "lost_during_restart": 2, "lost_in_takeover": 6}
    g3._begin_warm("car-1", "dmc-2")
    assert m1 not in rt3.drops
    rt3.journal.mm.flush()
    assert not any(k[1:] == m1 for k in Journal(jpath).load() if k[:1] in "ult")
    g3._arm("car-1", "dmc-2", 20.0)
    g3._takeover("car-1", {"drops": {m1: dict(rt2.drops[m1])}})
    assert rt3.drops[m1] == {"upstream_gap": 53, "lost_during_restart": 2, "lost_in_takeover": 6}


def test_a_dead_members_last_alarm_transition_the_mesh_never_showed_is_published_again(tmp_path, monkeypatch):
    """A kill -9 after an alarm transition was written to the member's alarm file but before its put left the
    process lost it for every subscriber (seen once in ten kills of 30 cars: a clear never received, then "raised"
    twice). The survivor taking the vehicle over publishes it again, seq and all, when its own watch of the alarm
    keys never showed it; a transition it saw, or one written before it watched, is not sent again."""
    import time
    from collections import defaultdict

    from magmesh.alarmstore import AlarmStore
    from schemas import messages

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    a = "magmesh/car-1/alarm/dmc"
    fields = dict(source="dmc", severity="warning", value=None, threshold=None, service="dmc-2")
    raised = messages.make("alarm", "car-1", 10.0, 10, state="raised", reason="Magnetic interference suspected.",
                           **fields)
    cleared = messages.make("alarm", "car-1", 13.0, 11, state="cleared", reason="Trustworthy again.", **fields)
    store = AlarmStore(tmp_path / "alarms" / "dmc_detector.dmc-2.json")
    store.record(a, "raised", 10, raised)
    store.record(a, "cleared", 11, cleared)  # written; its put never left dmc-2

    def survivor(seen: int, watched_from: float) -> tuple:
        g, rt, _ = _member("dmc-1", ["dmc-1"], {})
        puts = []
        rt._publisher = lambda k: type("P", (), {"put": lambda _s, p: puts.append((k, messages.decode(p)))})()
        rt.count_out = defaultdict(lambda: type("C", (), {"n": 0})())
        g.seen_alarm[a] = (seen, raised if seen == 10 else cleared)
        g._alarm_watch_t = (watched_from, time.time())
        g._failover("car-1", g._dead_state("car-1"), time.monotonic())
        return g, rt, puts

    g, rt, puts = survivor(10, time.time() - 60)  # watched for a minute, saw only the raise
    assert [(k, m["seq"], m["state"], m["service"]) for k, m in puts] == [(a, 11, "cleared", "dmc-2")]
    assert g.stats["alarms_sent_again"] == 1 and rt.count_out[a].n == 1
    assert rt.alarm_published[a] == "cleared" and rt.seq[a] == 11  # (its own next transition is seq 12)
    assert survivor(11, time.time() - 60)[2] == []  # it saw the clear: not sent twice
    assert survivor(10, time.time())[2] == []  # watching only since after the write: it cannot tell


def test_a_holder_killed_past_the_cut_hands_the_vehicle_over_from_its_journal(tmp_path, monkeypatch):
    """A holder that passed the cut of a hand-over published every output before it and none from it on, and
    journalled that; killed there, the new owner (armed, holding its outputs from the cut on) completes the
    hand-over from the journal: it publishes what it held, continuing the holder's seqs, and counts nothing lost
    (it used to discard them and count them lost, and the holder's one output at the cut went uncounted). A holder
    killed before the cut leaves no such mark: the new owner takes the vehicle over as from any dead member."""
    from magmesh.journal import Journal

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    m1, out = "magmesh/car-1/clean/mag/1", "magmesh/car-1/dmc"
    jd = tmp_path / "journal"
    jd.mkdir()
    h, hrt, _ = _member("dmc-2", ["dmc-1", "dmc-2"], {})
    hrt.journal = Journal(jd / "dmc_detector.dmc-2.seq")
    hrt.journal.open({"o" + out: 40, "i" + m1: 80})
    h.owned.add("car-1")
    hrt.last_in_t["car-1"] = 9.5
    h.control({"op": "g_release", "vehicles": ["car-1"], "from": "dmc-1", "not_before": 10.0})
    assert h.release["car-1"] == 10.0
    assert h.gate(out, "dmc", "car-1", 9.98, {}) and not h.gate(out, "dmc", "car-1", 10.0, {})  # passed here
    assert Journal(jd / "dmc_detector.dmc-2.seq").load()["pmagmesh/car-1/"] == 1

    n, nrt, _ = _member("dmc-1", ["dmc-1"], {})
    n.warming["car-1"] = "dmc-2"
    n.warm_buf["car-1"] = deque([(out, "dmc", "car-1", t, {}) for t in (9.98, 10.0, 10.02)])
    n._arm("car-1", "dmc-2", 10.0)
    n.live = {"dmc-1"}  # dmc-2 killed
    n._failover("car-1", n._dead_state("car-1"), 0.0)
    assert [x[3] for x in nrt.released] == [10.0, 10.02] and "car-1" in n.owned and not n.arm
    assert nrt.seq[out] == 40 and m1 not in nrt.takeover_in and not nrt.drops.get(m1)
    assert n.stats["failovers"] == 1

    # the same, killed before the cut: no mark, the outputs it held are not published, its inputs' gap is counted
    h._set_passed("car-1", False)
    assert "pmagmesh/car-1/" not in Journal(jd / "dmc_detector.dmc-2.seq").load()
    n2, nrt2, _ = _member("dmc-1", ["dmc-1"], {})
    n2.warming["car-1"] = "dmc-2"
    n2.warm_buf["car-1"] = deque([(out, "dmc", "car-1", 10.0, {})])
    n2._arm("car-1", "dmc-2", 10.0)
    n2.live = {"dmc-1"}
    n2._failover("car-1", n2._dead_state("car-1"), 0.0)
    assert not nrt2.released and nrt2.in_seq[m1] == 80 and m1 in nrt2.takeover_in


def test_a_frames_vehicles_are_admitted_as_one_by_one(tmp_path, monkeypatch):
    """The runtime cuts each fleet frame to the vehicles a member handles with one mask (GroupMember.admitted, a
    set lookup per vehicle): the same answer as admits() vehicle by vehicle, in every state a vehicle can be in,
    a new vehicle taken by its owner at once, and the same not-owned count."""
    from magmesh import groups

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))  # (a vehicle taken reads what dead members left)
    cars = [f"car-{i}" for i in range(40)]
    mine = [v for v in cars if groups.owner(v, ["dmc-1", "dmc-2"]) == "dmc-1"]

    def setup():
        g, rt, posted = _member("dmc-1", ["dmc-1", "dmc-2"], {})
        g.complete = True
        g.seen.update(cars[:30])  # car-30.. are new
        g.holdings = {v: "dmc-2" for v in cars[:30] if v not in mine}
        g.owned.update(mine[:3])
        g.warming[cars[3]] = "dmc-2"
        g.arm[cars[4]] = ("dmc-2", 5.0, 0.0)
        g.release.update({cars[5]: 1.0, cars[6]: 1.0})
        g.passed.add(cars[6])
        return g

    def key(v):
        return f"magmesh/{v}/clean/mag/1"

    a, b = setup(), setup()
    one_by_one = [a.admits(key(v)) for v in cars]
    mask = b.admitted(cars, key)
    assert mask.tolist() == one_by_one
    assert any(one_by_one[30:]) and not all(one_by_one[30:])  # new vehicles: the owner's taken at once
    assert a.owned == b.owned and a.seen == b.seen and a.stats["not_owned"] == b.stats["not_owned"]
    # the same list again: the same answer (kept), counted the same; any change of the holdings makes it anew
    not_owned = b.stats["not_owned"]
    assert b.admitted(cars, key) is mask
    assert b.stats["not_owned"] == 2 * not_owned  # (each frame counts the vehicles not held here)
    for change in (lambda g: g.owned.discard(mine[0]), lambda g: g.warming.pop(cars[3]),
                   lambda g: g.arm.__setitem__(cars[7], ("dmc-2", 5.0, 0.0)), lambda g: g.passed.discard(cars[6]),
                   lambda g: g.release.__delitem__(cars[5]), lambda g: g.owned.update([cars[8]])):
        change(a)
        change(b)
        again = b.admitted(cars, key)
        assert again is not mask and again.tolist() == [a.admits(key(v)) for v in cars]
        mask = again
    # heard per vehicle list: a vehicle of a list heard is heard then, one of no list is not
    import time as _time

    t0 = _time.monotonic()
    b.admitted(cars, key)
    assert b._heard_at(cars[20]) >= t0 and b._heard_at("car-999") is None


def test_a_new_vehicle_is_taken_at_once_by_its_owner_even_after_an_incomplete_round(tmp_path, monkeypatch):
    """A vehicle nobody holds, seen for the first time: its owner by the rule takes it at once. It used to wait
    for a round in which every member answered: under load a round is often incomplete, and every member then
    dropped the vehicle's first samples (not counted anywhere: no member held it)."""
    from magmesh import groups

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    g, rt, posted = _member("dmc-1", ["dmc-1", "dmc-2"], {})
    g.complete = False  # the last round missed dmc-2's answer
    cars = [f"car-{i}" for i in range(10)]
    took = [g.admits(f"magmesh/{v}/clean/mag/1") for v in cars]
    assert took == [groups.owner(v, ["dmc-1", "dmc-2"]) == "dmc-1" for v in cars] and any(took)
    held_elsewhere = next(v for v in (f"car-{i}" for i in range(100, 200)) if groups.owner(v, g.members) == "dmc-1")
    g.holdings[held_elsewhere] = "dmc-2"  # held by another member in the last complete round: never taken here
    assert not g.admits(f"magmesh/{held_elsewhere}/clean/mag/1") and held_elsewhere not in g.owned


def test_bench_runs_do_not_share_a_state_directory(tmp_path, monkeypatch):
    """bench mesh --instances: a group member stopped while holding vehicles keeps its seq journal (for the member
    taking them); the next run's member of the same name resumed it and counted the seqs the last run's ingest had
    numbered beyond what it handled as upstream gaps (10-60 per run, with every output delivered). Each run has its
    own state directory."""
    import subprocess as sp

    from bench import mesh_bench

    seen = []
    monkeypatch.setattr(sp, "Popen", lambda *a, **k: seen.append(k["env"]["MAGMESH_STATE_DIR"]))
    for port in (7001, 7002):
        mesh_bench._spawn(["-m", "services.ingest"], port, tmp_path / "ingest.log")
    assert len(set(seen)) == 2 and all(s.startswith(str(tmp_path)) for s in seen), seen


def test_a_dead_member_whose_journal_is_elsewhere_is_taken_from_what_the_mesh_showed(tmp_path, monkeypatch):
    """No journal of the dead member here (it ran on another host): its outputs' last seqs and times come from its
    fleet frames, its alarm from the alarm key, its input seqs and counts from its last answer, and what it handled
    after that answer from each key's rate up to its last output's time."""
    import numpy as np

    from magmesh.group_member import GroupMember
    from schemas import frame

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    m1, m2, d, a = ("magmesh/car-1/clean/mag/1", "magmesh/car-1/clean/mag/2", "magmesh/car-1/dmc",
                    "magmesh/car-1/alarm/dmc")
    g = GroupMember(_Rt(), "dmc")
    g.live = {"dmc-1"}
    g.last_holder["car-1"] = "dmc-2"
    # two answers 0.4 s of sample time apart: 50 Hz on each compass; the last one at t = 10.0 (mag/1: seq 500)
    for t, s in ((9.6, 480), (10.0, 500)):
        g._note_answers({"dmc-2": {"held": {"car-1": {"t": t, "in": {m1: [s, t], m2: [s - 1, t - 0.02]},
                                                      "drops": {m1: {"upstream_gap": 3, "lost_in_takeover": 2}}}}}})
    # then its fleet frames: outputs up to t = 10.3 (seq 515), from another shard (its own frames are skipped)
    def dmc_frame(shard, seq, t):
        one = np.array([0.0])
        st = frame.Stream("dmc", "dmc", np.array([0], np.uint32), np.array([t]), np.array([seq], np.int64),
                          {"dm_nt": np.zeros((1, 2)), "ddm_nt_s": np.zeros((1, 2)), "dh_rad": one, "ddh_rad_s": one,
                           "heading_rad": one, "stage1_pass": np.array([True]), "credibility": one + 1.0,
                           "valid": np.array([True]), "impl": "threshold", "param_source": "manifest"})
        return frame.encode(shard, "dmc", 0, ["car-1"], {"dmc": st})

    g._out_sub = _Sub([_Smp(dmc_frame("dmc-2", 514, 10.28)), _Smp(dmc_frame("dmc-2", 515, 10.3)),
                       _Smp(dmc_frame("dmc-1", 900, 99.0))])
    from schemas import messages

    alarm = messages.make("alarm", "car-1", 10.1, 3, source="dmc", state="raised", severity="warning",
                          reason="Magnetic interference suspected.", value=None, threshold=None, service="dmc-2")
    g._alarm_sub = _Sub([_Smp(messages.encode(alarm), a)])
    g._observe()
    st = g._dead_state("car-1")
    assert st["found"] and st["mesh"] and st["t_out"] == pytest.approx(10.3)
    assert st["seqs"] == {d: 515, a: 3} and st["alarms"] == {a: "raised"} and st["raised"][a]["seq"] == 3
    # 0.3 s at 50 Hz after each compass's last answered sample: 15 more handled on mag/1, 16 on mag/2
    assert st["inputs"] == {m1: 515, m2: 515}
    assert st["counts"] == {m1: {"upstream_gap": 3}} and st["lost"] == {m1: 2}
    g.last_holder["car-1"] = "dmc-9"  # a holder never heard from: what the frames showed, no input estimate
    st = g._dead_state("car-2")
    assert not st["found"]


def test_a_take_over_from_the_mesh_reads_the_holders_last_input_from_the_samples_heard(tmp_path, monkeypatch):
    """What a dead holder handled after its last answer: the seq of its input at its last output's sample time, read
    from the samples of that key this member heard and skipped. Sample times come from a real clock, so the key's
    rate is one sample off here (the 30-car eval counted one epoch too many on 7 of 10 cars of a member killed
    three times); samples that do not reach back that far leave the rate's estimate."""
    import msgpack

    from magmesh.group_member import GroupMember

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    m1 = "magmesh/car-1/clean/mag/1"

    class _Payload:
        def __init__(self, b):
            self.b = b

        def to_bytes(self):
            return self.b

    def member(first_heard: int) -> GroupMember:
        g = GroupMember(_Rt(), "dmc")
        g.live = {"dmc-1"}
        g.last_holder["car-1"] = "dmc-2"
        g.seen.add("car-1")
        for t, s in ((9.6, 480), (10.0, 500)):  # its answers: 50 Hz
            g._note_answers({"dmc-2": {"held": {"car-1": {"t": t, "in": {m1: [s, t]}}}}})
        g.seen_out["car-1"] = {"magmesh/car-1/dmc": (515, 10.3)}  # its last output: sample time 10.3
        for s in range(first_heard, 540):  # this clock ran 7 % fast: sample 516 is stamped 10.2992
            p = msgpack.packb({"type": "mag", "vehicle": "car-1", "seq": s, "t_s": 10.0 + (s - 500) * 0.0187})
            assert g.skips(m1, _Payload(p))
        g.skips(m1, _Payload(b"\xc1 not msgpack"))  # (garbage heard is passed over)
        return g

    assert member(505)._dead_state("car-1")["inputs"] == {m1: 516}
    g = member(300)
    assert len(g.heard_buf[m1]) == 128  # (the last HEARD_KEEP of a key only)
    # a batch skipped is heard (the vehicle's input came) but not kept: its seq is never read back
    assert g.skips("magmesh/car-1/raw/batch", _Payload(b"\x00" * 64)) and "magmesh/car-1/raw/batch" not in g.heard_buf
    # heard only from sample 520 (10.374) on: the rate's estimate, 0.3 s at 50 Hz after the answer
    assert member(520)._dead_state("car-1")["inputs"] == {m1: 515}


def test_a_member_cut_off_from_the_vehicles_takes_none_of_a_gone_members_vehicles(tmp_path, monkeypatch):
    """A link outage between hosts: each side sees the other go. The side that still hears the vehicles takes the
    other's; the side cut off (it heard its last input a lease before it saw the other go) takes none (before, it took
    them all and, on the link's return, published them from a state seconds old)."""
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    g, rt, posted, cars, theirs, answers = _dmc1_beside_dmc2(12)
    g._round()
    _run(posted)
    for v in theirs:  # its input last heard before the link went down
        assert g.skips(f"magmesh/{v}/clean/mag/1")
        g.heard_t[v] -= 5.0  # (more than HEARD_MARGIN_S before it saw dmc-2 go)
    answers.clear()
    g._tokens_now = {"dmc-1"}
    g._round()
    _run(posted)
    assert g.cut_off_since is None, "a round without the vehicles' input is normal right after their holder went"
    g._dead_since["dmc-2"] -= 2.0  # gone 2 s ago, its vehicles still not heard (last heard 5 s ago)
    for _ in range(2):
        g._round()
        _run(posted)
    assert not (set(theirs) & g.owned) and g.stats["failovers"] == 0, "took vehicles it does not hear"
    assert g.cut_off_since is not None, "the pause rule applies while it may be the member cut off"
    assert g.skips(f"magmesh/{theirs[0]}/clean/mag/1")  # one of them heard again: taken
    g._round()
    _run(posted)
    assert set(theirs) & g.owned == {theirs[0]}


def test_of_two_holders_the_one_whose_outputs_went_further_keeps_the_vehicle(tmp_path, monkeypatch):
    """After a split both members hold a vehicle. The one behind (its outputs' seqs below what the other published,
    seen in the other's frames) drops it whatever the rule prefers; the one ahead keeps it; with nothing to tell
    them apart the rule decides, as before."""
    from magmesh import groups

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    cars = [f"car-{i}" for i in range(12)]
    mine = sorted(v for v in cars if groups.owner(v, ["dmc-1", "dmc-2"]) == "dmc-1")
    theirs = sorted(v for v in cars if v not in mine)
    v_mine, v_theirs, v_tie = mine[0], theirs[0], theirs[1]
    answers = {"dmc-2": {"g_state": {"ok": True, "owned": [v_mine, v_theirs, v_tie], "releasing": {}, "taking": []}}}
    g, rt, posted = _member("dmc-1", ["dmc-1", "dmc-2"], answers)
    g.seen.update(cars)
    g.owned.update([v_mine, v_theirs, v_tie])
    k = {v: f"magmesh/{v}/dmc" for v in cars}
    rt.seq.update({k[v_mine]: 40, k[v_theirs]: 90, k[v_tie]: 10})
    g.seen_out.update({v_mine: {k[v_mine]: (95, 9.5)}, v_theirs: {k[v_theirs]: (60, 6.0)}})
    g._round()
    _run(posted)
    assert v_mine not in g.owned, "behind: dropped although the rule gives it to this member"
    assert v_theirs in g.owned, "ahead: kept although the rule gives it to the other"
    assert v_tie not in g.owned, "nothing to tell: the rule decides"
    assert g.stats["duplicates_behind"] == 1 and g.stats["duplicates_dropped"] == 2


def test_outputs_after_a_pause_are_held_until_a_round_shows_who_holds_the_vehicle(tmp_path, monkeypatch):
    """A held vehicle whose outputs stopped for longer than PAUSE_S (its input cut off by a link outage) has its
    next outputs held: published after two complete rounds when no other member holds it, dropped (counted
    suppressed) when another member holds it with outputs ahead."""
    from magmesh import group_member

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    answers = {"dmc-2": {"g_state": {"ok": True, "owned": [], "releasing": {}, "taking": []}}}
    g, rt, posted = _member("dmc-1", ["dmc-1", "dmc-2"], answers)
    g.seen.update(["car-1", "car-2"])
    g.owned.update(["car-1", "car-2"])
    g.last_out["car-1"] = 0.0
    assert g.plain("car-1"), "no pause held while this member hears the vehicles of every member seen gone"
    g.cut_off_since = 0.0  # it saw a member go and does not hear that member's vehicles (see _round)
    for v in ("car-1", "car-2"):
        assert g.gate(f"magmesh/{v}/dmc", "dmc", v, 1.0, {}) and g.plain(v)
        g.last_out[v] -= group_member.PAUSE_S + 0.1  # no output for longer than a pause
    assert not g.plain("car-1") and not g.gate("magmesh/car-1/dmc", "dmc", "car-1", 5.0, {"a": 1})
    assert not g.gate("magmesh/car-2/dmc", "dmc", "car-2", 5.0, {"a": 2})
    assert not g.gate("magmesh/car-2/dmc", "dmc", "car-2", 5.02, {"a": 3})
    assert g.stats["held_after_pause"] == 2 and rt.released == []
    # car-2: the other member holds it and went further meanwhile
    answers["dmc-2"]["g_state"]["owned"] = ["car-2"]
    g.seen_out["car-2"] = {"magmesh/car-2/dmc": (500, 9.0)}
    g._round()
    _run(posted)
    assert "car-2" not in g.owned and "car-2" not in g.pause_buf and rt.released == []
    g._round()
    _run(posted)
    assert [x[3] for x in rt.released] == [5.0], "car-1 released once two rounds showed nobody else holds it"
    assert g.gate("magmesh/car-1/dmc", "dmc", "car-1", 5.04, {}) and g.plain("car-1")


def test_the_output_watch_learns_each_vehicles_last_output_and_passes_over_names_no_key_carries():
    """``_observe`` reads the other members' output frames (their headers): per vehicle and key the newest seq and
    sample time. A frame naming a vehicle no key may carry (a put on the fleet key by anyone) costs that row only,
    not the round (before, it raised out of the round)."""
    import msgpack
    import numpy as np

    from magmesh.group_member import GroupMember

    def payload(shard, vehicles, rows):  # rows: (vehicle index, seq, t_s), sorted by vehicle
        vi, sq, ts = (np.array([r[i] for r in rows], dt) for i, dt in ((0, "<u4"), (1, "<i8"), (2, "<f8")))
        return msgpack.packb({"type": "frame", "version": 3, "shard": shard, "kind": "dmc", "t_s": 1.0, "seq": 0,
                              "vehicles": vehicles, "streams": {"dmc": {"n": len(rows), "vi": vi.tobytes(),
                                                                         "t_s": ts.tobytes(), "seq": sq.tobytes(),
                                                                         "cols": {}}}})

    g = GroupMember(_Rt(), "dmc")
    g._out_sub = _Sub([_Smp(payload("dmc-2", ["car-1", "bad/name", "car-2"], [(0, 7, 0.7), (0, 8, 0.8),
                                                                                  (1, 3, 0.3), (2, 5, 0.5)])),
                       _Smp(payload("dmc-2", ["car-1"], [(0, 6, 0.6)])),  # (older: not taken)
                       _Smp(payload("dmc-1", ["car-3"], [(0, 1, 0.1)])),  # (its own)
                       _Smp(b"\xc1")])
    g._observe()
    assert g.seen_out == {"car-1": {"magmesh/car-1/dmc": (8, 0.8)}, "car-2": {"magmesh/car-2/dmc": (5, 0.5)}}
    # a round's frames of one list are read newest first: each vehicle's row from the newest frame that has one
    two = ["car-1", "car-2"]
    g._out_sub = _Sub([_Smp(payload("dmc-2", two, [(0, 10, 1.0), (1, 6, 0.6)])),
                       _Smp(payload("dmc-2", two, [(0, 11, 1.1)])),
                       _Smp(payload("dmc-2", two, [(1, 7, 0.7)]))])
    g._observe()
    assert g.seen_out == {"car-1": {"magmesh/car-1/dmc": (11, 1.1)}, "car-2": {"magmesh/car-2/dmc": (7, 0.7)}}


def test_rounds_ask_for_the_held_tables_once_a_held_period_and_a_member_answers_without_one_when_not_asked(
        tmp_path, monkeypatch):
    """The held table (every input key's seq of every vehicle a member holds) is the part of an answer that grows
    with the fleet: a round asks for it only once per HELD_PERIOD_S (and from a member it has none of), the other
    rounds ask for membership and hand-overs alone; a g_state not asking for it is answered without it."""
    from magmesh import group_member as gm

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    answers = {"dmc-2": {"g_state": {"ok": True, "owned": [], "releasing": {}, "taking": [],
                                     "held": {"car-9": {"t": 1.0, "in": {}, "drops": {}}}}}}
    g, rt, posted = _member("dmc-1", ["dmc-1", "dmc-2"], answers)
    asked: list[bool] = []
    query = g._query

    def spy(inst, req, timeout=1.0):
        asked.append(bool(req.get("held", True)))
        return query(inst, req, timeout)

    g._query = spy
    clock = {"t": 1000.0}
    monkeypatch.setattr(gm.time, "monotonic", lambda: clock["t"])
    for _ in range(11):  # 2 s of rounds, 0.2 s apart
        g._round()
        _run(posted)
        clock["t"] += 0.2
    assert asked == [True, False, False, False, False, True, False, False, False, False, True]
    g.owned.add("car-1")
    assert "held" not in g.control({"op": "g_state", "held": False})
    assert "held" in g.control({"op": "g_state", "held": True})
    assert "held" in g.control({"op": "g_state"})  # a member that does not say gets it (as before)


def test_the_output_watch_passes_over_frames_of_members_whose_journal_is_on_this_host(tmp_path, monkeypatch):
    """A failover from a member whose seq journal is on this host reads the journal (every output is written there
    before it is put): that member's frames, and this member's own, are passed over from their shard alone; a
    member on another host (no journal here) is watched."""
    import numpy as np

    from magmesh.group_member import GroupMember
    from schemas import frame

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    (tmp_path / "journal").mkdir()
    (tmp_path / "journal" / "dmc_detector.dmc-2.seq").write_bytes(b"")

    def dmc_frame(shard, vehicle, seq, t):
        one = np.array([0.0])
        st = frame.Stream("dmc", "dmc", np.array([0], np.uint32), np.array([t]), np.array([seq], np.int64),
                          {"dm_nt": np.zeros((1, 2)), "ddm_nt_s": np.zeros((1, 2)), "dh_rad": one, "ddh_rad_s": one,
                           "heading_rad": one, "stage1_pass": np.array([True]), "credibility": one + 1.0,
                           "valid": np.array([True]), "impl": "threshold", "param_source": "manifest"})
        return frame.encode(shard, "dmc", 0, [vehicle], {"dmc": st})

    g = GroupMember(_Rt(), "dmc")
    assert g.role == "dmc_detector" and frame.shard_of(dmc_frame("dmc-3", "car-3", 1, 1.0)) == "dmc-3"
    g._out_sub = _Sub([_Smp(dmc_frame("dmc-2", "car-2", 7, 1.0)), _Smp(dmc_frame("dmc-3", "car-3", 8, 1.0)),
                       _Smp(dmc_frame(g.me, "car-1", 9, 1.0))])
    g._observe()
    assert set(g.seen_out) == {"car-3"} and g.seen_out["car-3"] == {"magmesh/car-3/dmc": (8, 1.0)}


def test_plain_many_says_what_plain_says_vehicle_by_vehicle(tmp_path, monkeypatch):
    """A frame's vehicles judged at once (the held-and-no-hand-over set kept until the holdings change) give what
    plain() gives one by one, in every state, before and after a change, and with outputs held after a pause."""
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    cars = [f"car-{i}" for i in range(12)]

    def setup():
        g, rt, posted = _member("dmc-1", ["dmc-1", "dmc-2"], {})
        g.owned.update(cars[:9])
        g.post_cut[cars[1]] = 5.0
        g.release[cars[2]] = 5.0
        g.arm[cars[3]] = ("dmc-2", 5.0, 0.0)
        g.warming[cars[4]] = "dmc-2"
        return g

    a, b = setup(), setup()
    assert b.plain_many(cars) == {v: a.plain(v) for v in cars}
    assert sum(b.plain_many(cars).values()) == 5 and set(b.last_out) == set(a.last_out)
    for g in (a, b):
        g.post_cut.pop(cars[1])
        g.owned.discard(cars[0])
    assert b.plain_many(cars) == {v: a.plain(v) for v in cars}
    for g in (a, b):  # cut off, and a vehicle whose outputs paused: held until a round shows nobody ahead
        g.cut_off_since = 1.0
        g.last_out[cars[5]] -= 10.0
    assert b.plain_many(cars) == {v: a.plain(v) for v in cars} and not b.plain_many(cars)[cars[5]]


def test_the_frames_watch_is_declared_only_while_another_member_keeps_its_journal_elsewhere(tmp_path, monkeypatch):
    """Every other live member journalled on this host: no frames watch (a failover reads the journals); one that
    is not (another host): the watch is declared, for remote publishers only (own frames never delivered), and
    undeclared again once that member is journalled here."""
    import zenoh

    from magmesh import group_member as gm

    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    (tmp_path / "journal").mkdir()
    declared, undeclared = [], []

    class _W:
        def undeclare(self):
            undeclared.append(self)

        def try_recv(self):
            return None

    class _Sess:
        def declare_subscriber(self, kexpr, handler, **kw):
            declared.append((kexpr, kw))
            return _W()

    class _RtS(_Rt):
        session = _Sess()

    g = gm.GroupMember(_RtS(), "dmc")
    g._out_kexpr = "magmesh/fleet/*/dmc"
    g.live = {"dmc-1", "dmc-2"}
    journal = tmp_path / "journal" / "dmc_detector.dmc-2.seq"
    journal.write_bytes(b"")
    g._watch_outputs()
    assert declared == [] and g._out_sub is None
    journal.unlink()
    g._journal_seen.clear()
    g._watch_outputs()
    assert declared == [("magmesh/fleet/*/dmc", {"allowed_origin": zenoh.Locality.REMOTE})] and g._out_sub is not None
    assert g.stats["output_watch"] is True
    g._watch_outputs()
    assert len(declared) == 1  # (declared once)
    journal.write_bytes(b"")
    g._journal_seen.clear()
    g._watch_outputs()
    assert len(undeclared) == 1 and g._out_sub is None and g.stats["output_watch"] is False


def test_a_settled_member_rounds_less_often_and_wakes_for_what_must_not_wait(monkeypatch):
    """Rounds every period_s while anything moves, every IDLE_PERIOD_S once the membership and holdings stayed the
    same for STEADY_AFTER_S; a hand-over request and a token that comes or goes wake the round at once."""
    import magmesh.group_member as gm

    g, rt, posted = _member("dmc-1", ["dmc-1", "dmc-2"], {})
    g.complete = True
    clock = [1000.0]
    monkeypatch.setattr(gm.time, "monotonic", lambda: clock[0])
    assert g._busy()  # the membership just seen: not settled yet
    clock[0] += gm.STEADY_AFTER_S + 0.1
    assert not g._busy()
    g.owned.add("car-1")  # the holdings changed: busy again for STEADY_AFTER_S
    assert g._busy()
    clock[0] += gm.STEADY_AFTER_S + 0.1
    assert not g._busy()
    g.warming["car-2"] = "dmc-2"  # a hand-over under way
    assert g._busy()
    del g.warming["car-2"]
    assert g._busy()  # (a change is seen by the round after it; settled STEADY_AFTER_S from there)
    clock[0] += gm.STEADY_AFTER_S + 0.1
    assert not g._busy()
    g._dead_since["dmc-3"] = clock[0]  # a member went a moment ago
    assert g._busy()
    clock[0] += gm.STEADY_AFTER_S + 0.1
    assert not g._busy()  # ... long ago: settled again
    g.complete = False  # a member did not answer
    assert g._busy()
    g.complete = True
    assert not g._busy()
    # a request of another member wakes the round; a plain state query does not
    g._wake.clear()
    g.control({"op": "g_state"})
    assert not g._wake.is_set()
    g.control({"op": "g_done", "vehicles": []})
    assert g._wake.is_set()
    assert g.status()["round_s"] == g.period_s


def test_a_member_narrows_its_frames_to_its_own_upstream_shard_only_when_co_partitioned_and_settled():
    """magmesh/frame_subs.py: narrowed per kind to the one upstream shard with this member's number when every
    upstream shard seen has a number of this group and this member's vehicles came from that shard alone; widened
    when the group is not settled or a token comes or goes."""
    from types import SimpleNamespace

    from magmesh import frame_subs as fsm

    g = SimpleNamespace(me="dmc-1", members=["dmc-1", "dmc-2"], ready=True, complete=True, settled=True,
                        leaving=False, owned={"car-1"})
    rt = SimpleNamespace(group=g, svc=SimpleNamespace(instance="dmc-1"), last_error=None)
    fs = fsm.FrameSubscriptions(rt, ["clean", "cal"])
    switched: list = []

    def switch(narrow):
        switched.append(dict(narrow))
        fs.narrow = dict(narrow)

    fs._switch = switch
    t0 = fs.changed_at
    now = t0 + fsm.NARROW_AFTER_S + 1.0

    def frames(kind, shards, mine):
        for s in shards:
            fs.noted(kind, s, s in mine, t0 + 0.5)

    frames("clean", ["ingest-1", "ingest-2"], {"ingest-1"})
    frames("cal", ["cal-1", "cal-2"], {"cal-1", "cal-2"})  # this member's vehicles in both: not co-partitioned
    fs._step(t0 + 1.0)
    assert switched == []  # not settled long enough since the last change
    fs._step(now)
    assert switched == [{"clean": "ingest-1"}]
    fs._step(now + 0.1)
    assert len(switched) == 1  # nothing new to narrow
    g.settled = False  # the group is busy (a hand-over under way): every shard again
    fs._step(now + 0.2)
    assert switched[-1] == {}
    # upstream shards numbered unlike this group (three ingest members, two here): every shard
    g.settled = True
    t0 = fs.changed_at
    now = t0 + fsm.NARROW_AFTER_S + 1.0
    frames("clean", ["ingest-1", "ingest-2", "ingest-3"], {"ingest-1"})
    fs._step(now)
    assert switched[-1] == {}
    # an upstream stage that is not a group (one shard with no number): every shard
    fs2 = fsm.FrameSubscriptions(rt, ["clean"])
    fs2._switch = lambda narrow: switched.append(("fs2", narrow))
    fs2.noted("clean", "ingest", True, fs2.changed_at + 0.5)
    fs2._step(fs2.changed_at + fsm.NARROW_AFTER_S + 1.0)
    assert not any(isinstance(x, tuple) for x in switched)
    # a token that comes or goes: the change time moves and the switch thread is woken
    import time

    before = time.monotonic()
    fs._on_token(None)
    assert fs._wide.is_set() and fs.changed_at >= before
    # a frame delivered twice around a switch is taken once; a newer one always
    fs.dedupe_until = float("inf")
    assert fs.duplicate("magmesh/fleet/ingest-1/clean", 7, 7) and not fs.duplicate("magmesh/fleet/ingest-1/clean", 8, 7)
    fs.dedupe_until = 0.0
    assert not fs.duplicate("magmesh/fleet/ingest-1/clean", 3, 7)  # (outside a switch: the seq checks count it)
