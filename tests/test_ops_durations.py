"""Every command with ``--duration`` ends by itself with exit 0: real processes (``sys.executable``) against a
router of the test's own, run side by side once per module. The bound is a hang guard only; how long each took
is printed (start-up included: imports take seconds on a loaded machine)."""

from __future__ import annotations

import concurrent.futures as cf
import subprocess
import sys
import time

import pytest
from meshutil import REPO, endpoint, free_port, open_router

pytestmark = pytest.mark.mesh

DURATION_S = 3.0
GUARD_S = DURATION_S + 90.0  # a hang guard, not a timing limit

COMMANDS: dict[str, list[str]] = {
    "up": ["up", "{tmp}/one.toml", "--endpoint", "{free}", "--quiet", "--log-dir", "{tmp}/logs"],
    "alarms": ["alarms", "--connect", "{mesh}"],
    "record": ["record", "-o", "{tmp}/run.mcap", "--quiet", "--connect", "{mesh}"],
    "router": ["router", "--listen", "{free}"],
    "foxglove": ["foxglove", "--port", "{freeport}", "--quiet", "--connect", "{mesh}"],
    "ros2-bridge": ["ros2-bridge", "--connect", "{mesh}"],
    "report --live": ["report", "--live", "-o", "{tmp}/report", "--no-progress", "--connect", "{mesh}"],
}


def _run(argv: list[str]) -> tuple[subprocess.CompletedProcess | None, float]:
    t0 = time.monotonic()
    try:
        r = subprocess.run([sys.executable, "-m", "magmesh", *argv, "--duration", f"{DURATION_S:g}"], cwd=REPO,
                           capture_output=True, text=True, timeout=GUARD_S, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        return None, time.monotonic() - t0
    return r, time.monotonic() - t0


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("durations")
    (tmp / "one.toml").write_text('[[process]]\nname = "ingest-1"\nmodule = "services.ingest"\n')
    port = free_port()
    router = open_router(port)
    try:
        def argv(name: str) -> list[str]:
            return [a.replace("{tmp}", str(tmp)).replace("{mesh}", endpoint(port))
                    .replace("{free}", endpoint(free_port())).replace("{freeport}", str(free_port()))
                    for a in COMMANDS[name]]

        with cf.ThreadPoolExecutor(len(COMMANDS)) as ex:
            futs = {n: ex.submit(_run, argv(n)) for n in COMMANDS}
            out = {n: f.result() for n, f in futs.items()}
    finally:
        router.close()
    print("\n" + ", ".join(f"{n} {d:.1f} s" for n, (_, d) in out.items()) + f" (--duration {DURATION_S:g})")
    return out


@pytest.mark.parametrize("command", list(COMMANDS))
def test_a_command_with_duration_ends_by_itself_with_exit_0(results, command):
    r, took = results[command]
    assert r is not None, f"magmesh {command} --duration {DURATION_S:g} still running after {took:.0f} s"
    assert r.returncode == 0, f"exit {r.returncode}: {r.stderr[-1500:]}"
    assert "Traceback" not in r.stderr, r.stderr[-2000:]
    assert took >= DURATION_S, f"ended after {took:.1f} s, before its --duration"
