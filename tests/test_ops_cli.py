"""Operator commands as users meet them: mistakes get one paragraph and a non-zero exit (never a traceback),
every wait is bounded, bad replies are warnings, --duration ends the command, swap picks the right instance.

Real subprocesses with ``sys.executable``; most need no mesh. The few that do use an in-test router on their
own port and the test's own MAGMESH_STATE_DIR (conftest)."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import msgpack
import pytest
from meshutil import REPO, endpoint, free_port, open_router

from schemas import keys, messages

DEMO = REPO / "deploy" / "mesh.toml"
WAIT_S = 90  # the bound on any one command (a loaded machine is slow; a hang never ends)


def magmesh(*args: str, timeout: float = WAIT_S) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "magmesh", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout, stdin=subprocess.DEVNULL)


def magmesh_inproc(capsys, *args: str) -> tuple[int, str, str]:
    """The same command in this process (the command's own code path, without a process start-up of a few
    seconds on a loaded machine); used for the many variants of a case a subprocess test already covers."""
    from magmesh_cli.cli import main

    rc = main(list(args))
    out, err = capsys.readouterr()
    return rc, out, err


def one_paragraph(text: str) -> str:
    """The message, checked to be one paragraph without a traceback."""
    t = text.strip()
    assert t, "no message"
    assert "Traceback" not in t, t
    assert "\n\n" not in t, t
    return t


# ---- magmesh up: the whole manifest is checked before anything starts --------------------------------


def _write(tmp_path: Path, text: str, name: str = "m.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


MANIFEST_MISTAKES = {
    "missing file": (None, ["no such file"]),
    "bad toml": ("[mesh\nendpoint = 1\n", ["not valid TOML", "line 1"]),
    "misspelled key": ('[[process]]\nname = "a"\nmodul = "services.ingest"\n',
                       ["'a'", "unknown key 'modul'", "did you mean 'module'", "known: name, module"]),
    "missing key": ('[[process]]\nname = "a"\n', ["missing key 'module'", "'a'"]),
    "unknown table": ('[proces]\nname = "a"\n', ["unknown table [proces]", "known: mesh, vehicles, process"]),
    "unknown module": ('[[process]]\nname = "a"\nmodule = "services.no_such"\n',
                       ["process 'a'", "no module named 'services.no_such'"]),
    "unknown setting": ('[[process]]\nname = "ing"\nmodule = "services.ingest"\nsettings = { bogus = 1 }\n',
                        ["process 'ing'", "unknown setting(s) bogus", "known:", "max_field_nt"]),
    "bad setting value": ('[[process]]\nname = "d"\nmodule = "services.dmc_detector"\n'
                          'args = ["--impl", "fcm"]\nsettings = { kc_min = 2.0 }\n', ["process 'd'", "kc_min"]),
    "unknown implementation": ('[[process]]\nname = "d"\nmodule = "services.dmc_detector"\nargs = ["--impl", "zz"]\n',
                               ["process 'd'", "unknown implementation 'zz'", "fcm, gyro_track, quasistatic, single, threshold"]),
    "wrong type": ('[[process]]\nname = "a"\nmodule = "services.ingest"\nenabled = "yes"\n',
                   ["enabled must be a bool"]),
}


SUBPROCESS_CASES = ("missing file", "misspelled key", "unknown setting")


@pytest.mark.parametrize("case", list(MANIFEST_MISTAKES))
def test_up_refuses_a_manifest_mistake_in_one_paragraph(tmp_path, capsys, case):
    text, needles = MANIFEST_MISTAKES[case]
    path = tmp_path / "absent.toml" if text is None else _write(tmp_path, text)
    args = ("up", str(path), "--endpoint", endpoint(free_port()), "--duration", "30", "--quiet", "--log-dir",
            str(tmp_path / "logs"))
    if case in SUBPROCESS_CASES:
        r = magmesh(*args)
        rc, err = r.returncode, r.stderr
    else:
        rc, _, err = magmesh_inproc(capsys, *args)
    assert rc == 2, err
    msg = one_paragraph(err)
    assert str(path) in msg, msg  # which file
    for n in needles:
        assert n in msg, (n, msg)
    assert not (tmp_path / "logs").exists(), "something was started before the manifest was checked"


@pytest.mark.parametrize("flag,needles", [
    (["--only", "dmc-9"], ["--only", "no process named dmc-9", "dmc-broad-1"]),
    (["--set", "sim-car-1.sped=3"], ["process 'sim-car-1'", "unknown setting(s) sped", "speed"]),
    (["--set", "nobody.speed=3"], ["no process named 'nobody'", "sim-car-1"]),
    (["--set", "speed3"], ["PROCESS.NAME=VALUE"]),
])
def test_up_refuses_bad_only_and_set_names(tmp_path, capsys, flag, needles):
    rc, _, err = magmesh_inproc(capsys, "up", str(DEMO), "--endpoint", endpoint(free_port()), "--duration", "30",
                                "--quiet", "--log-dir", str(tmp_path / "logs"), *flag)
    assert rc == 2, err
    msg = one_paragraph(err)
    for n in needles:
        assert n in msg, (n, msg)
    assert not (tmp_path / "logs").exists()


def test_demo_manifest_passes_the_check():
    from magmesh_cli.supervisor import check_processes, load_manifest

    m = load_manifest(DEMO)
    check_processes(m, all_processes=True)  # raises on any problem
    assert m.give_up_after == 5


def test_up_gives_up_a_process_that_fails_on_start_and_exits_non_zero(tmp_path):
    # passes the check (the path is a valid setting) but fails when the service starts: no such model file
    path = _write(tmp_path, '[mesh]\nrestart_backoff_s = [0.1]\ngive_up_after = 3\n'
                  '[[process]]\nname = "dmc-bad"\nmodule = "services.dmc_detector"\nargs = ["--impl", "fcm"]\n'
                  f'settings = {{ model_path = "{tmp_path / "no_such_model.json"}" }}\n')
    r = magmesh("up", str(path), "--endpoint", endpoint(free_port()), "--duration", "240", "--quiet",
                "--log-dir", str(tmp_path / "logs"), timeout=240)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "Traceback" not in r.stderr.split("Last lines")[0], r.stderr
    assert "dmc-bad failed 3 times in a row on start" in r.stderr, r.stderr
    assert "given up" in r.stderr and "no_such_model.json" in r.stderr, r.stderr  # its own error, on the terminal


# ---- bad names and unreachable endpoints -----------------------------------------------------------


@pytest.mark.parametrize("args", [["swap", "dmc/*", "fcm"], ["swap", "dmc_detector", "fcm", "--instance", "a/b"],
                                  ["swap", "dmc_detector", "fcm", "--vehicles", "car/**"],
                                  ["alarms", "--vehicle", "a/b", "--duration", "1"]])
def test_bad_names_are_one_paragraph(capsys, args):
    if args[:2] == ["swap", "dmc/*"]:  # the case of the report, as a user runs it
        r = magmesh(*args, "--connect", "tcp/127.0.0.1:1")
        rc, err = r.returncode, r.stderr
    else:
        rc, _, err = magmesh_inproc(capsys, *args, "--connect", "tcp/127.0.0.1:1")
    assert rc == 2, err
    msg = one_paragraph(err)
    assert msg.startswith("magmesh "), msg


@pytest.mark.parametrize("args", [["status"], ["status", "--json"], ["alarms", "--duration", "30"],
                                  ["swap", "dmc_detector", "fcm", "--timeout", "2"],
                                  ["record", "-o", "{tmp}/x.mcap", "--duration", "30", "--timeout", "2"]])
def test_client_commands_without_a_router_exit_non_zero(tmp_path, capsys, args):
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    if "--timeout" not in args:
        args += ["--timeout", "2"]
    if args == ["status", "--timeout", "2"]:  # the case of the report, as a user runs it
        r = magmesh(*args, "--connect", "tcp/127.0.0.1:1")
        rc, err = r.returncode, r.stderr
    else:
        rc, _, err = magmesh_inproc(capsys, *args, "--connect", "tcp/127.0.0.1:1")
    assert rc == 1, err
    msg = one_paragraph(err)
    assert "could not connect to tcp/127.0.0.1:1" in msg, msg


def test_ctrl_c_ends_a_client_waiting_for_a_connection():
    import signal

    # as from a terminal: a test run started in the background of a shell inherits SIGINT ignored, and Python
    # then installs no KeyboardInterrupt handler (seen: a clean-clone run under nohup hung here 90 s)
    p = subprocess.Popen([sys.executable, "-m", "magmesh", "status", "--connect", "tcp/127.0.0.1:1", "--timeout",
                          "300"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        # interrupted once it says it is waiting on the connection (not at a fixed time: a start can take longer)
        first = p.stderr.readline()
        assert "connecting to tcp/127.0.0.1:1" in first and p.poll() is None, (first, p.poll())
        os.killpg(p.pid, signal.SIGINT)
        out, err = p.communicate(timeout=WAIT_S)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err, err


# ---- help texts and reject reasons -----------------------------------------------------------------


@pytest.mark.parametrize("module", ["services.ingest", "services.dmc_detector", "sim_publishers.car"])
def test_service_help_names_the_program(module):
    r = subprocess.run([sys.executable, "-m", module, "--help"], cwd=REPO, capture_output=True, text=True,
                       timeout=WAIT_S)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith(f"usage: python -m {module} "), r.stdout[:200]
    assert "__main__.py" not in r.stdout


def test_dmc_detector_help_lists_impl():
    r = subprocess.run([sys.executable, "-m", "services.dmc_detector", "--help"], cwd=REPO, capture_output=True,
                       text=True, timeout=WAIT_S)
    assert "--impl {threshold,fcm,single,quasistatic,gyro_track}" in r.stdout, r.stdout[:600]
    for impl in ("threshold", "fcm", "single", "quasistatic", "gyro_track"):
        assert f"\n  {impl} " in r.stdout, impl


def test_garbage_reject_reason_is_not_empty():
    for payload in (b"\xc1", b"\xc1\xc1\xc1"):
        with pytest.raises(messages.SchemaError) as e:
            messages.decode(payload, where="magmesh/car-1/raw/imu")
        assert not str(e.value).rstrip().endswith(": )"), str(e.value)
        assert "FormatError: " in str(e.value) and "reserved" in str(e.value)


# ---- replies that are not what they should be ------------------------------------------------------


def _alarm(seq: int, state: str = "raised") -> dict:
    return messages.make("alarm", "car-1", 10.0 + seq, seq, source="dmc", state=state, severity="warning",
                         reason="test", value=1.0, threshold=2.0, service="fake-1")


@pytest.fixture
def router():
    port = free_port()
    s = open_router(port)
    yield port, s
    s.close()


def test_alarms_prints_each_alarm_once_and_survives_garbage(router):
    from zenoh import ext

    port, s = router
    good = messages.encode(_alarm(3))
    key = keys.alarm("car-1", "dmc")
    # the alarm's owner: history for late joiners (the same sample the query returns) and a queryable
    pub = ext.declare_advanced_publisher(s, key, cache=ext.CacheConfig(max_samples=8),
                                         sample_miss_detection=ext.MissDetectionConfig(heartbeat=0.5),
                                         publisher_detection=True)
    pub.put(good)
    bad_replies = [b"\xc1garbage", msgpack.packb([1, 2, 3]), msgpack.packb({"type": "alarm", "seq": 1}),
                   msgpack.packb({**_alarm(4), "state": None})]

    def answer(q):
        q.reply(key, good)
        for i, b in enumerate(bad_replies):
            q.reply(keys.alarm("car-1", f"bad{i}"), b)

    qa = s.declare_queryable(keys.alarms_all("car-1"), answer)
    stop = threading.Event()

    def live():  # the same transition again (a re-delivery), then garbage, then a new transition
        time.sleep(2.0)
        s.put(key, good)
        s.put(keys.alarm("car-1", "junk"), b"\x00\xff")
        pub.put(messages.encode(_alarm(4, "cleared")))

    try:
        t = threading.Thread(target=live, daemon=True)
        t.start()
        r = magmesh("alarms", "--json", "--duration", "8", "--connect", endpoint(port))
    finally:
        stop.set()
        qa.undeclare()
        pub.undeclare()
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    printed = [line for line in r.stdout.splitlines() if line.strip()]
    import json

    seqs = [(json.loads(x)["seq"], json.loads(x)["state"]) for x in printed]
    assert seqs == [(3, "raised"), (4, "cleared")], r.stdout
    warnings = [ln for ln in r.stderr.splitlines() if ln.startswith("warning: ignored an invalid alarm")]
    assert len(warnings) == len(bad_replies) + 1, r.stderr
    assert "ignored 5 invalid alarm(s)" in r.stderr, r.stderr


def test_status_survives_garbage_replies(router):
    port, s = router
    tok = s.liveliness().declare_token(keys.svc_token("fake", "f-1"))
    tok2 = s.liveliness().declare_token(keys.svc_token("fake", "f-2"))
    good = {"type": "status", "version": 1, "role": "fake", "instance": "f-2", "impl": "x", "uptime_s": "soon",
            "in": {"k": {"rate_hz": "fast"}}, "out": [], "rejects": 0, "drops_total": 0, "vehicles": None}

    def answer(q):
        q.reply(keys.svc_status("fake", "f-1"), b"\xc1\xc1")  # replies are consolidated per key: one each
        q.reply(keys.svc_status("fake", "f-3"), msgpack.packb("a string"))
        q.reply(keys.svc_status("fake", "f-2"), msgpack.packb(good))

    qs = s.declare_queryable(keys.svc_status_all(), answer)
    try:
        r = magmesh("status", "--connect", endpoint(port))
    finally:
        qs.undeclare()
        tok.undeclare()
        tok2.undeclare()
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    assert r.stderr.count("warning: ignored a status reply") == 2, r.stderr
    rows = {ln.split()[1]: ln for ln in r.stdout.splitlines() if ln.startswith("fake")}
    assert set(rows) == {"f-1", "f-2"}, r.stdout


# ---- --duration ends the command -------------------------------------------------------------------


def test_record_with_duration_exits_while_data_keeps_flowing(router, tmp_path):
    port, s = router
    stop = threading.Event()
    sent = [0]

    def publish():  # a steady stream: the recorder's final drain must not wait for a quiet moment
        pub = s.declare_publisher(keys.raw_imu("car-1"))
        while not stop.is_set():
            pub.put(messages.encode(messages.make("imu", "car-1", sent[0] * 0.005, sent[0], gyro_rad_s=[0.0, 0.0, 0.0],
                                                  accel_m_s2=[0.0, 0.0, 9.8])))
            sent[0] += 1
            time.sleep(0.005)
        pub.undeclare()

    t = threading.Thread(target=publish, daemon=True)
    t.start()
    try:
        r = magmesh("record", "-o", str(tmp_path / "run.mcap"), "--duration", "3", "--quiet", "--connect",
                    endpoint(port))
    finally:
        stop.set()
        t.join(5)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("recorded "), r.stdout
    n = int(r.stdout.split()[1])
    assert n > 50, r.stdout  # it did record the stream


# ---- swap: which instance ----------------------------------------------------------------------------


class _FakeChild:
    def __init__(self, spec):
        self.spec = spec
        self.alive = True


def _swapper(monkeypatch, instances: dict[str, tuple[str, str]]):
    """A Swapper over the demo manifest's detector specs; ``instances``: name -> (spec name, running impl)."""
    from magmesh_cli.supervisor import load_manifest
    from magmesh_cli.swap import Swapper

    specs = {p.name: p for p in load_manifest(DEMO).processes}
    children = {name: _FakeChild(specs[spec]) for name, (spec, _) in instances.items()}
    sw = Swapper(SimpleNamespace(children=children))
    monkeypatch.setattr(sw, "_candidates", lambda role: [
        (n, children[n], {"impl": impl, "mode": "active", "last_in_t": {}}) for n, (_, impl) in instances.items()])
    return sw


