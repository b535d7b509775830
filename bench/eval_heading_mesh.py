"""``magmesh eval heading --mesh``: the demo car driven through the real processes, its ``heading`` scored live.

The demo manifest's car (``deploy/mesh.toml``: ``sim-car-1`` on its layout and seed, ``ingest-1``, ``dmc-1``,
``calibration-1``, ``heading-1`` with their settings, implementations and the manifest's vehicle parameters) runs
as separate processes behind a Zenoh router on a free loopback port, with a fresh state directory (no calibration
or alarm state carried over). The car drives once (no loop) at ``speed`` × real time. Scored from what an outside
subscriber receives: ``heading`` against ``truth/pose``, the fuser's mode against ``truth/sources`` (which
interference sources are near the car) and against ``alarm/dmc``:

- ``rms_deg``: heading RMS error over the whole drive (calibration converging and every interference zone
  included); goal ≤ 2.5°;
- ``magnetic_frac_clear``: share of the heading messages in ``magnetic`` mode while no source is active; goal
  ≥ 90 % (``magnetometer_in_use_frac_clear`` also counts ``recovering``, where the magnetometer steers the
  heading with inflated noise and a bounded slew after a disturbance);
- ``gyro_within_1s``: for each ``alarm/dmc`` raised, whether the fuser is in ``gyro_only`` within 1 s of sample
  time of it; goal: every alarm.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from schemas import keys

GOAL_RMS_DEG = 2.5
GOAL_MAGNETIC_FRAC_CLEAR = 0.90
GYRO_WITHIN_S = 1.0
PROCESSES = ("sim-car-1", "ingest-1", "dmc-1", "calibration-1", "heading-1")
VEHICLE = "car-1"


def score(heading: list[dict], pose: list[dict], sources: list[dict], dmc_alarms: list[dict]) -> dict:
    """The live figures from the messages an outside subscriber received (each list in arrival order)."""
    if not heading or len(pose) < 2:
        raise ValueError(f"nothing to score: {len(heading)} heading and {len(pose)} truth/pose messages arrived")
    t_h = np.array([m["t_s"] for m in heading], float)
    est = np.array([m["heading_rad"] for m in heading], float)
    mode = np.array([m["mode"] for m in heading])
    tp = np.array([m["t_s"] for m in pose], float)
    order = np.argsort(tp, kind="stable")
    tp = tp[order]
    truth_h = np.unwrap(np.array([pose[i]["heading_rad"] for i in order], float))
    inside = (t_h >= tp[0]) & (t_h <= tp[-1])
    err = np.degrees(np.abs(np.remainder(est[inside] - np.interp(t_h[inside], tp, truth_h) + math.pi, 2 * math.pi)
                            - math.pi))
    out: dict = {"n_heading": int(len(heading)), "t_end_s": float(t_h.max()),
                 "rms_deg": float(np.sqrt(np.mean(err**2))) if err.size else float("nan"),
                 "p95_deg": float(np.percentile(err, 95)) if err.size else float("nan"),
                 "max_deg": float(err.max()) if err.size else float("nan"),
                 "mode_frac": {k: float(np.mean(mode == k)) for k in sorted(set(mode.tolist()))}}
    # sources active at each heading message: the last truth/sources sample at or before it
    if sources:
        ts = np.array([m["t_s"] for m in sources], float)
        so = np.argsort(ts, kind="stable")
        ts = ts[so]
        active = np.array([bool(sources[i].get("active_sources")) for i in so])
        j = np.searchsorted(ts, t_h, side="right") - 1
        clear = (j >= 0) & ~active[np.clip(j, 0, None)]
        out["clear_frac"] = float(np.mean(clear))
        out["magnetic_frac_clear"] = float(np.mean(mode[clear] == "magnetic")) if clear.any() else None
        # recovering fuses the magnetometer too (with inflated noise and a bounded slew): in use, not yet trusted
        out["magnetometer_in_use_frac_clear"] = (float(np.mean(np.isin(mode[clear], ("magnetic", "recovering"))))
                                                 if clear.any() else None)
    else:
        out["clear_frac"] = None
        out["magnetic_frac_clear"] = None
        out["magnetometer_in_use_frac_clear"] = None
    raised = [float(a["t_s"]) for a in dmc_alarms if a.get("state") == "raised"]
    hits = []
    for t_r in raised:
        w = (t_h >= t_r) & (t_h <= t_r + GYRO_WITHIN_S)
        hits.append(bool(np.any(mode[w] == "gyro_only")))
    out["dmc_alarms_raised"] = len(raised)
    out["gyro_within_1s"] = int(sum(hits))
    out["gyro_late_at_t_s"] = [t for t, h in zip(raised, hits, strict=True) if not h]
    out["meets"] = {"rms": bool(out["rms_deg"] <= GOAL_RMS_DEG),
                    "magnetic_clear": (out["magnetic_frac_clear"] is not None
                                       and out["magnetic_frac_clear"] >= GOAL_MAGNETIC_FRAC_CLEAR),
                    "gyro_within_1s": bool(raised) and all(hits)}
    return out


def measure(duration_s: float = 300.0, speed: float = 5.0, manifest_path: Path | None = None,
            heading_impl: str | None = None, progress: bool = True, raw: dict | None = None) -> dict:
    """Drive the manifest's car once through its real processes; the figures of :func:`score` plus the set-up."""
    import zenoh

    from bench.elastic_run import Collector, free_port
    from bench.mesh_bench import wait_tokens
    from magmesh import zconf
    from magmesh.paths import DEPLOY_DIR, REPO
    from magmesh_cli import supervisor

    path = Path(manifest_path or DEPLOY_DIR / "mesh.toml")
    man = supervisor.load_manifest(path)
    specs = {p.name: p for p in man.processes}
    missing = [n for n in PROCESSES if n not in specs]
    if missing:
        raise SystemExit(f"manifest {path}: the mesh heading eval drives the demo car and needs the processes "
                         f"{', '.join(PROCESSES)}; missing: {', '.join(missing)}.")
    sim = specs["sim-car-1"]
    sim = replace(sim, settings={**sim.settings, "speed": float(speed), "loop": False, "duration_s": float(duration_s)})
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    router = zenoh.open(zconf.build_config(mode="router", listen=[endpoint]))
    got = {"heading": Collector(router, keys.heading(VEHICLE)), "pose": Collector(router, keys.truth(VEHICLE, "pose")),
           "sources": Collector(router, keys.truth(VEHICLE, "sources")),
           "dmc_alarms": Collector(router, keys.alarm(VEHICLE, "dmc"))}
    procs: list[subprocess.Popen] = []
    with tempfile.TemporaryDirectory(prefix="magmesh-heading-mesh-") as tmp:
        env = dict(os.environ, MAGMESH_STATE_DIR=str(Path(tmp) / "state"), PYTHONUNBUFFERED="1")
        logs = Path(tmp)
        t0 = time.monotonic()
        try:
            for name in PROCESSES[1:] + PROCESSES[:1]:  # the services first, the car once they are up
                spec = sim if name == "sim-car-1" else specs[name]
                impl = heading_impl if name == "heading-1" else None
                cmd = supervisor.command_for(spec, endpoint, path, impl_override=impl)
                with open(logs / f"{name}.log", "ab") as log:  # the child keeps its own copy of the file
                    procs.append(subprocess.Popen(cmd, cwd=REPO, env=env, stdin=subprocess.DEVNULL, stdout=log,
                                                  stderr=subprocess.STDOUT, start_new_session=True))
                if name == "heading-1":
                    services = [(supervisor.role_of_spec(specs[n]), n) for n in PROCESSES[1:]]
                    if not wait_tokens(router, [keys.svc_token(r, n) for r, n in services], 60.0):
                        raise SystemExit("the mesh heading eval's services did not come up within 60 s: "
                                         + ", ".join(n for _, n in services))
            deadline = time.monotonic() + duration_s / max(speed, 0.1) * 3 + 60.0
            last_report = 0.0
            while time.monotonic() < deadline:
                h = [m for _, m, _ in got["heading"].items[-1:] if isinstance(m, dict)]
                if h and h[-1]["t_s"] >= duration_s - 0.5:
                    break
                for p, name in zip(procs, PROCESSES[1:] + PROCESSES[:1], strict=True):
                    if p.poll() is not None and name != "sim-car-1":
                        tail = (logs / f"{name}.log").read_text(errors="replace")[-1500:]
                        raise SystemExit(f"{name} exited with code {p.returncode} during the drive:\n{tail}")
                if progress and time.monotonic() - last_report > 10:
                    last_report = time.monotonic()
                    print(f"  heading mesh: {h[-1]['t_s'] if h else 0:.0f} of {duration_s:.0f} s of drive",
                          file=sys.stderr)
                time.sleep(0.5)
            time.sleep(1.0)
            wall_s = time.monotonic() - t0
        finally:
            for p in procs:
                if p.poll() is None:
                    try:
                        os.killpg(p.pid, 2)
                    except ProcessLookupError:
                        pass
            for p in procs:
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, 9)
                    p.wait(5)
            router.close()
    if raw is not None:  # the received messages themselves, for a closer look
        raw.update({k: _msgs(v) for k, v in got.items()})
    try:
        r = score(_msgs(got["heading"]), _msgs(got["pose"]), _msgs(got["sources"]), _msgs(got["dmc_alarms"]))
    except ValueError as e:
        raise SystemExit(f"the mesh heading eval could not score the drive after {wall_s:.0f} s: {e}. The services "
                         f"ran, but the drive's messages did not reach the eval's subscriber.") from None
    r.update(duration_s=float(duration_s), speed=float(speed), wall_s=float(wall_s), manifest=str(path),
             heading_impl=heading_impl or supervisor.spec_impl(specs["heading-1"]) or "ekf",
             dmc_impl=supervisor.spec_impl(specs["dmc-1"]),
             layout=sim.settings.get("layout"), seed=sim.settings.get("seed"),
             goal={"rms_deg": GOAL_RMS_DEG, "magnetic_frac_clear": GOAL_MAGNETIC_FRAC_CLEAR,
                   "gyro_within_s": GYRO_WITHIN_S})
    return r


