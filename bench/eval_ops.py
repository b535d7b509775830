"""Recording and replay fidelity: MCAP codec speed, loss and timing of record → replay → record on loopback.

Three measurements:

- ``codec``: write and read rate of the MCAP recording format (msgpack payloads, zstd chunks), pure;
- ``timing``: a synthetic recording (two 100 Hz streams and a 10 Hz one, seeded jitter) replayed at
  ``--rate`` through a Zenoh router on loopback into ``magmesh record`` (a separate process): every
  message must come back, and the receive times must keep the original spacing divided by the rate
  (error percentiles in ms, about the constant end-to-end latency);
- ``burst``: the same with ``--burst`` messages replayed as fast as possible (``--rate max``): messages
  per second end to end, and none lost (reliable publishers with blocking congestion control);
- ``broad`` (``--broad``): every bundled BROAD trial (Laidig et al. 2021, CC-BY-4.0) replayed with
  ``magmesh rerun`` through the demo's BROAD services (quasi-static DMC detector with the manifest's
  settings, heading fuser): heading error against the optical truth, share of magnetic mode, DMC alarms
  against the recording's disturbance truth.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from magmesh_cli import recording as rc
from schemas import keys, messages

REPO = Path(__file__).resolve().parent.parent


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=float, default=10.0, help="length of the timing recording, s")
    p.add_argument("--rate", type=float, default=1.0, help="replay speed factor of the timing run")
    p.add_argument("--burst", type=int, default=20000, help="messages in the as-fast-as-possible run")
    p.add_argument("--codec-n", type=int, default=50000, help="messages in the codec measurement")
    p.add_argument("--no-mesh", action="store_true", help="only the codec measurement")
    p.add_argument("--broad", action="store_true", help="also replay every BROAD trial through the mesh")
    p.add_argument("--broad-dmc-set", nargs="+", default=[], metavar="NAME=VALUE",
                   help="override settings of the manifest's dmc-broad-1 entry for the BROAD run")
    p.add_argument("--seed", type=int, default=1)


def synthetic_recording(path: Path, seconds: float, seed: int, rate_hz=(100.0, 100.0, 10.0),
                        t0_ns: int = 1_800_000_000_000_000_000) -> int:
    """Two magnetometers and a GNSS-like slow stream with ±1 ms receive jitter; returns the message count."""
    rng = np.random.default_rng(seed)
    events = []
    streams = [(keys.raw_mag("eval-1", "1"), "1"), (keys.raw_mag("eval-1", "2"), "2"), (keys.raw_mag("eval-1", "3"), "3")]
    for (key, sensor), hz in zip(streams, rate_hz, strict=False):
        t = np.arange(0.0, seconds, 1.0 / hz)
        jitter = rng.uniform(0.0, 1e-3, len(t))
        for i, ti in enumerate(t):
            events.append((int(t0_ns + (ti + jitter[i]) * 1e9), key, sensor, float(ti), i))
    events.sort()
    with rc.RecordingWriter(path) as w:
        for recv, key, sensor, ti, i in events:
            b = rng.normal(0.0, 20000.0, 3).tolist()
            w.write_message(key, messages.make("mag", "eval-1", ti, i, sensor=sensor, b_nt=b), recv)
    return len(events)


def measure_codec(n: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "codec.mcap"
        payloads = [messages.encode(messages.make("mag", "eval-1", i * 0.01, i, sensor="1",
                                                  b_nt=rng.normal(0, 20000, 3).tolist())) for i in range(n)]
        key = keys.raw_mag("eval-1", "1")
        t0 = time.perf_counter()
        with rc.RecordingWriter(path) as w:
            for i, p in enumerate(payloads):
                w.write(key, p, 1_000_000_000 + i * 10_000_000)
        t_write = time.perf_counter() - t0
        size = path.stat().st_size
        t0 = time.perf_counter()
        m = sum(1 for _ in rc.read_records(path))
        t_read = time.perf_counter() - t0
        t0 = time.perf_counter()
        decoded = len(rc.load_messages(path))
        t_decode = time.perf_counter() - t0
    return {
        "messages": n,
        "read_back": m,
        "decoded": decoded,
        "write_msgs_per_s": n / t_write,
        "read_msgs_per_s": m / t_read,
        "read_decode_msgs_per_s": decoded / t_decode,
        "bytes_per_message": size / n,
        "payload_bytes_per_message": float(np.mean([len(p) for p in payloads])),
    }


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _round_trip(src: Path, out: Path, endpoint: str, rate: float) -> tuple[dict, float]:
    """Replay ``src`` at ``rate`` into a ``magmesh record`` process; return (replay stats, wall seconds)."""
    from magmesh.zconf import build_config
    from magmesh_cli.commands.replay import replay_to_mesh

    env = {**os.environ, "PYTHONPATH": str(REPO)}
    rec = subprocess.Popen([sys.executable, "-m", "magmesh", "record", "-o", str(out), "--connect", endpoint, "-q",
                            "--no-liveliness"], cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        time.sleep(2.5)  # recorder up and subscribed
        t0 = time.monotonic()
        stats = replay_to_mesh(build_config(connect=[endpoint]), src, rate=rate, wait_subscribers_s=5.0)
        wall = time.monotonic() - t0
        time.sleep(1.0)
    finally:
        rec.send_signal(signal.SIGINT)
        try:
            rec.wait(timeout=20)
        except subprocess.TimeoutExpired:
            rec.kill()
    if rec.returncode != 0:
        raise RuntimeError(f"magmesh record failed: {rec.stderr.read().decode()[-1000:]}")
    return stats.as_dict(), wall


def measure_mesh(seconds: float, rate: float, burst: int, seed: int) -> dict:
    import zenoh

    from magmesh.zconf import build_config

    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    router = zenoh.open(build_config(mode="router", listen=[endpoint]))
    try:
        with tempfile.TemporaryDirectory() as d:
            d = Path(d)
            # -- timing at the given rate -------------------------------------------------------
            src = d / "timing_src.mcap"
            n = synthetic_recording(src, seconds, seed)
            stats, _ = _round_trip(src, d / "timing_out.mcap", endpoint, rate)
            orig = {(r.key, r.decode()["seq"]): r.receive_ns for r in rc.read_records(src)}
            back = {(r.key, r.decode()["seq"]): r.receive_ns for r in rc.read_records(d / "timing_out.mcap")}
            common = sorted(set(orig) & set(back), key=orig.get)
            o = np.array([orig[k] for k in common], float)
            b = np.array([back[k] for k in common], float)
            # receive time minus the scheduled time, up to the constant end-to-end latency (median)
            lag = (b - b[0]) - (o - o[0]) / rate
            err_ms = np.abs(lag - np.median(lag)) / 1e6
            timing = {
                "rate": rate,
                "recorded_s": seconds,
                "messages": n,
                "published": stats["published"],
                "received": len(back),
                "lost": n - len(common),
                "error_ms_p50": float(np.percentile(err_ms, 50)),
                "error_ms_p99": float(np.percentile(err_ms, 99)),
                "error_ms_max": float(err_ms.max()),
                "max_late_s": stats["max_late_s"],
            }
            # -- as fast as possible ---------------------------------------------------------------
            src = d / "burst_src.mcap"
            with rc.RecordingWriter(src) as w:
                for i in range(burst):
                    w.write_message(keys.raw_mag("eval-1", "1"),
                                    messages.make("mag", "eval-1", i * 0.001, i, sensor="1", b_nt=[1.0, 2.0, 3.0]),
                                    1_000_000_000 + i * 1_000_000)
            stats, wall = _round_trip(src, d / "burst_out.mcap", endpoint, 0.0)
            got = rc.summarize(d / "burst_out.mcap")["messages"]
            burst_res = {
                "messages": burst,
                "published": stats["published"],
                "received": got,
                "lost": burst - got,
                "replay_wall_s": stats["wall_s"],
                "msgs_per_s": burst / stats["wall_s"] if stats["wall_s"] > 0 else 0.0,
            }
    finally:
        router.close()
    return {"timing": timing, "burst": burst_res}


def broad_clean_recording(trial: str, path: Path, rate_hz: float = 50.0) -> int:
    """A BROAD trial as ingest would publish it (clean keys, truth), for ``magmesh rerun``."""
    from sim_publishers.replay import core

    rec = core.load(f"broad:{trial}", rate_hz=rate_hz)
    seq: dict[str, int] = {}
    with rc.RecordingWriter(path) as w:
        for t, key, mtype, fields in core.stream(rec, "broad-1"):
            key = keys.raw_to_clean(key) if keys.parse(key).kind == "raw" else key
            n = seq.get(key, 0)
            seq[key] = n + 1
            w.write_message(key, messages.make(mtype, "broad-1", t, n, **fields), int(1.8e18 + t * 1e9))
    return sum(seq.values())


def measure_broad(progress: bool = True, dmc_overrides: dict | None = None) -> list[dict]:
    import tomllib

    from magmesh.paths import DEPLOY_DIR
    from magmesh_cli.commands.rerun import rerun
    from magmesh_cli.report.data import group
    from magmesh_cli.report.summary import vehicle_summary
    from sim_publishers.replay.core import broad_trials

    manifest = DEPLOY_DIR / "mesh.toml"
    with open(manifest, "rb") as f:
        procs = {p["name"]: p for p in tomllib.load(f).get("process", [])}
    dmc = procs["dmc-broad-1"]
    settings = {**dmc.get("settings", {}), **(dmc_overrides or {})}
    dmc_cmd = " ".join(["services.dmc_detector", *dmc.get("args", []),
                        *[f"--set {k}={v}" for k, v in settings.items()]])
    rows = []
    trials = broad_trials()
    if progress:
        from tqdm import tqdm

        trials = tqdm(trials, desc="BROAD trials", unit="trial", file=sys.stderr)
    for trial in trials:
        with tempfile.TemporaryDirectory() as d:
            src, out = Path(d) / "clean.mcap", Path(d) / "out.mcap"
            broad_clean_recording(trial, src)
            res = rerun(src, [dmc_cmd, "services.heading_fuser"], out, manifest=manifest)
            msgs = rc.load_messages(src, [keys.truth("*", "*")]) + rc.load_messages(out)
        s = vehicle_summary(group(msgs)["broad-1"])
        h, a = s["heading"] or {}, s["alarms_vs_truth"] or {}
        rows.append({
            "trial": trial,
            "replayed": res["replay"]["published"],
            "heading_msgs": (h or {}).get("epochs", 0),
            "heading_rms_deg": h.get("rms_deg"),
            "heading_p95_deg": h.get("p95_deg"),
            "magnetic_mode_frac": (h.get("mode_frac") or {}).get("magnetic", 0.0),
            "dmc_alarms": s["alarms"].get("dmc", 0),
            "disturbed_episodes": a.get("episodes"),
            "episodes_alarmed": a.get("detected"),
            "median_alarm_delay_s": a.get("median_delay_s"),
            "alarms_outside_disturbance": a.get("false_alarms"),
        })
    return rows


def run(args: argparse.Namespace) -> dict:
    out = {"codec": measure_codec(args.codec_n, args.seed)}
    if not args.no_mesh:
        out.update(measure_mesh(args.seconds, args.rate, args.burst, args.seed))
    if getattr(args, "broad", False):
        overrides = dict(kv.split("=", 1) for kv in args.broad_dmc_set)
        out["broad"] = measure_broad(dmc_overrides=overrides)
        out["broad_dmc_overrides"] = overrides
    return out


def format_text(r: dict) -> str:
    c = r["codec"]
    lines = [
        "MCAP recording format (msgpack payloads, zstd chunks)",
        f"  write {c['write_msgs_per_s']:,.0f} msg/s, read {c['read_msgs_per_s']:,.0f} msg/s, "
        f"read+decode+validate {c['read_decode_msgs_per_s']:,.0f} msg/s",
        f"  {c['bytes_per_message']:.1f} bytes per message in the file ({c['payload_bytes_per_message']:.0f} payload)",
    ]
    if "timing" in r:
        t = r["timing"]
        lines += [
            f"replay at {t['rate']:g}× → router → magmesh record ({t['recorded_s']:g} s, {t['messages']} messages)",
            f"  received {t['received']} of {t['messages']} (lost {t['lost']})",
            f"  spacing error vs original: p50 {t['error_ms_p50']:.2f} ms, p99 {t['error_ms_p99']:.2f} ms, "
            f"max {t['error_ms_max']:.2f} ms",
        ]
        b = r["burst"]
        lines += [
            f"replay as fast as possible ({b['messages']} messages)",
            f"  {b['msgs_per_s']:,.0f} msg/s end to end, received {b['received']} (lost {b['lost']})",
        ]
    if "broad" in r:
        lines += ["BROAD trials through the mesh (rerun: quasi-static DMC + heading fuser; Laidig et al. 2021)",
                  f"  {'trial':<36} {'heading RMS':>11} {'p95':>6} {'magnetic':>8} {'alarms':>6} "
                  f"{'episodes alarmed':>16} {'delay':>6} {'outside':>7}"]
        for row in r["broad"]:
            def f(v, fmt):
                return format(v, fmt) if v is not None else "–"
            lines.append(f"  {row['trial']:<36} {f(row['heading_rms_deg'], '10.1f')}° {f(row['heading_p95_deg'], '5.1f')}° "
                         f"{100 * row['magnetic_mode_frac']:7.0f}% {row['dmc_alarms']:6d} "
                         f"{f(row['episodes_alarmed'], 'd'):>7} of {f(row['disturbed_episodes'], 'd'):<5} "
                         f"{f(row['median_alarm_delay_s'], '5.1f'):>5}s {f(row['alarms_outside_disturbance'], 'd'):>7}")
    return "\n".join(lines)
