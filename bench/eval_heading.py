"""``magmesh eval heading``: the heading fuser against simulated urban drives and the BROAD recordings.

1. Simulated drives (``sim_publishers.car``; seeded; layouts urban_a/b/c with bridges, viaducts,
   tunnels, trucks and cables). Compass 1 is compensated with the simulator's true calibration plus a
   calibration's typical error (the DMC evaluation's convention). Heading RMS and max error against
   the truth over the whole drive (alignment at t = 0 included, interference zones included), and RMS
   inside the zones where the true field disturbs a compass (``truth.disturbed``), for:

   - ``mag_only``   the tilt-compensated heading of compass 1 (what a single compass gives);
   - ``gyro_only``  aligned magnetically at the start, then the gyro alone;
   - ``ekf``        the quaternion EKF fusing every magnetometer sample (no DMC switching, no adaptive
                    noise, no field checks, no gate);
   - ``ekf_adaptive``  the same with §2's quasi-static detection, adaptive noise, field checks and gate;
   - ``fuser``      everything, plus §1's switch to the gyro while the DMC (the committed FCM model,
                    ``services.dmc_detector``) says the magnetic heading is invalid.

   Goal: the fuser ≤ 2.5° RMS over the whole drive for every seed (``sim_rms_deg`` is the worst one).

2. BROAD (Laidig et al. 2021, CC-BY-4.0; ``data/broad`` or ``--broad-dir``, HDF5 or BROAD's .mat
   files): every trial replayed through the fuser core with the IMU-only profile (the same named
   settings for every trial) and, in the same run, VQF (``vqf``, online, defaults), x-io Fusion
   (``imufusion``, magnetic rejection on) and the ``ahrs`` package's EKF; heading RMS over the
   ``movement`` samples (BROAD's own metric). A file that is not a usable trial is listed with the
   reason. Goal: at or below VQF on every trial; mean and worst trial below VQF's.

3. ``--mesh``: the demo car through the real processes, the live ``heading`` key scored
   (:mod:`bench.eval_heading_mesh`).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from magmesh import maths

GOAL_SIM_RMS_DEG = 2.5
LAYOUTS = ("urban_a", "urban_b", "urban_c")
SEEDS_FULL = (1, 2, 3)
SEEDS_QUICK = (1,)
VARIANTS = ("mag_only", "gyro_only", "ekf", "ekf_adaptive", "fuser")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="one seed per layout, short BROAD slices (the default test's size)")
    p.add_argument("--seeds", type=str, default=None, help="comma-separated simulation seeds (default 1,2,3)")
    p.add_argument("--layouts", type=str, default=",".join(LAYOUTS), help="comma-separated car layouts")
    p.add_argument("--duration-s", type=float, default=300.0, help="length of each simulated drive, s")
    p.add_argument("--broad-dir", type=Path, default=None, help="directory of BROAD trial files (*.hdf5 or *.mat)")
    p.add_argument("--profile", default=None, help="heading fuser profile for BROAD (default: the IMU-only profile)")
    p.add_argument("--broad-max-s", type=float, default=None, help="replay only the first this many seconds of each trial")
    p.add_argument("--no-sim", action="store_true", help="skip the simulated drives")
    p.add_argument("--no-broad", action="store_true", help="skip BROAD")
    p.add_argument("--mesh", action="store_true",
                   help="drive the demo car through the real processes (deploy/mesh.toml's car-1 services) and score "
                        "the live heading key instead of the in-process runs")
    p.add_argument("--mesh-duration-s", type=float, default=300.0, help="--mesh: length of the drive, s of sample time")
    p.add_argument("--mesh-speed", type=float, default=5.0, help="--mesh: the car's replay speed, × real time")
    p.add_argument("--mesh-impl", default=None, help="--mesh: heading_fuser implementation (default: the manifest's)")


# ---- simulated drives -------------------------------------------------------------------------


def sim_settings(**overrides):
    """Fuser settings for the simulated car: the core's defaults (chosen for a road vehicle)."""
    from services.heading_fuser.core import Settings

    return Settings(**overrides)