def test_swap_default_candidate_in_the_demo(monkeypatch):
    from magmesh_cli.swap import SwapError

    demo = {"dmc-1": ("dmc-1", "threshold"), "dmc-broad-1": ("dmc-broad-1", "quasistatic")}
    # the quasi-static detector's settings (level, dpsi_threshold_deg) are unknown to fcm/threshold
    assert _swapper(monkeypatch, demo)._choose("dmc_detector", "fcm", None, None)[0] == "dmc-1"
    after = {"dmc-1-fcm": ("dmc-1", "fcm"), "dmc-broad-1": ("dmc-broad-1", "quasistatic")}
    assert _swapper(monkeypatch, after)._choose("dmc_detector", "threshold", None, None)[0] == "dmc-1-fcm"
    with pytest.raises(SwapError, match=r"dmc-broad-1 cannot be swapped to threshold: .*unknown setting\(s\) "
                                        r"dpsi_threshold_deg, level"):
        _swapper(monkeypatch, after)._choose("dmc_detector", "threshold", "dmc-broad-1", None)
    assert _swapper(monkeypatch, after)._choose("dmc_detector", "threshold", None, "car-1")[0] == "dmc-1-fcm"
    with pytest.raises(SwapError, match="roles: dmc_detector"):
        _swapper(monkeypatch, demo)._choose("dmc_detectr", "fcm", None, None)
    with pytest.raises(SwapError, match="dmc-1-zz not started.*known: fcm, gyro_track, quasistatic, single, threshold"):
        _swapper(monkeypatch, {"dmc-1": ("dmc-1", "threshold")})._choose("dmc_detector", "zz", None, None)


