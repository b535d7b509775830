"""How much the ``imu_only`` heading profile's BROAD result depends on its exact values.

``python -m bench.heading_sensitivity [--json] [--trials DIR] [--factors 0.5,2] [--settings a,b,...]``

Some of the ``imu_only`` profile's values were chosen while looking at the optical truth of the BROAD
trials it is judged on. This study moves them, one at a time, and replays every trial:

* the baseline: the profile exactly as ``magmesh eval heading`` runs it
  (``bench.heading_broad.run_magmesh(trial, profiles.settings("imu_only"))``, the compiled filter), and VQF
  (``bench.heading_broad.run_vqf``: online, its defaults) once per trial;
* each float setting of the profile multiplied by each factor (default 0.5 and 2); a setting whose value
  is 0 is skipped (any factor leaves it at 0, the baseline);
* each integer setting moved to its neighbours (value − 1 and value + 1) that ``Settings`` accepts; a
  neighbour it rejects is skipped with its error;
* each bool setting flipped.

For each variant: the movement RMS heading error per trial (BROAD's metric, ``heading_rms_deg``), its mean
and worst trial, how many trials are at or below VQF's figure on that trial, and whether the mean and worst
stay below VQF's. Rows are sorted by worst-case damage: the largest increase over the baseline on any one
trial. Nothing here is random (the filter, VQF and the metric are deterministic); no seed is needed.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench import heading_broad as hb
from services.heading_fuser import profiles
from services.heading_fuser.core import Settings

PROFILE = profiles.IMU_ONLY
DEFAULT_FACTORS = (0.5, 2.0)


@dataclass(frozen=True)
class Variant:
    name: str  # e.g. "mag_noise_nt ×0.5", "rest_detection → False"
    setting: str
    value: float | int | bool
    baseline_value: float | int | bool
    settings: Settings  # the profile with this one value changed


def baseline_settings() -> Settings:
    """The profile's settings exactly as ``magmesh eval heading`` builds them."""
    return profiles.settings(PROFILE)


def _fmt(v) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def make_variants(factors=DEFAULT_FACTORS, only: list[str] | None = None) -> tuple[list[Variant], dict[str, str]]:
    """The one-at-a-time variants of the profile, and the ones skipped (name → why)."""
    values = profiles.values(PROFILE)
    if only is not None:
        unknown = [k for k in only if k not in values]
        if unknown:
            raise ValueError(f"not a setting of the {PROFILE} profile: {', '.join(unknown)}; "
                             f"known: {', '.join(values)}")
        values = {k: values[k] for k in only}
    out: list[Variant] = []
    skipped: dict[str, str] = {}

    def add(name: str, key: str, new, old) -> None:
        try:
            s = profiles.settings(PROFILE, **{key: new})
        except ValueError as e:
            skipped[name] = str(e)
            return
        out.append(Variant(name, key, new, old, s))

    for key, old in values.items():
        if isinstance(old, bool):
            add(f"{key} → {not old}", key, not old, old)
        elif isinstance(old, int):
            for new in (old - 1, old + 1):
                add(f"{key} = {new}", key, new, old)
        elif isinstance(old, float):
            if old == 0.0:
                skipped[f"{key} ×factor"] = "its value is 0: every factor gives 0, the baseline"
                continue
            for f in factors:
                add(f"{key} ×{_fmt(float(f))}", key, old * float(f), old)
        else:
            skipped[key] = f"not numeric or bool ({type(old).__name__})"
    return out, skipped


def load_trials(directory: Path | str | None = None, max_s: float | None = None) -> tuple[list[hb.Trial], dict[str, str]]:
    """Every scorable trial of ``directory`` (default ``data/broad``) and the skipped files (name → why)."""
    skipped: dict[str, str] = {}
    trials = list(hb.scorable_trials(directory, max_s, skipped))
    return trials, skipped


def magmesh_rms(trial: hb.Trial, settings: Settings) -> float:
    q, _ = hb.run_magmesh(trial, settings, impl="compiled")
    return hb.heading_rms_deg(q, trial)


def score_row(per_trial: dict[str, float], vqf: dict[str, float], baseline: dict[str, float] | None) -> dict:
    v = np.array([per_trial[k] for k in vqf])
    ref = np.array(list(vqf.values()))
    row = {"per_trial_deg": per_trial, "mean_deg": float(v.mean()), "worst_deg": float(v.max()),
           "n_at_or_below_vqf": int(np.sum(v <= ref)), "n_trials": len(v),
           "mean_below_vqf": bool(v.mean() < ref.mean()), "worst_below_vqf": bool(v.max() < ref.max())}
    row["all_at_or_below_vqf"] = row["n_at_or_below_vqf"] == len(v)
    if baseline is not None:
        d = v - np.array([baseline[k] for k in vqf])
        i = int(np.argmax(d))
        row["max_increase_deg"] = float(d[i])
        row["max_increase_trial"] = list(vqf)[i]
    return row


