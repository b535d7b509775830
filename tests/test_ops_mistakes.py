"""Every user mistake of the command line, as a user makes it: a real process (``sys.executable``), a non-zero exit,
no traceback, one short paragraph naming the problem.

The commands run side by side (a pool of eight: most of their time is waiting) once per module, so the whole table costs about as much as its
slowest few commands; a handful need a running mesh (a supervisor with one detector) and get one.
"""

from __future__ import annotations

import concurrent.futures as cf
import os
import subprocess
import sys

import pytest
from meshutil import REPO, endpoint, free_port, open_client, stop, wait_alive

from schemas import keys

pytestmark = pytest.mark.mesh

WAIT_S = 120  # a hang guard only (a loaded machine imports slowly)
M = [sys.executable, "-m", "magmesh"]
DEAD = ["--connect", "tcp/127.0.0.1:1", "--timeout", "2"]  # nothing answers there

MANIFESTS = {
    "bad.toml": "[mesh\nendpoint = 1\n",
    "misspelled.toml": '[[process]]\nname = "a"\nmodul = "services.ingest"\n',
    "missing.toml": '[[process]]\nname = "a"\n',
    "module.toml": '[[process]]\nname = "a"\nmodule = "services.no_such"\n',
    "setting.toml": '[[process]]\nname = "ing"\nmodule = "services.ingest"\nsettings = { bogus = 1 }\n',
    "impl.toml": '[[process]]\nname = "d"\nmodule = "services.dmc_detector"\nargs = ["--impl", "zz"]\n',
}
ONE_DETECTOR = ('[mesh]\nrestart_backoff_s = [0.2]\n'
                '[[process]]\nname = "dmc-1"\nmodule = "services.dmc_detector"\nvehicles = "car-$*"\n'
                'args = ["--impl", "threshold"]\n')

# name: (command after `magmesh` (or a full argv when it starts with "-m"), text the message must contain);
# {tmp} is the test's directory, {mesh} the endpoint of the running mesh
CASES: dict[str, tuple[list[str], str]] = {
    "up: missing manifest": (["up", "{tmp}/absent.toml"], "no such file"),
    "up: bad TOML": (["up", "{tmp}/bad.toml"], "not valid TOML"),
    "up: misspelled key": (["up", "{tmp}/misspelled.toml"], "unknown key 'modul'"),
    "up: missing key": (["up", "{tmp}/missing.toml"], "missing key 'module'"),
    "up: unknown module": (["up", "{tmp}/module.toml"], "no module named 'services.no_such'"),
    "up: unknown setting": (["up", "{tmp}/setting.toml"], "unknown setting(s) bogus"),
    "up: unknown implementation": (["up", "{tmp}/impl.toml"], "unknown implementation 'zz'"),
    "up: --only unknown process": (["up", "deploy/mesh.toml", "--only", "dmc-9"], "no process named dmc-9"),
    "up: --set unknown process": (["up", "deploy/mesh.toml", "--set", "nobody.speed=3"], "no process named 'nobody'"),
    "up: --set misspelled setting": (["up", "deploy/mesh.toml", "--set", "sim-car-1.sped=3"],
                                     "unknown setting(s) sped"),
    "up: --duration not a number": (["up", "deploy/mesh.toml", "--duration", "abc"], "--duration"),
    "up: --duration negative": (["up", "deploy/mesh.toml", "--duration", "-5"], "--duration -5"),
    "up: --endpoint not an endpoint": (["up", "deploy/mesh.toml", "--endpoint", "garbage"], "endpoint 'garbage'"),
    "swap: pattern as the role": (["swap", "dmc/*", "fcm", *DEAD], "role 'dmc/*' is not valid"),
    "swap: bad --instance": (["swap", "dmc_detector", "fcm", "--instance", "a/b", *DEAD], "'a/b'"),
    "swap: * inside a vehicle name": (["swap", "dmc_detector", "fcm", "--vehicles", "car-*", *DEAD], "'car-$*'"),
    "swap: unknown role": (["swap", "no_such_role", "fcm", "--connect", "{mesh}"], "'no_such_role'"),
    "swap: unknown implementation": (["swap", "dmc_detector", "zz", "--connect", "{mesh}"],
                                     "no implementation 'zz'"),
    "swap: unknown instance": (["swap", "dmc_detector", "fcm", "--instance", "dmc-9", "--connect", "{mesh}"],
                               "no running instance 'dmc-9'"),
    "swap: no instance serves the vehicles": (["swap", "dmc_detector", "fcm", "--vehicles", "boat-1",
                                              "--connect", "{mesh}"], "vehicles 'boat-1'"),
    "status: nothing answers": (["status", "--connect", "tcp/127.0.0.1:1"], "could not connect to tcp/127.0.0.1:1"),
    "status: not an endpoint": (["status", "--connect", "garbage"], "endpoint 'garbage'"),
    "status: --timeout 0": (["status", "--timeout", "0", "--connect", "tcp/127.0.0.1:1"], "--timeout 0"),
    "alarms: bad vehicle": (["alarms", "--vehicle", "a/b", *DEAD], "'a/b'"),
    "alarms: --duration negative": (["alarms", "--duration", "-3", *DEAD], "--duration -3"),
    "record: --duration negative": (["record", "-o", "{tmp}/x.mcap", "--duration", "-1", *DEAD], "--duration -1"),
    "record: nothing answers": (["record", "-o", "{tmp}/x.mcap", "--duration", "5", *DEAD],
                                "could not connect to tcp/127.0.0.1:1"),
    "replay: missing recording": (["replay", "{tmp}/absent.mcap", "--connect", "tcp/127.0.0.1:1"], "does not exist"),
    "replay: not a recording": (["replay", "{tmp}/bad.mcap", "--connect", "{mesh}"],
                                "not a readable MCAP recording"),
    "mcap info: not a recording": (["mcap", "info", "{tmp}/bad.mcap"], "not a readable MCAP recording"),
    "mcap info: missing recording": (["mcap", "info", "{tmp}/absent.mcap"], "does not exist"),
    "report: missing recording": (["report", "{tmp}/absent.mcap", "-o", "{tmp}/report"], "does not exist"),
    "unknown command": (["frobnicate"], "unknown command 'frobnicate'"),
    "router: not an endpoint": (["router", "--listen", "garbage"], "endpoint 'garbage'"),
    "service: unknown --impl": (["-m", "services.dmc_detector", "--impl", "zz", "--connect", "tcp/127.0.0.1:1"],
                                "unknown --impl 'zz'"),
    "service: unknown setting": (["-m", "services.ingest", "--set", "bogus=1", "--connect", "tcp/127.0.0.1:1"],
                                 "unknown setting(s) bogus"),
    "simulator: unknown layout": (["-m", "sim_publishers.car", "--set", "layout=nowhere", "--connect",
                                   "tcp/127.0.0.1:1"], "layout 'nowhere' is unknown"),
}
NEEDS_MESH = {n for n, (a, _) in CASES.items() if "{mesh}" in a}


