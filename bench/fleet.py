"""Load generator for ``magmesh bench mesh``: N vehicles publishing car sensor streams at their default rates.

Values come from one simulated car drive (looped); each vehicle is offset in the drive. ``t_s`` is the wall
clock at publication, so a sink on the same machine reads end-to-end latency as ``now − t_s``.
``--max`` publishes as fast as the mesh takes it instead of at the sensor rates.

``--wire v1`` publishes every sample alone on its ``raw/`` key (contract v1, what most clients send);
``--wire v2`` publishes, as a vehicle's on-board agent would, one ``raw/batch`` per vehicle per ``--window``
seconds holding that window's samples of all its streams (contract v2). Both carry the same samples with the
same ``t_s`` (the wall time at which each sample was taken) and per-stream ``seq``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

import msgpack

#: how long the fleet keeps its session open after its last put: closing it at once drops what its transmit
#: queue still holds (as fast as possible, about 2 % of the samples)
FLUSH_S = 2.0


def vehicle_ids(n: int, first: int = 0) -> list[str]:
    return [f"bench-{i:04d}" for i in range(first, first + n)]


def load_drive(duration_s: float = 60.0):
    from sim_publishers.car.core import CarSimSettings, simulate

    return simulate(CarSimSettings(layout="urban_a", seed=5, duration_s=duration_s))


def window_ticks(window_s: float) -> int:
    """10 ms ticks per v2 window: an even number, so a window holds whole magnetometer epochs."""
    w = max(2, round(window_s / 0.01))
    return w + w % 2


def _publish_v2_windows(s, args, ids: list[str], d, opts, start_at: float) -> tuple[dict, float, int, Any]:
    """Contract v2 at fleet scale: per window, one batch per vehicle holding its streams' samples of that window.

    Sample times are the grid ``start_at + tick × 10 ms`` (IMU every tick, magnetometers every second, GNSS every
    20th); the batch of window ``w`` (ticks ``w·W … w·W + W − 1``) is put once the wall clock has reached its last
    sample's time, so a sample's *raw publish* time is known to the sink from its ``t_s`` alone
    (:func:`publish_time`). Each vehicle replays the drive from its own offset. Returns (sent per stream, wall
    time, windows, put log): the log (paced runs; else None) holds each batch's put, s after that time, windows ×
    vehicles — the sink measures latency from the moment a batch really went out, not from when it was due."""
    import msgspec
    import numpy as np
    import zenoh

    from schemas import keys, streams

    enc = msgspec.msgpack.Encoder().encode
    binary = args.wire == "v3"
    W = window_ticks(args.window)
    if binary:  # the drive as little-endian bytes, sliced per vehicle and window (contract v2's binary form)
        mag1, mag2 = (np.ascontiguousarray(d.mag_b_nt[s], "<f8").tobytes() for s in ("1", "2"))
        gyro, acc = (np.ascontiguousarray(x, "<f8").tobytes() for x in (d.gyro_rad_s, d.accel_m_s2))
    else:
        mag1, mag2 = d.mag_b_nt["1"].tolist(), d.mag_b_nt["2"].tolist()
        gyro, acc = d.gyro_rad_s.tolist(), d.accel_m_s2.tolist()
    g = d.gnss
    gn = [{"lat_deg": float(g.lat_deg[j]), "lon_deg": float(g.lon_deg[j]), "alt_m": float(g.alt_m[j]),
           "pos_enu_m": g.pos_enu_m[j].tolist(), "vel_enu_m_s": g.vel_enu_m_s[j].tolist(),
           "course_rad": float(g.course_rad[j]), "speed_m_s": float(g.speed_m_s[j]), "fix_type": str(g.fix_type[j]),
           "num_sats": int(g.num_sats[j]), "pdop": float(g.pdop[j])} for j in range(len(g.t_s))]
    n_mag, n_imu, n_g = len(d.mag_b_nt["1"]), len(d.gyro_rad_s), len(gn)
    bk = [keys.raw_batch(v).replace("/raw/", f"/{args.stream}/") for v in ids]
    enc_name = streams.encoding_name("batch", 3 if binary else 2)
    pubs = [s.declare_publisher(k, encoding=zenoh.Encoding(enc_name), **opts) for k in bk]
    time.sleep(1.0)  # let declarations settle
    while time.time() < start_at:
        time.sleep(0.005)
    sent = {"mag": 0, "imu": 0, "gnss": 0}
    t_wall0 = time.time()
    w = 0
    put_log = None if args.max else np.full((int(args.duration / (W * 0.01)) + 2, len(ids)), np.nan, np.float32)
    while True:
        tick0 = w * W
        t_last = start_at + (tick0 + W - 1) * 0.01
        if args.max:
            if time.time() - t_wall0 >= args.duration:
                break
        else:
            if tick0 * 0.01 >= args.duration:
                break
            delay = t_last - time.time()
            if delay > 0:
                time.sleep(delay)
        ticks = list(range(tick0, tick0 + W))
        t_imu = [start_at + k * 0.01 for k in ticks]
        mticks = [k for k in ticks if k % 2 == 0]
        t_mag = [start_at + k * 0.01 for k in mticks]
        s_mag = [k // 2 for k in mticks]
        gticks = [k for k in ticks if k % 20 == 0]
        nm = len(mticks)
        if binary:
            t_imu, t_mag = (np.asarray(x, "<f8").tobytes() for x in (t_imu, t_mag))
            s_imu, s_mag = (np.asarray(x, "<i8").tobytes() for x in (ticks, s_mag))
        else:
            s_imu = ticks
        for vi in range(len(ids)):
            o_imu = (tick0 + vi * 74) % n_imu
            o_mag = (tick0 // 2 + vi * 37) % n_mag
            if o_imu + W > n_imu:
                o_imu = 0  # (the drive loops: a window never straddles its end)
            if o_mag + nm > n_mag:
                o_mag = 0
            if binary:
                gy, ac = gyro[o_imu * 24:(o_imu + W) * 24], acc[o_imu * 24:(o_imu + W) * 24]
                m1, m2 = mag1[o_mag * 24:(o_mag + nm) * 24], mag2[o_mag * 24:(o_mag + nm) * 24]
            else:
                gy, ac = gyro[o_imu:o_imu + W], acc[o_imu:o_imu + W]
                m1, m2 = mag1[o_mag:o_mag + nm], mag2[o_mag:o_mag + nm]
            st = {"mag/1": {"n": nm, "t_s": t_mag, "seq": s_mag, "cols": {"sensor": "1", "b_nt": m1}},
                  "mag/2": {"n": nm, "t_s": t_mag, "seq": s_mag, "cols": {"sensor": "2", "b_nt": m2}},
                  "imu": {"n": W, "t_s": t_imu, "seq": s_imu, "cols": {"gyro_rad_s": gy, "accel_m_s2": ac}}}
            if gticks:
                rows = [gn[(k // 20 + vi) % n_g] for k in gticks]
                gt, gs = [start_at + k * 0.01 for k in gticks], [k // 20 for k in gticks]
                gcols = {f: [r[f] for r in rows] for f in rows[0]}
                if binary:
                    gt, gs = np.asarray(gt, "<f8").tobytes(), np.asarray(gs, "<i8").tobytes()
                    gcols = {f: (v if f == "fix_type" else np.asarray(v, "<i8" if f == "num_sats" else "<f8").tobytes())
                             for f, v in gcols.items()}
                st["gnss"] = {"n": len(gticks), "t_s": gt, "seq": gs, "cols": gcols}
            pubs[vi].put(enc({"type": "batch", "version": 3 if binary else 2, "vehicle": ids[vi], "t_s": t_last,
                              "seq": w, "streams": st}))
            if put_log is not None and w < put_log.shape[0]:
                put_log[w, vi] = time.time() - t_last
        sent["imu"] += W * len(ids)
        sent["mag"] += 2 * len(mticks) * len(ids)
        sent["gnss"] += len(gticks) * len(ids)
        w += 1
    return sent, time.time() - t_wall0, w, None if put_log is None else put_log[:w]


def window_index(t_s, start_at: float, window_s: float):
    """The v2 fleet's window holding a sample of time ``t_s`` (arrays welcome): its ``seq``, a row of the put log."""
    import numpy as np

    return np.floor(np.rint((np.asarray(t_s, float) - start_at) / 0.01) / window_ticks(window_s)).astype(np.int64)


