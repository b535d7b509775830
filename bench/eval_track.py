"""Track monitor evaluation: the paper's two alarm-time tables and undisturbed flights (docs/methods.md#track).

Seeded multirotor flights (``sim_publishers.multirotor.core``): 5 fast-ramp (+0.06 G/s) and 5 slow-ramp
(+0.0125 G/s) flights with the onsets of the paper's Tables 1–2, plus undisturbed flights. Each flight's
streams are replayed through the track monitor core exactly as the service receives them (route, 10 Hz
GNSS, 50 Hz attitude with the magnetometer heading). Reported per detector: alarm delay after onset and
false alarms (raises before the onset, or at any time on undisturbed flights).

Detectors: ``threshold`` = the paper's |ψ_mag − ψ_att| > 5σ per sample (σ = std on undisturbed flight);
``track`` = cross-track deviation > 1 m on RTK GNSS (paper eq. 6); ``innovation`` = the robust
heading-innovation test (median gate + CUSUM); ``combined`` = the ``mag_anomaly`` verdict (earliest of
track and innovation).

``magmesh eval track [--json]``.
"""

from __future__ import annotations

import math
import time

import numpy as np

from services.track_monitor.core import TrackMonitor, TrackMonitorSettings, learn_sigmas
from sim_publishers.multirotor.core import Flight, MultirotorSettings, simulate

#: the paper's flight tests (Tables 1 and 2): onset, threshold alarm, track ("behaviour") alarm, s
PAPER_FAST = {"onset_s": (60.79, 56.29, 59.51, 57.26, 59.13),
              "threshold_s": (63.23, 60.22, 63.10, 61.10, 61.64),
              "track_s": (76.33, 67.76, 71.32, 70.11, 66.23)}
PAPER_SLOW = {"onset_s": (56.39, 61.96, 56.70, 60.20, 59.06),
              "threshold_s": (91.21, 99.27, 101.25, 110.34, 93.21),
              "track_s": (60.99, 66.27, 67.80, 66.71, 65.10)}
GOALS = {"fast_s": 3.0, "slow_s": 5.0, "false_alarms": 0}
DETECTORS = ("threshold", "track", "innovation", "combined")


def replay(flight: Flight, monitor: TrackMonitor) -> list:
    """Feed a flight's streams to a monitor in time order; return every alarm transition."""
    s = flight.settings
    monitor.set_route(s.a_enu_m, s.b_enu_m, f"leg-{s.seed}")
    events = []
    gi = 0
    gidx = flight.gnss_idx
    t = flight.t_s
    att = flight.att_heading_rad
    magh = flight.mag_heading_rad
    for k in range(len(t)):
        if gi < len(gidx) and gidx[gi] == k:
            events += monitor.update_gnss(float(t[k]), flight.gnss_pos_enu_m[gi], flight.gnss_vel_enu_m_s[gi],
                                          "rtk_fixed", 18, 1.3, s.gnss_noise_m)
            gi += 1
        events += monitor.update_mag(float(t[k]), flight.mag_nt[k])
        events += monitor.update_attitude(float(t[k]), float(att[k]), float(magh[k]))
    return events


def train_sigmas(flights: list[Flight], settings: TrackMonitorSettings) -> dict:
    """σ of the heading innovation pooled over undisturbed training flights (the paper's "σ estimated from
    undisturbed flight"), learned exactly as the service learns it online."""
    samples = []
    learner = settings.replace(learn_s=1e9, innovation_sigma_rad=0.0, median_sigma_rad=0.0, block_sigma_rad=0.0)
    for f in flights:
        m = TrackMonitor(learner)
        replay(f, m)
        samples += m.innovation.learning_samples
    return learn_sigmas(samples, learner)


def _first_raise(events: list, source: str, after_s: float) -> float | None:
    for ev in events:
        if ev.source == source and ev.state == "raised" and ev.t_s >= after_s:
            return ev.t_s
    return None


def _raises(events: list, source: str, before_s: float = math.inf) -> int:
    return sum(1 for ev in events if ev.source == source and ev.state == "raised" and ev.t_s < before_s)