def test_swap_with_several_candidates_refuses_and_lists_them(monkeypatch):
    from magmesh_cli.swap import SwapError

    two = {"dmc-1": ("dmc-1", "threshold"), "dmc-2": ("dmc-1", "single")}
    with pytest.raises(SwapError) as e:
        _swapper(monkeypatch, two)._choose("dmc_detector", "fcm", None, None)
    msg = str(e.value)
    assert "dmc-1 (threshold, vehicles car-$*)" in msg and "dmc-2 (single, vehicles car-$*)" in msg, msg
    assert "--instance" in msg
    assert _swapper(monkeypatch, two)._choose("dmc_detector", "fcm", "dmc-2", None)[0] == "dmc-2"


def test_a_swap_standby_process_is_not_restarted_or_misnamed(tmp_path):
    from magmesh_cli.supervisor import Child, ProcessSpec

    spec = ProcessSpec(name="dmc-broad-1", module="services.dmc_detector")
    log = tmp_path / "x.log"
    ch = Child(spec, [sys.executable, "-c", "import sys; print('threshold: unknown setting(s) level'); sys.exit(1)"],
               log, [0.1], name="dmc-broad-1-threshold", give_up_after=3)
    ch.supervised = False
    ch.start()
    ch.proc.wait(WAIT_S)
    assert ch.check(time.monotonic() + 10) is None  # the swap, not the supervisor, handles it
    ch.supervised = True
    ev = ch.check(time.monotonic())
    assert ev.startswith("dmc-broad-1-threshold exited with code 1"), ev
    assert ch.last_lines() == ["threshold: unknown setting(s) level"]