def variant_settings(name: str, **overrides):
    if name == "ekf":
        overrides.update(adaptive_noise=False, use_field_check=False, use_dmc=False, mag_gate_sigma=1e6,
                         rejection_timeout_s=1e9)
    elif name == "ekf_adaptive":
        overrides.update(use_dmc=False)
    return sim_settings(**overrides)


def run_filter_on_drive(drive, settings, dmc_valid: np.ndarray | None, use_mag: bool = True, impl: str = "compiled"):
    """Replay a drive through the filter in time order; returns heading (rad) and mode at each mag epoch, and
    the filter. ``impl``: ``compiled`` (the default; the whole drive in one call of the compiled filter) or
    ``reference`` (:class:`core.HeadingFilter` sample by sample); they agree within 1e-9 rad."""
    if impl == "compiled":
        return _run_compiled_on_drive(drive, settings, dmc_valid, use_mag)
    if impl != "reference":
        raise ValueError(f"unknown impl {impl!r} (compiled or reference)")
    from services.heading_fuser.core import HeadingFilter

    f = HeadingFilter(settings)
    t_imu, t_mag = drive.gyro_t_s, drive.t_s
    mag = drive.params1.apply(drive.mag1_nt)
    gyro, acc = drive.gyro_rad_s.tolist(), drive.accel_m_s2
    n = len(t_mag)
    heading = np.full(n, np.nan)
    modes = np.empty(n, dtype=object)
    j, t_prev = 0, float(t_imu[0])
    aligned_with_mag = False
    for i in range(n):
        while j < len(t_imu) and t_imu[j] <= t_mag[i] + 1e-9:
            f.update_imu(gyro[j], acc[j], float(t_imu[j]) - t_prev)
            t_prev = float(t_imu[j])
            j += 1
        if use_mag or not aligned_with_mag:
            f.update_mag(mag[i], None if dmc_valid is None else bool(dmc_valid[i]))
            aligned_with_mag = f.aligned
        heading[i] = f.heading_rad() if f.aligned else np.nan  # no heading before alignment
        modes[i] = f.mode
    return heading, modes, f


class _CompiledRun:
    """What the evaluation reads of a finished compiled run (``transitions``)."""

    def __init__(self, transitions: list):
        self.transitions = transitions


def _run_compiled_on_drive(drive, settings, dmc_valid, use_mag: bool):
    from services.heading_fuser import compiled

    t_imu, t_mag = np.asarray(drive.gyro_t_s, float), np.asarray(drive.t_s, float)
    mag = drive.params1.apply(drive.mag1_nt)
    n = len(t_mag)
    # the reference steps the IMU only up to the last magnetometer epoch
    n_imu = int(np.searchsorted(t_imu, t_mag[-1] + 1e-9, side="right"))
    dmc = None if dmc_valid is None else np.asarray(dmc_valid, bool).astype(np.int8)
    k = n  # magnetometer epochs fed
    if not use_mag:  # only until the filter has aligned: find that epoch on a prefix of the drive
        m = 1
        while True:
            m = min(n, max(2 * m, int(np.searchsorted(t_mag, t_mag[0] + settings.init_duration_s + 2.0)) + 1))
            out, _, pos_mag, _ = compiled.run_recording(
                settings, drive.gyro_rad_s[:n_imu], drive.accel_m_s2[:n_imu], mag[:m], t_imu_s=t_imu[:n_imu],
                t_mag_s=t_mag[:m], dmc=None if dmc is None else dmc[:m])
            aligned = np.flatnonzero(out.mode[pos_mag] != 0)
            if len(aligned) or m == n:
                k = int(aligned[0]) + 1 if len(aligned) else m
                break
    out, pos_imu, pos_mag, _ = compiled.run_recording(
        settings, drive.gyro_rad_s[:n_imu], drive.accel_m_s2[:n_imu], mag[:k], t_imu_s=t_imu[:n_imu],
        t_mag_s=t_mag[:k], dmc=None if dmc is None else dmc[:k], full_output=True)
    # the row after which each epoch is read: its magnetometer row, or the last IMU row at or before it
    rows = np.empty(n, np.int64)
    rows[:k] = pos_mag
    if k < n:
        last_imu = np.searchsorted(t_imu[:n_imu], t_mag[k:] + 1e-9, side="right") - 1
        rows[k:] = pos_imu[last_imu]
    mode = out.mode[rows]
    heading = np.where(mode != 0, out.heading_rad[rows], np.nan)
    modes = np.array(compiled.MODES, dtype=object)[mode]
    changed = np.flatnonzero(out.reason)
    transitions = [(float(out.t_s[r]), None, compiled.MODES[out.mode[r]], compiled.REASONS[out.reason[r]])
                   for r in changed]
    return heading, modes, _CompiledRun(transitions)


