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

import msgpack


def vehicle_ids(n: int) -> list[str]:
    return [f"bench-{i:04d}" for i in range(n)]


def load_drive(duration_s: float = 60.0):
    from sim_publishers.car.core import CarSimSettings, simulate

    return simulate(CarSimSettings(layout="urban_a", seed=5, duration_s=duration_s))


_HEADER = ("type", "version", "vehicle", "t_s", "seq")


def _batch(vehicle: str, seq: int, pending: dict[str, list[dict]]) -> dict:
    """One v2 batch (schemas/batch.py) of a vehicle's pending samples, stream by stream, as columns."""
    streams = {}
    t_max = 0.0
    for name, msgs in pending.items():
        if not msgs:
            continue
        cols = {f: [m[f] for m in msgs] for f in msgs[0] if f not in _HEADER}
        if "sensor" in cols:
            cols["sensor"] = cols["sensor"][0]
        t = [m["t_s"] for m in msgs]
        t_max = max(t_max, t[-1])
        streams[name] = {"n": len(msgs), "t_s": t, "seq": [m["seq"] for m in msgs], "cols": cols}
    return {"type": "batch", "version": 2, "vehicle": vehicle, "t_s": t_max, "seq": seq, "streams": streams}


def main(argv: list[str] | None = None) -> int:
    import zenoh

    from magmesh import zconf
    from schemas import keys

    p = argparse.ArgumentParser(description=__doc__)
    zconf.add_zenoh_args(p)
    p.add_argument("--vehicles", type=int, default=10)
    p.add_argument("--duration", type=float, default=10.0, help="seconds of publishing")
    p.add_argument("--max", action="store_true", help="as fast as possible instead of real-time rates")
    p.add_argument("--stream", default="raw", help="key stream to publish on (raw)")
    p.add_argument("--start-at", type=float, default=0.0, help="wall time to start at (time.time())")
    p.add_argument("--wire", choices=("v1", "v2"), default="v1", help="single samples (v1) or batches (v2)")
    p.add_argument("--window", type=float, default=0.02, help="v2: seconds of samples per vehicle batch")
    args = p.parse_args(argv)
    import msgspec

    from schemas import streams

    v2 = args.wire == "v2"
    window_ticks = max(1, round(args.window / 0.01))
    enc = msgspec.msgpack.Encoder().encode

    d = load_drive()
    ids = vehicle_ids(args.vehicles)
    n_mag = len(d.t_mag_s)
    mag1, mag2 = d.mag_b_nt["1"].tolist(), d.mag_b_nt["2"].tolist()
    gyro, acc = d.gyro_rad_s.tolist(), d.accel_m_s2.tolist()
    g = d.gnss
    pack = msgpack.Packer(use_bin_type=True).pack
    with zenoh.open(zconf.config_from_args(args)) as s:
        opts = dict(congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)
        pubs = []
        bpubs = []
        for v in ids:
            kk = (keys.raw_mag(v, "1"), keys.raw_mag(v, "2"), keys.raw_imu(v), keys.raw_gnss(v))
            if args.stream != "raw":
                kk = tuple(k.replace("/raw/", f"/{args.stream}/") for k in kk)
            if v2:
                bk = keys.raw_batch(v).replace("/raw/", f"/{args.stream}/")
                bpubs.append(s.declare_publisher(bk, encoding=zenoh.Encoding(streams.encoding_name("batch")), **opts))
                continue
            pubs.append(tuple(s.declare_publisher(k, encoding=zenoh.Encoding(streams.encoding_name(
                "mag" if "/mag/" in k else k.rsplit("/", 1)[1])), **opts) for k in kk))
        time.sleep(1.0)  # let declarations settle
        while time.time() < args.start_at:
            time.sleep(0.01)
        sent = {"mag": 0, "imu": 0, "gnss": 0}
        seq = [[0, 0, 0, 0] for _ in ids]
        pend = [{"mag/1": [], "mag/2": [], "imu": [], "gnss": []} for _ in ids]
        bseq = [0] * len(ids)
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
                out = pend[vi] if v2 else None
                imu = {"type": "imu", "version": 1, "vehicle": v, "t_s": t_s, "seq": sq[2],
                       "gyro_rad_s": gyro[ki], "accel_m_s2": acc[ki]}
                if v2:
                    out["imu"].append(imu)
                else:
                    pubs[vi][2].put(pack(imu))
                sq[2] += 1
                sent["imu"] += 1
                if tick % 2 == 0:
                    m1 = {"type": "mag", "version": 1, "vehicle": v, "t_s": t_s, "seq": sq[0], "sensor": "1",
                          "b_nt": mag1[k]}
                    m2 = {"type": "mag", "version": 1, "vehicle": v, "t_s": t_s, "seq": sq[1], "sensor": "2",
                          "b_nt": mag2[k]}
                    if v2:
                        out["mag/1"].append(m1)
                        out["mag/2"].append(m2)
                    else:
                        pubs[vi][0].put(pack(m1))
                        pubs[vi][1].put(pack(m2))
                    sq[0] += 1
                    sq[1] += 1
                    sent["mag"] += 2
                if tick % 20 == 0:
                    j = (tick // 20 + vi) % len(g.t_s)
                    gm = {"type": "gnss", "version": 1, "vehicle": v, "t_s": t_s, "seq": sq[3],
                          "lat_deg": float(g.lat_deg[j]), "lon_deg": float(g.lon_deg[j]),
                          "alt_m": float(g.alt_m[j]), "pos_enu_m": g.pos_enu_m[j].tolist(),
                          "vel_enu_m_s": g.vel_enu_m_s[j].tolist(), "course_rad": float(g.course_rad[j]),
                          "speed_m_s": float(g.speed_m_s[j]), "fix_type": str(g.fix_type[j]),
                          "num_sats": int(g.num_sats[j]), "pdop": float(g.pdop[j])}
                    if v2:
                        out["gnss"].append(gm)
                    else:
                        pubs[vi][3].put(pack(gm))
                    sq[3] += 1
                    sent["gnss"] += 1
                if v2 and (tick + 1) % window_ticks == 0:
                    bpubs[vi].put(enc(_batch(v, bseq[vi], out)))
                    bseq[vi] += 1
                    pend[vi] = {"mag/1": [], "mag/2": [], "imu": [], "gnss": []}
            tick += 1
        if v2:  # the last partial window
            for vi, v in enumerate(ids):
                if any(pend[vi].values()):
                    bpubs[vi].put(enc(_batch(v, bseq[vi], pend[vi])))
        wall = time.time() - t0
    total = sum(sent.values())
    offered = args.vehicles * (100 + 100 + 5)
    json.dump({"sent": sent, "total": total, "wall_s": wall, "rate": total / wall, "offered_rate": offered,
               "epochs_per_vehicle": (tick + 1) // 2, "ticks": tick}, sys.stdout)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