def test_give_up_counts_own_exits_on_start_not_kills(tmp_path):
    import signal

    from magmesh_cli.supervisor import Child, ProcessSpec

    spec = ProcessSpec(name="p", module="services.ingest")
    failing = Child(spec, [sys.executable, "-c", "import sys; sys.exit(3)"], tmp_path / "f.log", [0.0],
                    give_up_after=2)
    killed = Child(spec, [sys.executable, "-c", "import time; time.sleep(60)"], tmp_path / "k.log", [0.0],
                   give_up_after=2)
    for _ in range(4):
        for ch in (failing, killed):
            if ch.given_up:
                continue
            ch.start()
            if ch is killed:
                ch.stop(signal.SIGKILL)
            ch.proc.wait(WAIT_S)
            ch.check(time.monotonic())
            ch.died_at = None  # the next start is immediate (the test starts it)
    assert failing.given_up and failing.start_failures == 2
    assert not killed.given_up and killed.start_failures == 0


def test_up_on_a_taken_endpoint_is_one_paragraph(router, tmp_path, capsys):
    port, _ = router
    rc, _, err = magmesh_inproc(capsys, "up", str(DEMO), "--endpoint", endpoint(port), "--only", "ingest-1",
                                "--duration", "5", "--quiet", "--log-dir", str(tmp_path / "logs"))
    assert rc == 1, err
    msg = one_paragraph(err)
    assert f"cannot host the Zenoh endpoint {endpoint(port)}" in msg and "--endpoint" in msg, msg