def tilt_compensated_headings(b_nt: np.ndarray, accel_m_s2: np.ndarray, declination_rad: float) -> np.ndarray:
    """Row-wise :func:`magmesh.maths.tilt_compensated_heading`: b_level = Ry(−θ) Rx(φ) b."""
    roll, pitch = maths.roll_pitch_from_accel(accel_m_s2)
    bx, by, bz = b_nt[:, 0], b_nt[:, 1], b_nt[:, 2]
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    y1 = cr * by - sr * bz  # Rx(φ)
    z1 = sr * by + cr * bz
    x2 = cp * bx - sp * z1  # Ry(−θ)
    return maths.mag_heading_flu(x2, y1, declination_rad)


def _err_stats(err_deg: np.ndarray, zone: np.ndarray) -> dict:
    ok = np.isfinite(err_deg)
    e = err_deg[ok]
    z = zone[ok]
    return {
        "unaligned_frac": float(1.0 - np.mean(ok)),
        "rms_deg": float(np.sqrt(np.mean(e**2))),
        "max_deg": float(np.max(np.abs(e))),
        "zone_rms_deg": float(np.sqrt(np.mean(e[z] ** 2))) if z.any() else None,
    }


def evaluate_drive(layout: str, seed: int, duration_s: float, dmc_model=None) -> dict:
    from bench.dmc_training import simulate_drive
    from services.dmc_detector import fcm

    t0 = time.perf_counter()
    d = simulate_drive(layout, seed, duration_s=duration_s)
    model = dmc_model or fcm.FcmModel.load()
    valid = np.asarray(model.classify(d.features)[0], bool)
    truth = d.true_heading_rad
    zone = d.disturbed
    out: dict = {"layout": layout, "seed": seed, "duration_s": float(d.t_s[-1]),
                 "zone_frac": float(np.mean(zone)), "dmc_invalid_frac": float(np.mean(~valid))}
    # magnetometer only: compass 1 levelled with the accelerometer sample at (or just before) each epoch
    k = np.clip(np.searchsorted(d.gyro_t_s, d.t_s, side="right") - 1, 0, len(d.gyro_t_s) - 1)
    h_mag = tilt_compensated_headings(d.params1.apply(d.mag1_nt), d.accel_m_s2[k], d.declination_rad)
    out["mag_only"] = _err_stats(np.degrees(maths.angle_diff(h_mag, truth)), zone)
    decl = float(d.declination_rad)
    h, _, _ = run_filter_on_drive(d, sim_settings(declination_rad=decl), None, use_mag=False)
    out["gyro_only"] = _err_stats(np.degrees(maths.angle_diff(h, truth)), zone)
    for name in ("ekf", "ekf_adaptive", "fuser"):
        s = variant_settings(name, declination_rad=decl)
        h, modes, f = run_filter_on_drive(d, s, valid if name == "fuser" else None)
        out[name] = _err_stats(np.degrees(maths.angle_diff(h, truth)), zone)
        if name == "fuser":
            out["fuser"]["mode_frac"] = {m: float(np.mean(modes == m)) for m in ("magnetic", "gyro_only", "recovering")}
            out["fuser"]["transitions"] = len(f.transitions)
            # largest change of the heading error in one magnetometer epoch while re-acquiring (the
            # yaw-jump guard; the vehicle's own turning is not counted)
            err = maths.angle_diff(h, truth)
            dh = np.abs(np.degrees(maths.angle_diff(err[1:], err[:-1])))
            rec = (modes[1:] == "recovering") & np.isfinite(dh)
            out["fuser"]["max_step_recovering_deg"] = float(dh[rec].max()) if rec.any() else 0.0
    out["elapsed_s"] = time.perf_counter() - t0
    return out