def fly(sim: MultirotorSettings, robust: TrackMonitorSettings, paper: TrackMonitorSettings) -> dict:
    """One flight through both monitors: alarm times and false alarms per detector."""
    flight = simulate(sim)
    ev_r = replay(flight, TrackMonitor(robust))
    ev_p = replay(flight, TrackMonitor(paper))
    onset = sim.onset_s if sim.disturbance != "none" else math.inf
    per = {"threshold": (ev_p, "heading_innovation"), "track": (ev_r, "track"),
           "innovation": (ev_r, "heading_innovation"), "combined": (ev_r, "mag_anomaly")}
    out = {"seed": sim.seed, "onset_s": None if onset == math.inf else onset, "alarm_s": {}, "delay_s": {},
           "false_alarms": {}}
    for name, (evs, src) in per.items():
        t_alarm = _first_raise(evs, src, onset) if onset < math.inf else None
        out["alarm_s"][name] = t_alarm
        out["delay_s"][name] = None if t_alarm is None else round(t_alarm - onset, 3)
        out["false_alarms"][name] = _raises(evs, src, onset)
    xt = np.abs(flight.true_cross_track_m())
    after = flight.t_s > (onset if onset < math.inf else 10.0)
    out["max_cross_track_m"] = float(xt[after].max()) if after.any() else 0.0
    return out


def add_arguments(parser) -> None:
    parser.add_argument("--undisturbed", type=int, default=20, help="number of undisturbed flights (default 20)")
    parser.add_argument("--undisturbed-duration", type=float, default=150.0,
                        help="length of each undisturbed flight, s (default 150)")
    parser.add_argument("--after-onset", type=float, default=60.0,
                        help="disturbed flights continue this long after the onset, s (default 60)")
    parser.add_argument("--flights", type=int, default=5, help="disturbed flights per table (default 5, max 5)")
    parser.add_argument("--train", type=int, default=5,
                        help="undisturbed training flights σ is learned from (default 5; 0: learn online per flight)")
    parser.add_argument("--seed", type=int, default=7, help="base seed of every flight")


def _stats(values: list) -> dict:
    v = [x for x in values if x is not None]
    return {"min": min(v) if v else None, "max": max(v) if v else None,
            "mean": round(float(np.mean(v)), 3) if v else None, "missed": len(values) - len(v)}


def run(args) -> dict:
    t0 = time.monotonic()
    robust = TrackMonitorSettings()
    paper = TrackMonitorSettings(innovation_test="paper")
    base = MultirotorSettings()
    learned = {}
    if args.train > 0:
        train = [simulate(base.replace(seed=args.seed * 1000 + 900 + i, duration_s=args.undisturbed_duration))
                 for i in range(int(args.train))]
        for name in ("robust", "paper"):
            st = robust if name == "robust" else paper
            sig = train_sigmas(train, st)
            learned[name] = {(k[:-4] + "_deg" if k.endswith("_rad") else k): (
                round(math.degrees(v), 4) if k.endswith("_rad") else v) for k, v in sig.items()}
            st = st.replace(**{k: v for k, v in sig.items() if k.endswith("_rad")})
            if name == "robust":
                robust = st
            else:
                paper = st
    n = max(1, min(5, int(args.flights)))
    tables = {}
    for kind, paper_table, offset in (("fast", PAPER_FAST, 100), ("slow", PAPER_SLOW, 200)):
        rows = []
        for i, onset in enumerate(paper_table["onset_s"][:n]):
            sim = base.replace(seed=args.seed * 1000 + offset + i, disturbance=f"{kind}_ramp", onset_s=onset,
                               duration_s=onset + args.after_onset)
            rows.append(fly(sim, robust, paper))
        tables[kind] = {
            "ramp_g_s": sim.ramp_g_s,
            "flights": rows,
            "delay_s": {d: _stats([r["delay_s"][d] for r in rows]) for d in DETECTORS},
            "false_alarms_before_onset": {d: sum(r["false_alarms"][d] for r in rows) for d in DETECTORS},
            "paper_delay_s": {
                "threshold": [round(a - o, 2) for a, o in zip(paper_table["threshold_s"], paper_table["onset_s"], strict=True)],
                "track": [round(a - o, 2) for a, o in zip(paper_table["track_s"], paper_table["onset_s"], strict=True)]},
        }
    und = []
    for i in range(int(args.undisturbed)):
        sim = base.replace(seed=args.seed * 1000 + 500 + i, disturbance="none", duration_s=args.undisturbed_duration)
        und.append(fly(sim, robust, paper))
    false_alarms = {d: sum(r["false_alarms"][d] for r in und) for d in DETECTORS}
    worst = {k: tables[k]["delay_s"]["combined"]["max"] for k in ("fast", "slow")}
    missed = {k: tables[k]["delay_s"]["combined"]["missed"] for k in ("fast", "slow")}
    goals_met = (all(worst[k] is not None and missed[k] == 0 for k in worst)
                 and worst["fast"] <= GOALS["fast_s"] and worst["slow"] <= GOALS["slow_s"]
                 and false_alarms["combined"] == GOALS["false_alarms"]
                 and all(tables[k]["false_alarms_before_onset"]["combined"] == 0 for k in tables))
    return {
        "combined_delay_s": worst,
        "false_alarms": false_alarms["combined"],
        "false_alarms_by_detector": false_alarms,
        "undisturbed": {"flights": len(und), "duration_s": float(args.undisturbed_duration),
                        "flight_hours": round(len(und) * args.undisturbed_duration / 3600.0, 3),
                        "max_cross_track_m": round(max((r["max_cross_track_m"] for r in und), default=0.0), 3),
                        "paper_false_alarms": {"threshold": 3, "track": 0}},
        "tables": tables,
        "goals": GOALS,
        "learned_sigma_deg": learned,
        "train_flights": int(args.train),
        "goals_met": bool(goals_met),
        "settings": {"monitor": {k: v for k, v in robust.__dict__.items()},
                     "paper_monitor_innovation_test": paper.innovation_test,
                     "sim_mag_gain_per_s": base.mag_gain_per_s, "sim_earth_field_nt": base.earth_field_nt},
        "elapsed_s": round(time.monotonic() - t0, 2),
    }