def _msgs(c) -> list[dict]:
    return [m for _, m, _ in list(c.items) if isinstance(m, dict)]


def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{100 * x:.1f} %"


def format_text(r: dict) -> str:
    m = r["meets"]
    mc = r["magnetic_frac_clear"]
    lines = [f"Live mesh — the demo car ({r['layout']}, seed {r['seed']}) through ingest → dmc_detector "
             f"({r['dmc_impl']}) → calibration → heading_fuser ({r['heading_impl']}), {r['duration_s']:.0f} s of "
             f"drive at {r['speed']:g}× ({r['wall_s']:.0f} s wall)",
             f"  heading RMS {r['rms_deg']:.2f}° (p95 {r['p95_deg']:.2f}°, max {r['max_deg']:.1f}°; goal ≤ "
             f"{GOAL_RMS_DEG}°: {'met' if m['rms'] else 'NOT met'})",
             f"  magnetic mode while no source is active: "
             f"{'n/a' if mc is None else f'{100 * mc:.1f} %'} of {100 * (r['clear_frac'] or 0):.0f} % of the drive "
             f"(goal ≥ {100 * GOAL_MAGNETIC_FRAC_CLEAR:.0f} %: {'met' if m['magnetic_clear'] else 'NOT met'}); "
             f"magnetic or recovering {_pct(r['magnetometer_in_use_frac_clear'])}",
             f"  gyro_only within {GYRO_WITHIN_S:g} s of an alarm/dmc raise: {r['gyro_within_1s']} of "
             f"{r['dmc_alarms_raised']} ({'met' if m['gyro_within_1s'] else 'NOT met'})"
             + (f"; late at t = {', '.join(f'{t:.1f}' for t in r['gyro_late_at_t_s'])} s" if r["gyro_late_at_t_s"]
                else ""),
             "  modes: " + ", ".join(f"{k} {100 * v:.1f} %" for k, v in r["mode_frac"].items())]
    return "\n".join(lines)