# ---- BROAD ------------------------------------------------------------------------------------


def evaluate_broad(directory: Path | None, max_s: float | None, peers: bool = True, profile: str | None = None,
                   skipped: dict | None = None) -> dict:
    """Per trial: the RMS heading error of magmesh (``profile``) and of each peer; a file that cannot be
    scored goes into ``skipped`` (name → reason) instead."""
    from bench import heading_broad as hb
    from services.heading_fuser import profiles

    profile = profile or profiles.IMU_ONLY
    out = {}
    for trial in hb.scorable_trials(directory, max_s, skipped):
        q, info = hb.run_magmesh(trial, profiles.settings(profile))
        row = {"profile": profile, "magmesh": hb.heading_rms_deg(q, trial)}
        if peers:
            for name, fn in hb.PEERS.items():
                row[name] = hb.heading_rms_deg(fn(trial), trial)
        row["disturbed"] = hb.is_disturbed(trial.name)
        row["magmesh_us_per_sample"] = info["us_per_sample"]
        row["magmesh_mode_frac"] = info["mode_frac"]
        out[trial.name] = row
    return out


def broad_goal(broad: dict) -> dict:
    """Per trial: magmesh at or below VQF (the strongest peer) in the same run."""
    return {name: bool(r["magmesh"] <= r["vqf"]) for name, r in broad.items() if "vqf" in r}


def broad_summary(broad: dict) -> dict:
    """Mean and worst trial per estimator, and whether magmesh's are below VQF's."""
    names = [n for n in ("magmesh", "vqf", "imufusion", "ahrs_ekf") if broad and all(n in r for r in broad.values())]
    out = {n: {"mean_deg": float(np.mean([r[n] for r in broad.values()])),
               "worst_deg": float(np.max([r[n] for r in broad.values()]))} for n in names}
    if "vqf" in out:
        out["mean_below_vqf"] = bool(out["magmesh"]["mean_deg"] < out["vqf"]["mean_deg"])
        out["worst_below_vqf"] = bool(out["magmesh"]["worst_deg"] < out["vqf"]["worst_deg"])
    return out


# ---- entry points -----------------------------------------------------------------------------


def run(args: argparse.Namespace) -> dict:
    if getattr(args, "mesh", False):
        from bench import eval_heading_mesh

        if args.mesh_duration_s <= 0 or args.mesh_speed <= 0:
            raise SystemExit(f"--mesh-duration-s and --mesh-speed must be > 0 (got {args.mesh_duration_s:g} and "
                             f"{args.mesh_speed:g}).")
        return {"mesh": eval_heading_mesh.measure(args.mesh_duration_s, args.mesh_speed, heading_impl=args.mesh_impl)}
    result: dict = {"goal": {"sim_rms_deg": GOAL_SIM_RMS_DEG,
                             "broad": "at or below VQF on every trial; mean and worst trial below VQF's"},
                    "paper": {"dmc_gyro_heading_error_deg": 6.0, "adaptive_ahrs_heading_error_deg": 5.0}}
    if not args.no_sim:
        seeds = [int(x) for x in args.seeds.split(",")] if args.seeds else list(SEEDS_QUICK if args.quick else SEEDS_FULL)
        layouts = [x for x in args.layouts.split(",") if x]
        drives = [evaluate_drive(lay, seed, args.duration_s) for lay in layouts for seed in seeds]
        result["sim"] = drives
        result["sim_summary"] = {
            v: {"worst_rms_deg": max(d[v]["rms_deg"] for d in drives),
                "mean_rms_deg": float(np.mean([d[v]["rms_deg"] for d in drives])),
                "worst_max_deg": max(d[v]["max_deg"] for d in drives),
                "mean_zone_rms_deg": float(np.mean([d[v]["zone_rms_deg"] for d in drives if d[v]["zone_rms_deg"] is not None]
                                                   or [float("nan")]))}
            for v in VARIANTS
        }
        result["sim_rms_deg"] = result["sim_summary"]["fuser"]["worst_rms_deg"]
        result["sim_meets_goal"] = bool(result["sim_rms_deg"] <= GOAL_SIM_RMS_DEG)
    if not args.no_broad:
        max_s = args.broad_max_s if args.broad_max_s is not None else (90.0 if args.quick else None)
        from services.heading_fuser import profiles

        profile = getattr(args, "profile", None) or profiles.IMU_ONLY
        if profile not in profiles.PROFILES:
            raise SystemExit(f"unknown heading profile {profile!r}; known: {', '.join(profiles.PROFILES)}")
        skipped: dict = {}
        broad = evaluate_broad(args.broad_dir, max_s, profile=profile, skipped=skipped)
        result["broad_profile"] = profile
        result["broad"] = broad
        result["broad_skipped"] = skipped
        result["broad_max_s"] = max_s
        result["broad_goal"] = broad_goal(broad)
        result["broad_summary"] = broad_summary(broad)
        sm = result["broad_summary"]
        result["broad_meets_goal"] = (bool(all(result["broad_goal"].values()) and sm["mean_below_vqf"]
                                           and sm["worst_below_vqf"]) if result["broad_goal"] else None)
    return result