def test_recording_counts_samples_missed_in_transit(tmp_path):
    from magmesh_cli.recording import RecordingWriter

    def imu(seq):
        return messages.make("imu", "car-1", seq * 0.01, seq, gyro_rad_s=[0.0, 0.0, 0.0], accel_m_s2=[0.0, 0.0, 9.8])

    with RecordingWriter(tmp_path / "r.mcap") as w:
        for seq in (0, 1, 2, 5, 6, 0, 1, 10**9):  # a gap of 2; a restarted publisher; a forged jump
            w.write_message(keys.raw_imu("car-1"), imu(seq))
    c = w.counts.as_dict()
    assert c["written"] == 8
    assert c["missed"] == 2 and c["missed_per_key"] == {keys.raw_imu("car-1"): 2}, c
    from magmesh_cli.commands.record import format_counts

    assert "MISSED in transit (gaps in seq, never received): 2" in format_counts(c, "r.mcap")


def test_json_output_is_only_the_json_whatever_else_writes_to_stdout():
    """With --json, what writes to file descriptor 1 besides the command's print (Zenoh's own log, programs started
    with its stdout) goes to stderr: the JSON stays readable."""
    code = ("import os, subprocess, sys; from magmesh_cli.cli import json_stdout; json_stdout(); "
            "os.write(1, b'rust log line\\n'); subprocess.run([sys.executable, '-c', 'print(\"child\")']); "
            "print('{\"ok\": true}')")
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout == '{"ok": true}\n'
    assert "rust log line" in r.stderr and "child" in r.stderr