def study(trials: list[hb.Trial], variants: list[Variant]) -> dict:
    """The baseline (profile and VQF) and every variant on ``trials``; rows sorted by worst-case damage."""
    t0 = time.perf_counter()
    vqf = {t.name: hb.heading_rms_deg(hb.run_vqf(t), t) for t in trials}
    base = {t.name: magmesh_rms(t, baseline_settings()) for t in trials}
    rows = []
    for var in variants:
        per = {t.name: magmesh_rms(t, var.settings) for t in trials}
        rows.append({"variant": var.name, "setting": var.setting, "value": var.value,
                     "baseline_value": var.baseline_value, **score_row(per, vqf, base)})
    rows.sort(key=lambda r: (-r["max_increase_deg"], -r["worst_deg"], r["variant"]))
    summary = {"n_variants": len(rows),
               "n_all_at_or_below_vqf": sum(r["all_at_or_below_vqf"] for r in rows),
               "n_mean_and_worst_below_vqf": sum(r["mean_below_vqf"] and r["worst_below_vqf"] for r in rows)}
    return {"profile": PROFILE, "trials": [t.name for t in trials],
            "vqf": score_row(vqf, vqf, None), "baseline": score_row(base, vqf, None),
            "rows": rows, "summary": summary, "wall_s": time.perf_counter() - t0}


def _short(name: str) -> str:
    return name.split("_", 1)[0]


def format_text(r: dict) -> str:
    trials = r["trials"]
    n = len(trials)
    w = max([len("variant"), *(len(x["variant"]) for x in r["rows"])]) + 2
    head = (f"{'variant':<{w}}" + "".join(f"{_short(t):>6}" for t in trials)
            + f"{'mean':>7}{'worst':>7}{'max +Δ':>8}{'at':>4}  {'≤vqf':>5}  mean<vqf  worst<vqf")
    lines = [f"Sensitivity of the {r['profile']} profile on BROAD: movement RMS heading error (deg), one setting "
             f"changed at a time; sorted by max +Δ (the largest increase over the baseline on one trial)",
             "trials: " + ", ".join(trials), head]

    def line(label: str, x: dict, delta: str = "", on: str = "") -> str:
        return (f"{label:<{w}}" + "".join(f"{x['per_trial_deg'][t]:6.2f}" for t in trials)
                + f"{x['mean_deg']:7.2f}{x['worst_deg']:7.2f}{delta:>8}{on:>4}  "
                + f"{str(x['n_at_or_below_vqf']) + '/' + str(n):>5}  "
                + f"{'yes' if x['mean_below_vqf'] else 'NO':>8}  {'yes' if x['worst_below_vqf'] else 'NO':>9}")

    v = r["vqf"]
    lines.append(f"{'vqf':<{w}}" + "".join(f"{v['per_trial_deg'][t]:6.2f}" for t in trials)
                 + f"{v['mean_deg']:7.2f}{v['worst_deg']:7.2f}")
    lines.append(line(f"{r['profile']} (baseline)", r["baseline"]))
    for x in r["rows"]:
        lines.append(line(x["variant"], x, f"{x['max_increase_deg']:+.2f}", _short(x["max_increase_trial"])))
    s = r["summary"]
    lines.append(f"summary: {s['n_all_at_or_below_vqf']} of {s['n_variants']} variants at or below vqf on all "
                 f"{n} trials; {s['n_mean_and_worst_below_vqf']} of {s['n_variants']} keep mean and worst below "
                 f"vqf's ({v['mean_deg']:.2f}, {v['worst_deg']:.2f}); baseline {r['baseline']['n_at_or_below_vqf']}/{n}, "
                 f"mean {r['baseline']['mean_deg']:.2f}, worst {r['baseline']['worst_deg']:.2f}")
    for name, why in r.get("skipped_variants", {}).items():
        lines.append(f"skipped variant {name}: {why}")
    for name, why in r.get("skipped_trials", {}).items():
        lines.append(f"skipped trial {name}: {why}")
    lines.append(f"wall time {r['wall_s']:.0f} s")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.heading_sensitivity", description=__doc__.split("\n\n")[0])
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--trials", type=Path, default=None, help="directory of BROAD trial files (default data/broad)")
    p.add_argument("--factors", default=",".join(_fmt(f) for f in DEFAULT_FACTORS),
                   help="comma-separated factors for the float settings (default 0.5,2)")
    p.add_argument("--settings", default=None, help="comma-separated profile settings to vary (default: all)")
    p.add_argument("--max-s", type=float, default=None, help="replay only the first this many seconds of each trial")
    a = p.parse_args(argv)
    try:
        factors = [float(x) for x in a.factors.split(",") if x.strip()]
    except ValueError:
        p.error(f"--factors must be comma-separated numbers, got {a.factors!r}")
    if not factors or any(not np.isfinite(f) or f < 0 for f in factors):
        p.error(f"--factors must be finite numbers ≥ 0, got {a.factors!r}")
    only = [x.strip() for x in a.settings.split(",") if x.strip()] if a.settings else None
    try:
        variants, skipped_variants = make_variants(factors, only)
        trials, skipped_trials = load_trials(a.trials, a.max_s)
    except (ValueError, FileNotFoundError) as e:
        p.error(str(e))
    if not trials:
        p.error("no scorable trial")
    r = study(trials, variants)
    r.update(factors=factors, skipped_variants=skipped_variants, skipped_trials=skipped_trials, max_s=a.max_s)
    print(json.dumps(r, indent=1, default=lambda o: dataclasses.asdict(o)) if a.json else format_text(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
