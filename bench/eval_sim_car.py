"""Car simulator evaluation: disturbance sizes per source kind and the DMC features a detector sees.

For each layout and seed, :func:`sim_publishers.car.core.simulate` is run and measured:

- single-compass heading error inside each source's zone (compass 1, measured field compensated with the
  car's true calibration, levelled with the true attitude, against the true heading) and outside every
  zone (no source's field above ``active_field_nt``);
- the DMC features of docs/methods.md#dmc on the same compensated fields: Δm_k = |h_k| − R (3-D strength),
  Δh = h_1 − h_2 (level-compass headings, Δh_r = 0 with the true calibration), and their rates, both
  between consecutive 50 Hz samples and between 0.2 s window means 0.5 s apart (what a detector that
  smooths before differentiating sees) — inside disturbed epochs (truth ``disturbed``) and outside;
- GNSS error statistics in open sky and the share of degraded / lost epochs;
- simulation time of one drive.

``magmesh eval sim_car [--json]``.
"""

from __future__ import annotations

import time

import numpy as np

from magmesh import maths
from sim_publishers.car.core import LAYOUTS, CarDrive, CarSimSettings, simulate

SMOOTH_S = 0.2
RATE_S = 0.5


def add_arguments(parser) -> None:
    parser.add_argument("--layouts", default="urban_a,urban_b,urban_c,clean", help="comma-separated layouts")
    parser.add_argument("--seeds", type=int, default=3, help="seeds per layout (1..N)")
    parser.add_argument("--duration-s", type=float, default=300.0)


def compensated(drive: CarDrive) -> dict[str, np.ndarray]:
    return {sid: p.apply(drive.mag_b_nt[sid]) for sid, p in drive.true_params.items()}


def levelled_heading(drive: CarDrive, h: np.ndarray) -> np.ndarray:
    """Tilt-compensated heading of a compensated field using the true pitch and roll."""
    tr = drive.truth
    cp, sp = np.cos(tr.pitch_rad), np.sin(tr.pitch_rad)
    cr, sr = np.cos(tr.roll_rad), np.sin(tr.roll_rad)
    # Ry(−θ) Rx(φ) h (maths.tilt_compensated_heading, vectorised over epochs)
    y = cr * h[:, 1] - sr * h[:, 2]
    z = sr * h[:, 1] + cr * h[:, 2]
    x = cp * h[:, 0] - sp * z
    return maths.mag_heading_flu(x, y, drive.declination_rad)


def _window_rate(t: np.ndarray, y: np.ndarray, rate_hz: float) -> np.ndarray:
    """Rate between means of SMOOTH_S windows RATE_S apart (NaN until the history is full)."""
    n = max(1, int(round(SMOOTH_S * rate_hz)))
    lag = max(1, int(round(RATE_S * rate_hz)))
    c = np.concatenate([[0.0], np.cumsum(y)])
    mean = np.full(y.size, np.nan)
    mean[n - 1:] = (c[n:] - c[:-n]) / n
    out = np.full(y.size, np.nan)
    out[lag:] = (mean[lag:] - mean[:-lag]) / (t[lag:] - t[:-lag])
    return out


def dmc_features(drive: CarDrive) -> dict[str, np.ndarray]:
    """Δm (N×2, nT), Δh (rad) and their rates, raw (consecutive samples) and windowed."""
    h = compensated(drive)
    t = drive.t_mag_s
    rate = drive.settings.mag_rate_hz
    radius = drive.true_params["1"].field_radius_nt
    dm = np.stack([np.linalg.norm(h[sid], axis=1) - radius for sid in ("1", "2")], axis=1)
    hd = {sid: maths.mag_heading_flu(h[sid][:, 0], h[sid][:, 1], drive.declination_rad) for sid in ("1", "2")}
    dh = np.asarray(maths.angle_diff(hd["1"], hd["2"]))
    dt = np.diff(t, prepend=np.nan)
    ddm_raw = np.diff(dm, axis=0, prepend=np.nan) / dt[:, None]
    ddh_raw = np.asarray(maths.wrap_pi(np.diff(dh, prepend=np.nan))) / dt
    ddm_win = np.stack([_window_rate(t, dm[:, k], rate) for k in range(2)], axis=1)
    ddh_win = _window_rate(t, np.unwrap(dh), rate)
    return {"dm_nt": dm, "dh_rad": dh, "ddm_raw_nt_s": ddm_raw, "ddh_raw_rad_s": ddh_raw,
            "ddm_win_nt_s": ddm_win, "ddh_win_rad_s": ddh_win}


