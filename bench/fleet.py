"""Load generator for ``magmesh bench mesh``: N vehicles publishing car sensor streams at their default rates.

Values come from one simulated car drive (looped); each vehicle is offset in the drive. ``t_s`` is the wall
clock at publication, so a sink on the same machine reads end-to-end latency as ``now − t_s``.
``--max`` publishes as fast as the mesh takes it instead of at the sensor rates.
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
    args = p.parse_args(argv)

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
        for v in ids:
            kk = (keys.raw_mag(v, "1"), keys.raw_mag(v, "2"), keys.raw_imu(v), keys.raw_gnss(v))
            if args.stream != "raw":
                kk = tuple(k.replace("/raw/", f"/{args.stream}/") for k in kk)
            pubs.append(tuple(s.declare_publisher(k, **opts) for k in kk))
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
                pm1, pm2, pimu, pgnss = pubs[vi]
                sq = seq[vi]
                ki = (tick + vi * 74) % len(gyro)
                pimu.put(pack({"type": "imu", "version": 1, "vehicle": v, "t_s": t_s, "seq": sq[2],
                               "gyro_rad_s": gyro[ki], "accel_m_s2": acc[ki]}))
                sq[2] += 1
                sent["imu"] += 1
                if tick % 2 == 0:
                    pm1.put(pack({"type": "mag", "version": 1, "vehicle": v, "t_s": t_s, "seq": sq[0],
                                  "sensor": "1", "b_nt": mag1[k]}))
                    pm2.put(pack({"type": "mag", "version": 1, "vehicle": v, "t_s": t_s, "seq": sq[1],
                                  "sensor": "2", "b_nt": mag2[k]}))
                    sq[0] += 1
                    sq[1] += 1
                    sent["mag"] += 2
                if tick % 20 == 0:
                    j = (tick // 20 + vi) % len(g.t_s)
                    pgnss.put(pack({"type": "gnss", "version": 1, "vehicle": v, "t_s": t_s, "seq": sq[3],
                                    "lat_deg": float(g.lat_deg[j]), "lon_deg": float(g.lon_deg[j]),
                                    "alt_m": float(g.alt_m[j]), "pos_enu_m": g.pos_enu_m[j].tolist(),
                                    "vel_enu_m_s": g.vel_enu_m_s[j].tolist(), "course_rad": float(g.course_rad[j]),
                                    "speed_m_s": float(g.speed_m_s[j]), "fix_type": str(g.fix_type[j]),
                                    "num_sats": int(g.num_sats[j]), "pdop": float(g.pdop[j])}))
                    sq[3] += 1
                    sent["gnss"] += 1
            tick += 1
        wall = time.time() - t0
    total = sum(sent.values())
    offered = args.vehicles * (100 + 100 + 5)
    json.dump({"sent": sent, "total": total, "wall_s": wall, "rate": total / wall, "offered_rate": offered,
               "epochs_per_vehicle": (tick + 1) // 2, "ticks": tick}, sys.stdout)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