def publish_time(t_s, start_at: float, window_s: float):
    """When the v2 fleet was due to put the batch holding a sample of time ``t_s`` (arrays welcome): its window's
    last tick (when it really put it: that plus the put log's entry)."""
    W = window_ticks(window_s)
    return start_at + (window_index(t_s, start_at, window_s) * W + W - 1) * 0.01


def main(argv: list[str] | None = None) -> int:
    import zenoh

    from magmesh import zconf
    from schemas import keys

    p = argparse.ArgumentParser(description=__doc__)
    zconf.add_zenoh_args(p)
    p.add_argument("--vehicles", type=int, default=10)
    p.add_argument("--first", type=int, default=0, help="number of the first vehicle (bench-NNNN)")
    p.add_argument("--duration", type=float, default=10.0, help="seconds of publishing")
    p.add_argument("--max", action="store_true", help="as fast as possible instead of real-time rates")
    p.add_argument("--stream", default="raw", help="key stream to publish on (raw)")
    p.add_argument("--start-at", type=float, default=0.0, help="wall time to start at (time.time())")
    p.add_argument("--wire", choices=("v1", "v2", "v3"), default="v1",
                   help="single samples (v1), batches with list columns (v2) or with binary columns (v3)")
    p.add_argument("--window", type=float, default=0.02, help="v2: seconds of samples per vehicle batch")
    p.add_argument("--put-log", default=None,
                   help="v2, paced: save each batch's put time (s after its window's last sample; windows × vehicles, "
                        ".npy) here")
    args = p.parse_args(argv)
    from schemas import streams

    v2 = args.wire in ("v2", "v3")
    d = load_drive()
    ids = vehicle_ids(args.vehicles, args.first)
    opts = dict(congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)
    if v2:
        start_at = args.start_at or time.time() + 1.5
        with zenoh.open(zconf.config_from_args(args)) as s:
            sent, wall, windows, put_log = _publish_v2_windows(s, args, ids, d, opts, start_at)
            time.sleep(FLUSH_S)
        total = sum(sent.values())
        last = None  # how late each window's last batch went out: the fleet's own lag
        if put_log is not None and put_log.size:
            import numpy as np

            if args.put_log:
                np.save(args.put_log, put_log)
            q = np.percentile(put_log.max(axis=1), [50, 99]) * 1000
            last = {"p50": round(float(q[0]), 2), "p99": round(float(q[1]), 2)}
        json.dump({"sent": sent, "total": total, "wall_s": wall, "rate": total / wall,
                   "offered_rate": args.vehicles * 205, "windows": windows, "start_at": start_at,
                   "last_put_lag_ms": last}, sys.stdout)
        print()
        return 0
    n_mag = len(d.t_mag_s)
    mag1, mag2 = d.mag_b_nt["1"].tolist(), d.mag_b_nt["2"].tolist()
    gyro, acc = d.gyro_rad_s.tolist(), d.accel_m_s2.tolist()
    g = d.gnss
    pack = msgpack.Packer(use_bin_type=True).pack
    with zenoh.open(zconf.config_from_args(args)) as s:
        pubs = []
        for v in ids:
            kk = (keys.raw_mag(v, "1"), keys.raw_mag(v, "2"), keys.raw_imu(v), keys.raw_gnss(v))
            if args.stream != "raw":
                kk = tuple(k.replace("/raw/", f"/{args.stream}/") for k in kk)
            pubs.append(tuple(s.declare_publisher(k, encoding=zenoh.Encoding(streams.encoding_name(
                "mag" if "/mag/" in k else k.rsplit("/", 1)[1])), **opts) for k in kk))
        time.sleep(1.0)  # let declarations settle
        while time.time() < args.start_at:
            time.sleep(0.01)
        sent = {"mag": 0, "imu": 0, "gnss": 0}
        seq = [[0, 0, 0, 0] for _ in ids]
        t0 = time.time()
        tick = 0  # 100 Hz ticks
        offered_period = 0.01
        while True:
            now = time.time()
            if now - t0 >= args.duration:
                break
            if not args.max:
                due = t0 + tick * offered_period
                if due > now:
                    time.sleep(due - now)
            for vi, v in enumerate(ids):
                t_s = time.time() if not args.max else tick * offered_period + 1.0
                k = (tick // 2 + vi * 37) % n_mag
                sq = seq[vi]
                ki = (tick + vi * 74) % len(gyro)
                pubs[vi][2].put(pack({"type": "imu", "version": 1, "vehicle": v, "t_s": t_s, "seq": sq[2],
                                      "gyro_rad_s": gyro[ki], "accel_m_s2": acc[ki]}))
                sq[2] += 1
                sent["imu"] += 1
                if tick % 2 == 0:
                    pubs[vi][0].put(pack({"type": "mag", "version": 1, "vehicle": v, "t_s": t_s, "seq": sq[0],
                                          "sensor": "1", "b_nt": mag1[k]}))
                    pubs[vi][1].put(pack({"type": "mag", "version": 1, "vehicle": v, "t_s": t_s, "seq": sq[1],
                                          "sensor": "2", "b_nt": mag2[k]}))
                    sq[0] += 1
                    sq[1] += 1
                    sent["mag"] += 2
                if tick % 20 == 0:
                    j = (tick // 20 + vi) % len(g.t_s)
                    pubs[vi][3].put(pack({"type": "gnss", "version": 1, "vehicle": v, "t_s": t_s, "seq": sq[3],
                                          "lat_deg": float(g.lat_deg[j]), "lon_deg": float(g.lon_deg[j]),
                                          "alt_m": float(g.alt_m[j]), "pos_enu_m": g.pos_enu_m[j].tolist(),
                                          "vel_enu_m_s": g.vel_enu_m_s[j].tolist(),
                                          "course_rad": float(g.course_rad[j]), "speed_m_s": float(g.speed_m_s[j]),
                                          "fix_type": str(g.fix_type[j]), "num_sats": int(g.num_sats[j]),
                                          "pdop": float(g.pdop[j])}))
                    sq[3] += 1
                    sent["gnss"] += 1
            tick += 1
        wall = time.time() - t0
        time.sleep(FLUSH_S)
    total = sum(sent.values())
    offered = args.vehicles * (100 + 100 + 5)
    json.dump({"sent": sent, "total": total, "wall_s": wall, "rate": total / wall, "offered_rate": offered,
               "epochs_per_vehicle": (tick + 1) // 2, "ticks": tick}, sys.stdout)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