def _pct(x: np.ndarray, qs=(50, 95, 99)) -> list[float] | None:
    x = np.abs(x[np.isfinite(x)])
    if x.size == 0:
        return None
    return [float(v) for v in np.percentile(x, qs)]


def feature_table(drives: list[CarDrive]) -> dict:
    """Percentiles (50, 95, 99) of |feature| inside disturbed epochs and outside every zone."""
    rows: dict[str, dict[str, list]] = {"inside": {}, "outside": {}}
    acc: dict[str, dict[str, list]] = {"inside": {}, "outside": {}}
    for d in drives:
        f = dmc_features(d)
        inside = d.truth.disturbed
        outside = ~d.truth.disturbed & ~d.truth.active.any(axis=1)
        for zone, mask in (("inside", inside), ("outside", outside)):
            a = acc[zone]
            a.setdefault("dm_nt", []).append(np.max(np.abs(f["dm_nt"][mask]), axis=1))
            a.setdefault("dh_deg", []).append(np.degrees(f["dh_rad"][mask]))
            a.setdefault("ddm_raw_nt_s", []).append(np.fmax.reduce(np.abs(f["ddm_raw_nt_s"][mask]), axis=1))
            a.setdefault("ddh_raw_deg_s", []).append(np.degrees(f["ddh_raw_rad_s"][mask]))
            a.setdefault("ddm_win_nt_s", []).append(np.fmax.reduce(np.abs(f["ddm_win_nt_s"][mask]), axis=1))
            a.setdefault("ddh_win_deg_s", []).append(np.degrees(f["ddh_win_rad_s"][mask]))
    for zone in acc:
        for k, parts in acc[zone].items():
            rows[zone][k] = _pct(np.concatenate(parts))
    return rows


def zone_errors(drives: list[CarDrive]) -> dict:
    """Per source kind: seconds active and compass-1 heading error percentiles (deg) while active."""
    per_kind: dict[str, dict[str, list]] = {}
    outside: list[np.ndarray] = []
    for d in drives:
        err = np.degrees(np.abs(maths.angle_diff(levelled_heading(d, compensated(d)["1"]), d.truth.heading_rad)))
        dh = np.degrees(np.abs(dmc_features(d)["dh_rad"]))
        for j, src in enumerate(d.sources):
            m = d.truth.active[:, j]
            if not m.any():
                continue
            k = per_kind.setdefault(src.kind, {"err": [], "seconds": [], "dh": []})
            k["err"].append(err[m])
            k["dh"].append(dh[m])
            k["seconds"].append(m.sum() / d.settings.mag_rate_hz)
        outside.append(err[~d.truth.active.any(axis=1)])
    out = {kind: {"zones": len(v["seconds"]), "mean_seconds": float(np.mean(v["seconds"])),
                  "err_deg_p50_p90_max": _pct(np.concatenate(v["err"]), (50, 90, 100)),
                  "dh_deg_p50_p90_max": _pct(np.concatenate(v["dh"]), (50, 90, 100))}
           for kind, v in sorted(per_kind.items())}
    out["outside"] = {"err_deg_p50_p99_max": _pct(np.concatenate(outside), (50, 99, 100))}
    return out


def gnss_stats(drives: list[CarDrive]) -> dict:
    err_h, err_v, n_all, n_2d, n_none = [], [], 0, 0, 0
    for d in drives:
        g = d.gnss
        ok = g.fix_type == "3d"
        e = g.pos_enu_m - g.true_pos_enu_m
        err_h.append(e[ok, :2].ravel())
        vt = np.interp(g.t_s, d.t_mag_s, d.truth.vel_enu_m_s[:, 0]), np.interp(g.t_s, d.t_mag_s, d.truth.vel_enu_m_s[:, 1])
        err_v.append(np.concatenate([g.vel_enu_m_s[ok, 0] - vt[0][ok], g.vel_enu_m_s[ok, 1] - vt[1][ok]]))
        n_all += g.t_s.size
        n_2d += int(np.sum(g.fix_type == "2d"))
        n_none += int(np.sum(g.fix_type == "none"))
    eh, ev = np.concatenate(err_h), np.concatenate(err_v)
    return {"pos_err_std_m": float(np.std(eh)), "pos_err_mean_m": float(np.mean(eh)),
            "vel_err_std_m_s": float(np.std(ev)), "frac_2d": n_2d / n_all, "frac_none": n_none / n_all}