def _fmt(x) -> str:
    return "   —  " if x is None else f"{x:6.2f}"


def format_text(r: dict) -> str:
    lines = []
    for kind, title in (("fast", "Fast ramp"), ("slow", "Slow ramp")):
        tb = r["tables"][kind]
        lines.append(f"{title} (+{tb['ramp_g_s']:g} G/s): alarm delay after onset, s")
        lines.append("  flight   onset  " + "  ".join(f"{d:>10}" for d in DETECTORS))
        for i, row in enumerate(tb["flights"], 1):
            lines.append(f"  {i:>6}  {row['onset_s']:6.2f}  " + "  ".join(
                f"{_fmt(row['delay_s'][d]):>10}" for d in DETECTORS))
        lines.append("  paper   threshold " + " ".join(f"{x:+.1f}" for x in tb["paper_delay_s"]["threshold"])
                     + " | track " + " ".join(f"{x:+.1f}" for x in tb["paper_delay_s"]["track"]))
        lines.append("  false alarms before onset: " + ", ".join(
            f"{d} {tb['false_alarms_before_onset'][d]}" for d in DETECTORS))
        lines.append("")
    u = r["undisturbed"]
    lines.append(f"Undisturbed: {u['flights']} flights × {u['duration_s']:g} s, max |cross-track| "
                 f"{u['max_cross_track_m']:.2f} m; false alarms: " + ", ".join(
                     f"{d} {n}" for d, n in r["false_alarms_by_detector"].items())
                 + " (paper, one flight: threshold 3, track 0)")
    c = r["combined_delay_s"]
    lines.append(f"Combined worst delay: fast {_fmt(c['fast']).strip()} s (goal ≤ {r['goals']['fast_s']:g}), "
                 f"slow {_fmt(c['slow']).strip()} s (goal ≤ {r['goals']['slow_s']:g}); "
                 f"combined false alarms {r['false_alarms']} (goal 0) → goals met: {r['goals_met']}")
    for name, sig in r.get("learned_sigma_deg", {}).items():
        lines.append(f"σ learned on {r['train_flights']} undisturbed flights ({name} test): innovation "
                     f"{sig['innovation_sigma_deg']:.3f}°, median {sig['median_sigma_deg']:.3f}°, "
                     f"block {sig['block_sigma_deg']:.3f}°")
    lines.append(f"({r['elapsed_s']:.1f} s)")
    return "\n".join(lines)


if __name__ == "__main__":
    import argparse

    p = argparse.ArgumentParser()
    add_arguments(p)
    print(format_text(run(p.parse_args())))
