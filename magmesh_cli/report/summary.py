"""The report's summary figures per vehicle (plain Python numbers; also written as summary.json).

Metrics follow docs/methods.md#metrics: DMC recognition rate RP, error rate MP and accuracy WP of the samples
recognised as valid ("good" = heading error < 5°); alarm delays against the recording's own
disturbance truth (``truth/sources``); heading error against ``truth/pose``.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from .data import VehicleRun, heading_error, rms
from .plots import _spread, calibration_pairs

GOOD_DEG = 5.0


def _f(x) -> float | None:
    return None if x is None or not np.isfinite(x) else float(x)


def alarm_vs_truth(run: VehicleRun, min_episode_s: float = 1.0, slack_s: float = 2.0) -> dict | None:
    """Disturbed episodes of the truth vs raised alarms: detected episodes, delays, false alarms."""
    episodes = [(s, e) for s, e in run.disturbed_intervals() if e - s >= min_episode_s]
    alarms = run.alarms()
    if not run.truth("sources"):
        return None
    delays = []
    for s, e in episodes:
        hits = [a.start for a in alarms if s - slack_s <= a.start <= e]
        if hits:
            delays.append(max(0.0, min(hits) - s))
    all_dist = run.disturbed_intervals()
    false = [a for a in alarms if not any(s - slack_s <= a.start <= e + slack_s for s, e in all_dist)]
    return {
        "episodes": len(episodes),
        "detected": len(delays),
        "median_delay_s": _f(np.median(delays)) if delays else None,
        "false_alarms": len(false),
    }


def dmc_metrics(run: VehicleRun) -> dict | None:
    dmc = run.messages("dmc")
    if not dmc:
        return None
    out = {
        "epochs": len(dmc),
        "valid_frac": float(np.mean([m["valid"] for m in dmc])),
        "mean_credibility": float(np.mean([m["credibility"] for m in dmc])),
        "impl": sorted({m.get("impl", "?") for m in dmc}),
    }
    err = heading_error(run, "dmc")
    if err is not None and len(err[0]):
        t_ok = set(np.round(err[0], 9))
        valid = np.array([m["valid"] for m in dmc if round(m["t_s"], 9) in t_ok], bool)
        e = np.degrees(np.abs(err[1]))
        if len(valid) == len(e):
            good = e < GOOD_DEG
            out.update(
                rp_pct=_f(100.0 * np.sum(valid & good) / max(1, np.sum(good))),
                mp_pct=_f(100.0 * np.sum(valid & ~good) / max(1, np.sum(valid))),
                wp_deg=_f(rms(e[valid])) if valid.any() else None,
                all_rms_deg=_f(rms(e)),
            )
    return out


def heading_metrics(run: VehicleRun) -> dict | None:
    hd = run.messages("heading")
    if not hd:
        return None
    modes = Counter(m["mode"] for m in hd)
    out = {"epochs": len(hd), "mode_frac": {k: v / len(hd) for k, v in sorted(modes.items())}}
    err = heading_error(run)
    if err is not None and len(err[1]):
        e = np.degrees(np.abs(err[1]))
        out.update(rms_deg=_f(rms(e)), p95_deg=_f(np.percentile(e, 95)), max_deg=_f(e.max()), n_compared=len(e))
        tt = set(np.round(err[0], 9))
        mag = np.array([m["mode"] == "magnetic" for m in hd if round(m["t_s"], 9) in tt], bool)
        if len(mag) == len(e) and mag.any():
            out["rms_deg_magnetic_mode"] = _f(rms(e[mag]))
    return out


def calibration_metrics(run: VehicleRun) -> list[dict]:
    out = []
    for sensor, b, h, p in calibration_pairs(run):
        model = (p or {}).get("model", "3d")
        cols = slice(0, 3) if model == "3d" else slice(0, 2)
        out.append({
            "sensor": sensor,
            "model": model,
            "method": (p or {}).get("method"),
            "status": (p or {}).get("status"),
            "offset_nt": [float(x) for x in (p or {}).get("offset_nt", [])],
            "rmse_nt": _f((p or {}).get("rmse_nt")),
            "spread_before_pct": _f(_spread(np.linalg.norm(b[:, cols], axis=1))),
            "spread_after_pct": _f(_spread(np.linalg.norm(h[:, cols], axis=1))),
        })
    return out


def geomag_metrics(run: VehicleRun) -> dict | None:
    fixes = run.messages("fix")
    if not fixes:
        return None
    acc = [f for f in fixes if f["accepted"]]
    out = {"matches": len(fixes), "accepted": len(acc),
           "status": dict(Counter(f["status"] for f in fixes))}
    pose = [m for m in run.truth("pose") if "pos_enu_m" in m]
    if acc and len(pose) >= 2:
        tp = np.array([m["t_s"] for m in pose])
        pp = np.array([m["pos_enu_m"] for m in pose])
        ta = np.array([f["t_s"] for f in acc])
        truth = np.stack([np.interp(ta, tp, pp[:, k]) for k in range(2)], 1)
        fix = np.array([f["pos_enu_m"] for f in acc])[:, :2]
        ins = np.array([f["ins_pos_enu_m"] for f in acc])[:, :2]
        out["fix_error_m_median"] = _f(np.median(np.linalg.norm(fix - truth, axis=1)))
        out["ins_error_m_median"] = _f(np.median(np.linalg.norm(ins - truth, axis=1)))
    return out


def track_metrics(run: VehicleRun) -> dict | None:
    tr = run.messages("track")
    if not tr:
        return None
    d = np.array([m["cross_track_m"] for m in tr])
    first = {}
    for a in run.alarms():
        first.setdefault(a.source, a.start)
    return {"max_cross_track_m": float(d.max()), "first_alarm_s": first}


def vehicle_summary(run: VehicleRun) -> dict:
    t0, t1 = run.t_range
    n = {k: len(v) for k, v in sorted(run.by_key.items())}
    rejects = run.messages("rejects")
    alarms = run.alarms()
    per_source = Counter(a.source for a in alarms)
    first = {}
    for a in alarms:
        first.setdefault(a.source, a.start)
    return {
        "vehicle": run.vehicle,
        "t_start_s": t0,
        "t_end_s": t1,
        "duration_s": t1 - t0,
        "messages": int(sum(n.values())),
        "per_key": n,
        "rejects": len(rejects),
        "rejects_per_code": dict(Counter(m["code"] for m in rejects)),
        "alarms": dict(per_source),
        "first_alarm_s": first,
        "alarms_vs_truth": alarm_vs_truth(run),
        "heading": heading_metrics(run),
        "dmc": dmc_metrics(run),
        "calibration": calibration_metrics(run),
        "geomag": geomag_metrics(run),
        "track": track_metrics(run),
    }


def summary_rows(s: dict) -> list[tuple[str, str]]:
    """(metric, value) rows of one vehicle summary, for the HTML table."""
    rows = [("time span", f"{s['t_start_s']:.1f} … {s['t_end_s']:.1f} s ({s['duration_s']:.1f} s)"),
            ("messages", f"{s['messages']} on {len(s['per_key'])} keys")]
    if s["rejects"]:
        rows.append(("rejected inputs", ", ".join(f"{k}: {v}" for k, v in s["rejects_per_code"].items())))
    rows.append(("alarms raised", ", ".join(f"{k}: {v} (first at {s['first_alarm_s'][k]:.1f} s)"
                                            for k, v in s["alarms"].items()) or "none"))
    avt = s["alarms_vs_truth"]
    if avt:
        delay = f", median delay {avt['median_delay_s']:.1f} s" if avt["median_delay_s"] is not None else ""
        rows.append(("alarms vs truth", f"{avt['detected']} of {avt['episodes']} disturbed episodes (≥ 1 s) "
                                        f"alarmed{delay}; {avt['false_alarms']} alarms outside disturbances"))
    h = s["heading"]
    if h:
        if h.get("rms_deg") is not None:
            rows.append(("heading error vs truth", f"RMS {h['rms_deg']:.2f}°, p95 {h['p95_deg']:.2f}°, "
                                                   f"max {h['max_deg']:.1f}° over {h['n_compared']} epochs"))
        rows.append(("heading modes", ", ".join(f"{k} {100 * v:.1f}%" for k, v in h["mode_frac"].items())))
    d = s["dmc"]
    if d:
        txt = f"valid {100 * d['valid_frac']:.1f}% of {d['epochs']} epochs, mean K_c {d['mean_credibility']:.2f}"
        if d.get("rp_pct") is not None:
            wp = f"{d['wp_deg']:.2f}°" if d.get("wp_deg") is not None else "n/a"
            txt += f"; RP {d['rp_pct']:.1f}%, MP {d['mp_pct']:.1f}%, WP {wp}"
        rows.append((f"DMC ({', '.join(d['impl'])})", txt))
    for c in s["calibration"]:
        rmse = f", rmse {c['rmse_nt']:.0f} nT" if c["rmse_nt"] is not None else ""
        how = f"{c['method']} {c['status']}" if c["method"] else "the cal/mag stream (no parameters recorded)"
        rows.append((f"calibration sensor {c['sensor']}",
                     f"{c['model']} {how}{rmse}; |field| spread "
                     f"{c['spread_before_pct']:.1f}% → {c['spread_after_pct']:.1f}%"))
    g = s["geomag"]
    if g:
        txt = f"{g['accepted']} accepted of {g['matches']} matches"
        if g.get("fix_error_m_median") is not None:
            txt += f"; median error fix {g['fix_error_m_median']:.0f} m vs INS {g['ins_error_m_median']:.0f} m"
        rows.append(("geomagnetic matching", txt))
    tr = s["track"]
    if tr:
        rows.append(("track", f"max cross-track {tr['max_cross_track_m']:.2f} m"))
    return rows