def run(args) -> dict:
    layouts = [x.strip() for x in str(args.layouts).split(",") if x.strip()]
    for lay in layouts:
        if lay not in LAYOUTS:
            raise SystemExit(f"unknown layout {lay!r}; known: {', '.join(LAYOUTS)}")
    result: dict = {"seeds": int(args.seeds), "duration_s": float(args.duration_s), "layouts": {}}
    all_drives: list[CarDrive] = []
    times = []
    for lay in layouts:
        drives = []
        for seed in range(1, int(args.seeds) + 1):
            t0 = time.perf_counter()
            drives.append(simulate(CarSimSettings(layout=lay, seed=seed, duration_s=float(args.duration_s))))
            times.append(time.perf_counter() - t0)
        all_drives += drives
        result["layouts"][lay] = {
            "disturbed_frac": float(np.mean([d.truth.disturbed.mean() for d in drives])),
            "zones": zone_errors(drives),
        }
    urban = [d for d in all_drives if d.settings.layout != "clean"]
    result["features"] = feature_table(urban or all_drives)
    result["gnss"] = gnss_stats(all_drives)
    result["simulate_s"] = {"median": float(np.median(times)), "max": float(np.max(times))}
    return result


def _f(x, nd=1) -> str:
    return "-" if x is None else "/".join(f"{v:.{nd}f}" for v in x)


def format_text(r: dict) -> str:
    lines = [f"car simulator: {r['seeds']} seed(s) × {r['duration_s']:.0f} s per layout", ""]
    lines.append(f"{'layout':9} {'source':8} {'zones':>5} {'s/zone':>7}  compass-1 heading error deg p50/p90/max")
    for lay, v in r["layouts"].items():
        for kind, z in v["zones"].items():
            if kind == "outside":
                lines.append(f"{lay:9} {'outside':8} {'':>5} {'':>7}  p50/p99/max {_f(z['err_deg_p50_p99_max'], 2)}")
            else:
                lines.append(f"{lay:9} {kind:8} {z['zones']:5d} {z['mean_seconds']:7.1f}  "
                             f"{_f(z['err_deg_p50_p90_max']):>28}  {_f(z['dh_deg_p50_p90_max']):>16}")
        lines.append(f"{lay:9} disturbed fraction {v['disturbed_frac']:.3f}")
    lines += ["", "DMC features (true calibration), |value| percentiles p50/p95/p99:",
              f"{'feature':16} {'inside (disturbed)':>24} {'outside':>24}"]
    names = {"dm_nt": "Δm nT", "dh_deg": "Δh deg", "ddm_raw_nt_s": "dΔm nT/s 50Hz", "ddh_raw_deg_s": "dΔh deg/s 50Hz",
             "ddm_win_nt_s": "dΔm nT/s win", "ddh_win_deg_s": "dΔh deg/s win"}
    for k, label in names.items():
        lines.append(f"{label:16} {_f(r['features']['inside'][k], 2):>24} {_f(r['features']['outside'][k], 2):>24}")
    g = r["gnss"]
    lines += ["", f"GNSS open sky: position error σ {g['pos_err_std_m']:.2f} m per axis, velocity σ "
              f"{g['vel_err_std_m_s']:.3f} m/s; 2d epochs {100 * g['frac_2d']:.1f} %, no fix {100 * g['frac_none']:.1f} %",
              f"simulate(): median {r['simulate_s']['median']:.2f} s, max {r['simulate_s']['max']:.2f} s per drive"]
    return "\n".join(lines)


if __name__ == "__main__":
    import argparse

    p = argparse.ArgumentParser()
    add_arguments(p)
    print(format_text(run(p.parse_args())))