def _run(argv: list[str]) -> subprocess.CompletedProcess:
    cmd = [sys.executable, *argv] if argv[0] == "-m" else [*M, *argv]
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=WAIT_S, stdin=subprocess.DEVNULL)


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """Every case's completed process; the mesh cases against one supervisor with one detector."""
    tmp = tmp_path_factory.mktemp("mistakes")
    for name, text in MANIFESTS.items():
        (tmp / name).write_text(text)
    (tmp / "bad.mcap").write_bytes(b"not an MCAP file at all")
    (tmp / "one.toml").write_text(ONE_DETECTOR)
    port = free_port()
    sup = subprocess.Popen([*M, "up", str(tmp / "one.toml"), "--endpoint", endpoint(port), "--duration", "600",
                            "--quiet", "--log-dir", str(tmp / "logs")], cwd=REPO, stdout=open(tmp / "up.log", "ab"),
                           stderr=subprocess.STDOUT, start_new_session=True,
                           env={**os.environ, "MAGMESH_STATE_DIR": str(tmp / "state")})
    out: dict[str, subprocess.CompletedProcess] = {}
    try:
        def argv(name: str) -> list[str]:
            return [a.replace("{tmp}", str(tmp)).replace("{mesh}", endpoint(port)) for a in CASES[name][0]]

        with cf.ThreadPoolExecutor(8) as ex:
            futs = {n: ex.submit(_run, argv(n)) for n in CASES if n not in NEEDS_MESH}
            client = open_client(port)
            try:
                assert wait_alive(client, keys.svc_token("dmc_detector", "dmc-1"), 90), "the test mesh never came up"
            finally:
                client.close()
            futs.update({n: ex.submit(_run, argv(n)) for n in NEEDS_MESH})
            out = {n: f.result() for n, f in futs.items()}
    finally:
        stop(sup, 10)
    return out


@pytest.mark.parametrize("case", list(CASES))
def test_a_mistake_is_one_short_paragraph_and_a_non_zero_exit(results, case):
    r = results[case]
    needle = CASES[case][1]
    err = r.stderr.strip()
    assert r.returncode != 0, f"exit 0 for a mistake: {r.stdout[-500:]} {err[-500:]}"
    assert "Traceback" not in r.stderr + r.stdout, err[-2000:]
    assert err, f"no message on stderr (stdout: {r.stdout[-500:]})"
    assert "\n\n" not in err, f"more than one paragraph: {err}"
    assert len(err) <= 1200, f"not short ({len(err)} characters): {err}"
    assert needle in err, f"the message does not name the problem ({needle!r}): {err}"