def format_text(r: dict) -> str:
    lines = []
    if "mesh" in r:
        from bench import eval_heading_mesh

        lines.append(eval_heading_mesh.format_text(r["mesh"]))
    if "sim" in r:
        lines.append("Simulated urban drives — heading error vs truth, whole drive (deg)")
        lines.append(f"{'drive':<16}" + "".join(f"{v:>22}" for v in VARIANTS))
        lines.append(f"{'':<16}" + "".join(f"{'rms / max / zone':>22}" for _ in VARIANTS))
        for d in r["sim"]:
            cells = []
            for v in VARIANTS:
                z = d[v]["zone_rms_deg"]
                cells.append(f"{d[v]['rms_deg']:6.2f} /{d[v]['max_deg']:6.1f} /{(z if z is not None else float('nan')):6.2f}")
            lines.append(f"{d['layout'] + '/s' + str(d['seed']):<16}" + "".join(f"{c:>22}" for c in cells))
        f = r["sim_summary"]["fuser"]
        lines.append(f"fuser worst-seed RMS {r['sim_rms_deg']:.2f}° (goal ≤ {GOAL_SIM_RMS_DEG}°: "
                     f"{'met' if r['sim_meets_goal'] else 'NOT met'}); worst max {f['worst_max_deg']:.1f}°")
        for d in r["sim"]:
            m = d["fuser"]["mode_frac"]
            lines.append(f"  {d['layout']}/s{d['seed']}: zones {100 * d['zone_frac']:.1f}% of the drive, DMC invalid "
                         f"{100 * d['dmc_invalid_frac']:.1f}%, fuser gyro-only {100 * m['gyro_only']:.1f}% / recovering "
                         f"{100 * m['recovering']:.1f}%, largest error step while recovering "
                         f"{d['fuser']['max_step_recovering_deg']:.2f}°/epoch")
    if "broad" in r:
        lines.append("")
        cut = f" (first {r['broad_max_s']:.0f} s of each trial)" if r.get("broad_max_s") else ""
        lines.append(f"BROAD — heading RMS over the movement samples (deg){cut}; magmesh profile "
                     f"{r.get('broad_profile')!r}")
        cols = ("magmesh", "vqf", "imufusion", "ahrs_ekf")
        lines.append(f"{'trial':<36}" + "".join(f"{c:>11}" for c in cols) + "  ≤ vqf")
        for name, row in r["broad"].items():
            g = r["broad_goal"].get(name)
            lines.append(f"{name:<36}" + "".join(f"{row.get(c, float('nan')):11.2f}" for c in cols)
                         + f"  {'yes' if g else 'NO'}")
        sm = r.get("broad_summary", {})
        for k in ("mean_deg", "worst_deg"):
            if all(c in sm for c in cols):
                lines.append(f"{k[:-4]:<36}" + "".join(f"{sm[c][k]:11.2f}" for c in cols))
        for name, why in r.get("broad_skipped", {}).items():
            lines.append(f"skipped {name}: {why}")
    return "\n".join(lines)



