"""Choosing the ``imu_only`` heading profile's values without the truth, and judging the choice on trials it
was not made on.

``python -m bench.heading_selection [--json] [--trials DIR] [--factors a,b,c] [--settings a,b,...] [--horizon-s H]
[--max-s S]``

**The criterion** (:func:`criterion`, computed from the sensors and the filter's own output only): the
magnetometer's heading predicted ``HORIZON_S`` (5 s) ahead. At a time ``t`` the filter's attitude
``q(t)`` is carried to ``t + H`` by the gyro alone, ``q_p = q(t) ⊗ G(t)⁻¹ ⊗ G(t+H)`` (``G``: the
gyro's own attitude, integrated once per recording with a bias taken from the recording's still
stretches); at ``t + H`` the magnetometer, levelled with the filter's tilt at ``t + H``, says where
north is. The prediction error is the heading difference between the two, wrapped to ±180°. The
criterion of a recording is its RMS over every ``STEP_S`` (0.1 s) after the first second, each squared
error capped at ``CAP_DEG`` (30°)², over the instants ``t + H`` whose field strength is within
``STRENGTH_TOL`` (5 %) of the recording's first second (a fixed test on the raw magnitude, the same
for every candidate, so that no setting can choose which samples it is judged on). Over several
recordings the criterion is the mean of theirs; the candidate with the smallest wins (ties: the
earlier in the grid, whose first candidate is the profile itself).

Why this and not the usual innovation statistics: the one-step magnetometer innovations of this
filter are far from white — the handheld board's field direction wanders by several degrees with its
motion, for seconds at a time — and their normalized squares (NIS) or their Gaussian likelihood, over
the eight BROAD trials, both prefer a magnetometer noise halved (NIS over accepted updates 0.027 at the
profile, 0.107 at ×0.5; the innovation likelihood likewise falls monotonically as the noise does): a
filter that follows the wander predicts the next sample best. Five seconds ahead, the magnetometer's
error is nearly independent of the filter's error at ``t`` (the filter has only seen the field up to
``t``), so the prediction error's mean square is the filter's own heading error's, plus the
magnetometer's and the gyro's over ``H``, which are the same for every candidate: a filter that follows
the wander, or one that lets the gyro drift, both pay. A user can compute it on any unlabelled
recording. Horizons of 1, 2, 5 and 10 s ranked the one-at-a-time variants of the profile nearly alike; 5 s
was taken. Those exploratory runs also showed each variant's truth figure: the choice of the criterion,
though not of any value, was made having seen them (the README says so too).

The criterion never receives the truth: :func:`strip_truth` gives it a copy of the trial whose
``quat_true`` is NaN and whose ``movement`` mask (BROAD's, derived from the optical motion data) is
all false; ``tests/test_heading_selection.py`` checks that scrambling both leaves it unchanged.

**The search space** (:data:`SEARCH_SETTINGS`): the five continuous values the sensitivity study
(``bench/heading_sensitivity.py``) shows to matter most after the tilt-loop limit —
``mag_noise_nt``, ``gyro_noise_rad_s_rt_hz``, ``gravity_lpf_tau_s``, ``gravity_lpf_noise_m_s2``,
``field_strength_tol_frac`` — each at the profile's value times each of :data:`DEFAULT_FACTORS`
(1/√2, 1, √2): a full grid of 3⁵ = 243 candidates, every one replayed (compiled filter) on every trial
once; the criterion of a candidate on a set of trials is then a mean over table rows.

**The evaluation**: leave one trial out. For each trial ``k`` the candidate is chosen by the criterion
on the other trials only (:func:`choose` is handed a list without ``k``), then scored on ``k`` against
the optical truth (BROAD's metric, ``heading_rms_deg``) beside the profile as it is and VQF (online, its
defaults) in the same run. Also: the candidate the criterion chooses on all trials, and its truth
figures. As diagnostics only (never used to choose): the truth figure of every candidate, the best the
grid holds by the truth (an oracle no user has), and the rank correlation between the criterion and the
truth over the candidates.

Nothing here is random (the filter, VQF, the criterion and the metric are deterministic).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench import heading_broad as hb
from services.heading_fuser import profiles
from services.heading_fuser.core import Settings

PROFILE = profiles.IMU_ONLY
SEARCH_SETTINGS = ("mag_noise_nt", "gyro_noise_rad_s_rt_hz", "gravity_lpf_tau_s", "gravity_lpf_noise_m_s2",
                   "field_strength_tol_frac")
DEFAULT_FACTORS = (1.0 / math.sqrt(2.0), 1.0, math.sqrt(2.0))

HORIZON_S = 5.0
STEP_S = 0.1
CAP_DEG = 30.0
STRENGTH_TOL = 0.05
REF_S = 1.0  # the field strength's reference: the median over the recording's first second
STILL_WINDOW_S = 1.0  # the gyro's bias: its median where the 1-s mean of |ω| is below STILL_RAD_S
STILL_RAD_S = 0.03


# ---- the truth kept away --------------------------------------------------------------------------------


def strip_truth(trial: hb.Trial) -> hb.Trial:
    """A copy of ``trial`` with no truth in it: ``quat_true`` all NaN, ``movement`` all false."""
    return hb.Trial(trial.name, trial.rate_hz, trial.gyro_rad_s.copy(), trial.accel_m_s2.copy(),
                    trial.mag_nt.copy(), np.full_like(trial.quat_true, np.nan),
                    np.zeros_like(trial.movement, dtype=bool))


# ---- the criterion --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Prepared:
    """What the criterion needs of a recording, computed once: the truth-free trial, the gyro's bias and
    integrated attitude ``G`` (one row per sample), and the instants it is evaluated at."""

    trial: hb.Trial
    gyro_bias_rad_s: np.ndarray
    gyro_attitude: np.ndarray  # (N, 4): G[i], the bias-corrected gyro integrated to sample i
    i0: np.ndarray  # the prediction's start samples
    i1: np.ndarray  # ... and its end samples (i0 + H), only those with the field's strength near the reference
    frac_kept: float


def still_gyro_bias(gyro: np.ndarray, rate_hz: float) -> np.ndarray:
    """The gyro's median over the samples whose 1-s mean rate magnitude is below ``STILL_RAD_S`` (zero when
    the recording never stands still that long)."""
    n = max(1, int(round(STILL_WINDOW_S * rate_hz)))
    mean_rate = np.convolve(np.linalg.norm(gyro, axis=1), np.ones(n) / n, "same")
    still = mean_rate < STILL_RAD_S
    return np.median(gyro[still], axis=0) if still.sum() > n else np.zeros(3)


def gyro_attitude(gyro: np.ndarray, rate_hz: float, bias: np.ndarray) -> np.ndarray:
    """``G[i]``: the body's attitude at sample i relative to sample 0 from the bias-corrected gyro alone
    (sample i's rate over the step into it, the replay's convention: the first step is of 0 s)."""
    rv = (gyro - bias) / rate_hz
    ang = np.linalg.norm(rv, axis=1)
    axis = rv / np.maximum(ang, 1e-300)[:, None]
    dq = np.column_stack([np.cos(ang / 2), axis * np.sin(ang / 2)[:, None]])
    out = np.empty((len(rv), 4))
    w, x, y, z = 1.0, 0.0, 0.0, 0.0
    out[0] = (w, x, y, z)
    for i, (qw, qx, qy, qz) in enumerate(dq[1:].tolist(), start=1):
        w, x, y, z = (w * qw - x * qx - y * qy - z * qz, w * qx + x * qw + y * qz - z * qy,
                      w * qy - x * qz + y * qw + z * qx, w * qz + x * qy - y * qx + z * qw)
        nrm = math.sqrt(w * w + x * x + y * y + z * z)
        w, x, y, z = w / nrm, x / nrm, y / nrm, z / nrm
        out[i] = (w, x, y, z)
    return out


def prepare(trial: hb.Trial, horizon_s: float = HORIZON_S) -> Prepared:
    """The criterion's view of ``trial`` (its truth stripped first)."""
    t = strip_truth(trial)
    bias = still_gyro_bias(t.gyro_rad_s, t.rate_hz)
    g = gyro_attitude(t.gyro_rad_s, t.rate_hz, bias)
    n = len(t.gyro_rad_s)
    h = max(1, int(round(horizon_s * t.rate_hz)))
    first = int(round(REF_S * t.rate_hz)) + 1
    i0 = np.arange(first, max(first, n - h), max(1, int(round(STEP_S * t.rate_hz))))
    i1 = i0 + h
    strength = np.linalg.norm(t.mag_nt, axis=1)
    ref = float(np.median(strength[:first]))
    keep = np.abs(strength[i1] / ref - 1.0) <= STRENGTH_TOL if len(i1) else np.zeros(0, bool)
    frac = float(keep.mean()) if len(keep) else 0.0
    return Prepared(t, bias, g, i0[keep], i1[keep], frac)


def _conj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` rotated by the rows of ``q`` (body → ENU)."""
    qv = np.column_stack([np.zeros(len(v)), v])
    return hb.quat_mul_rows(hb.quat_mul_rows(q, qv), _conj(q))[:, 1:]


def prediction_errors_rad(prep: Prepared, q: np.ndarray) -> np.ndarray:
    """The magnetometer heading at ``t + H`` against the filter's attitude at ``t`` carried there by the gyro
    (rad, wrapped to ±π), at each of ``prep``'s instants; ``q`` is the filter's attitude after each sample."""
    i0, i1, g = prep.i0, prep.i1, prep.gyro_attitude
    if len(i0) == 0:
        return np.zeros(0)
    qp = hb.quat_mul_rows(hb.quat_mul_rows(q[i0], _conj(g[i0])), g[i1])
    d = hb.quat_mul_rows(q[i1], _conj(qp))  # the filter at t+H against the prediction, about the vertical
    yaw = 2.0 * np.arctan2(d[:, 3], d[:, 0])
    mn = _rotate(q[i1], prep.trial.mag_nt[i1])  # the field levelled by the filter's tilt at t+H
    beta = np.arctan2(mn[:, 0], mn[:, 1])  # its azimuth: the filter's heading error as the magnetometer sees it
    return np.remainder(beta + yaw + np.pi, 2.0 * np.pi) - np.pi


def criterion_of(prep: Prepared, q: np.ndarray) -> float:
    """The criterion (deg) of a replay ``q`` of ``prep``'s recording."""
    e = prediction_errors_rad(prep, q)
    if len(e) == 0:
        return float("nan")
    return float(np.degrees(np.sqrt(np.mean(np.minimum(e * e, math.radians(CAP_DEG) ** 2)))))


def replay(trial: hb.Trial, settings: Settings) -> np.ndarray:
    """The filter's attitude after each sample (``run_magmesh``'s compiled replay, as ``magmesh eval`` runs it)."""
    q, _ = hb.run_magmesh(trial, settings, impl="compiled")
    return q


def criterion(trial: hb.Trial, settings: Settings, horizon_s: float = HORIZON_S) -> float:
    """The truth-free criterion (deg) of ``settings`` on one recording; ``trial``'s truth is stripped first."""
    prep = prepare(trial, horizon_s)
    return criterion_of(prep, replay(prep.trial, settings))


# ---- the search space -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Candidate:
    factors: tuple[float, ...]  # per SEARCH setting, the factor on the profile's value
    values: dict
    settings: Settings

    @property
    def is_profile(self) -> bool:
        return all(f == 1.0 for f in self.factors)


def make_grid(factors=DEFAULT_FACTORS, names=SEARCH_SETTINGS) -> list[Candidate]:
    """Every combination of the factors (1 always among them) on the named settings; the profile itself first."""
    base = profiles.values(PROFILE)
    unknown = [k for k in names if k not in base or not isinstance(base[k], float)]
    if unknown:
        raise ValueError(f"not a float setting of the {PROFILE} profile: {', '.join(unknown)}")
    order = sorted({float(f) for f in factors} | {1.0}, key=lambda f: (f != 1.0, f))
    out = []
    for combo in itertools.product(order, repeat=len(names)):
        vals = {k: base[k] * f for k, f in zip(names, combo, strict=True)}
        out.append(Candidate(tuple(combo), vals, profiles.settings(PROFILE, **vals)))
    return out


# ---- choosing and judging -------------------------------------------------------------------------------


class Table:
    """Each candidate's criterion on each trial, computed once (on the trial's truth-free copy); rows are
    keyed by the trial object itself, so a list without a trial cannot reach its row."""

    def __init__(self, candidates: list[Candidate], horizon_s: float = HORIZON_S):
        self.candidates = candidates
        self.horizon_s = horizon_s
        self._rows: dict[int, tuple[hb.Trial, np.ndarray, np.ndarray]] = {}

    def add(self, trial: hb.Trial, truth_of=None) -> None:
        """Replay every candidate on ``trial``'s truth-free copy; the criterion goes into the table.
        ``truth_of(q)``, if given, is called on each replay's attitude for the diagnostics (kept apart)."""
        prep = prepare(trial, self.horizon_s)
        crit = np.empty(len(self.candidates))
        truth = np.full(len(self.candidates), np.nan)
        for j, c in enumerate(self.candidates):
            q = replay(prep.trial, c.settings)
            crit[j] = criterion_of(prep, q)
            if truth_of is not None:
                truth[j] = truth_of(q)
        self._rows[id(trial)] = (trial, crit, truth)

    def criterion(self, trial: hb.Trial) -> np.ndarray:
        return self._rows[id(trial)][1]

    def truth(self, trial: hb.Trial) -> np.ndarray:
        return self._rows[id(trial)][2]


def choose(table: Table, trials: list[hb.Trial]) -> tuple[int, np.ndarray]:
    """The candidate with the smallest mean criterion over ``trials`` (the earliest on a tie), and that mean
    for every candidate."""
    mean = np.mean([table.criterion(t) for t in trials], axis=0)
    return int(np.argmin(mean)), mean  # argmin: the first of equal minima


def leave_one_out(table: Table, trials: list[hb.Trial]) -> list[dict]:
    """Per trial ``k``: the candidate chosen on the others (``choose`` never sees ``k``)."""
    out = []
    for k, held in enumerate(trials):
        train = [t for i, t in enumerate(trials) if i != k]
        j, mean = choose(table, train)
        out.append({"held_out": held.name, "trained_on": [t.name for t in train], "chosen": j,
                    "train_criterion_deg": float(mean[j]), "train_criterion_profile_deg": float(mean[0])})
    return out


def _summary(per: dict[str, float], vqf: dict[str, float]) -> dict:
    v = np.array([per[k] for k in vqf])
    ref = np.array(list(vqf.values()))
    return {"per_trial_deg": per, "mean_deg": float(v.mean()), "worst_deg": float(v.max()),
            "at_or_below_vqf": {k: bool(per[k] <= vqf[k]) for k in vqf},
            "n_at_or_below_vqf": int(np.sum(v <= ref)), "n_trials": len(v),
            "mean_below_vqf": bool(v.mean() < ref.mean()), "worst_below_vqf": bool(v.max() < ref.max())}


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1]) if len(a) > 1 and ra.std() > 0 and rb.std() > 0 else float("nan")


def run(trials: list[hb.Trial], candidates: list[Candidate], progress=None, horizon_s: float = HORIZON_S) -> dict:
    """The whole study: the table (criterion per candidate and trial), leave-one-out, all-trials choice,
    truth figures of the chosen ones, the profile and VQF."""
    t0 = time.perf_counter()
    if not candidates or not candidates[0].is_profile:
        raise ValueError("the grid's first candidate must be the profile itself")
    table = Table(candidates, horizon_s)
    vqf, prep_s = {}, {}
    for t in trials:
        table.add(t, truth_of=lambda q, t=t: hb.heading_rms_deg(q, t))
        vqf[t.name] = hb.heading_rms_deg(hb.run_vqf(t), t)
        prep_s[t.name] = prepare(t, horizon_s).frac_kept
        if progress:
            progress(f"{t.name}: {len(candidates)} candidates replayed ({time.perf_counter() - t0:.0f} s)")
    names = [k for k in candidates[0].values]

    def values_of(j: int) -> dict:
        return {k: float(v) for k, v in candidates[j].values.items()}

    def factors_of(j: int) -> dict:
        return {k: float(f) for k, f in zip(names, candidates[j].factors, strict=True)}

    current = {t.name: float(table.truth(t)[0]) for t in trials}
    folds = leave_one_out(table, trials)
    held = {}
    for f, t in zip(folds, trials, strict=True):
        held[t.name] = float(table.truth(t)[f["chosen"]])
        f.update(values=values_of(f["chosen"]), factors=factors_of(f["chosen"]), held_out_deg=held[t.name],
                 profile_deg=current[t.name], vqf_deg=vqf[t.name], at_or_below_vqf=held[t.name] <= vqf[t.name],
                 chosen_is_profile=candidates[f["chosen"]].is_profile)
    j_all, mean_all = choose(table, trials)
    all_truth = {t.name: float(table.truth(t)[j_all]) for t in trials}
    truth_mean = np.mean([table.truth(t) for t in trials], axis=0)
    truth_worst = np.max([table.truth(t) for t in trials], axis=0)
    j_oracle = int(np.argmin(truth_mean))
    return {
        "profile": PROFILE, "trials": [t.name for t in trials],
        "search": {"settings": names, "factors": sorted({float(x) for c in candidates for x in c.factors}),
                   "profile_values": {k: float(profiles.values(PROFILE)[k]) for k in names},
                   "n_candidates": len(candidates)},
        "criterion": {"horizon_s": horizon_s, "step_s": STEP_S, "cap_deg": CAP_DEG, "strength_tol": STRENGTH_TOL,
                      "frac_instants_kept": prep_s},
        "vqf": _summary(vqf, vqf), "profile_now": _summary(current, vqf),
        "leave_one_out": {"folds": folds, **_summary(held, vqf)},
        "all_trials": {"chosen": j_all, "values": values_of(j_all), "factors": factors_of(j_all),
                       "chosen_is_profile": candidates[j_all].is_profile, "criterion_deg": float(mean_all[j_all]),
                       "criterion_profile_deg": float(mean_all[0]), **_summary(all_truth, vqf)},
        "diagnostics": {
            "spearman_criterion_vs_truth_mean": _spearman(mean_all, truth_mean),
            "oracle_by_truth_mean": {"values": values_of(j_oracle), "mean_deg": float(truth_mean[j_oracle]),
                                     "worst_deg": float(truth_worst[j_oracle])},
            "n_candidates_all_at_or_below_vqf": int(sum(
                all(table.truth(t)[j] <= vqf[t.name] for t in trials) for j in range(len(candidates)))),
        },
        "wall_s": time.perf_counter() - t0,
    }


# ---- output ---------------------------------------------------------------------------------------------


def _short(name: str) -> str:
    return name.split("_", 1)[0]


def _fmt_values(v: dict, f: dict) -> str:
    return ", ".join(f"{k} {v[k]:.4g} (×{f[k]:.3g})" for k in v)


def format_text(r: dict) -> str:
    trials = r["trials"]
    n = len(trials)
    lo = r["leave_one_out"]
    lines = [f"Truth-free selection of the {r['profile']} profile's values, judged leave-one-trial-out on BROAD "
             f"(movement RMS heading error, deg)",
             f"search: {', '.join(r['search']['settings'])} × factors "
             f"{', '.join(f'{x:.3g}' for x in r['search']['factors'])} ({r['search']['n_candidates']} candidates)",
             f"criterion: RMS of the magnetometer heading predicted {r['criterion']['horizon_s']:g} s ahead by the "
             f"gyro from the filter's attitude (deg), mean over the training trials",
             "",
             f"{'trial':<8}{'held-out':>9}{'profile':>9}{'vqf':>7}  ≤vqf  chosen on the other trials"]
    for f in lo["folds"]:
        lines.append(f"{_short(f['held_out']):<8}{f['held_out_deg']:9.2f}{f['profile_deg']:9.2f}{f['vqf_deg']:7.2f}"
                     f"  {'yes' if f['at_or_below_vqf'] else 'NO ':>4}  "
                     + ("the profile" if f["chosen_is_profile"] else _fmt_values(f["values"], f["factors"])))
    pn, v = r["profile_now"], r["vqf"]
    lines.append(f"{'mean':<8}{lo['mean_deg']:9.2f}{pn['mean_deg']:9.2f}{v['mean_deg']:7.2f}")
    lines.append(f"{'worst':<8}{lo['worst_deg']:9.2f}{pn['worst_deg']:9.2f}{v['worst_deg']:7.2f}")
    lines.append(f"held-out: {lo['n_at_or_below_vqf']}/{n} at or below vqf; mean below vqf's: "
                 f"{'yes' if lo['mean_below_vqf'] else 'NO'}; worst below vqf's: {'yes' if lo['worst_below_vqf'] else 'NO'}")
    a = r["all_trials"]
    lines += ["", "chosen on all trials: " + ("the profile" if a["chosen_is_profile"]
                                               else _fmt_values(a["values"], a["factors"])),
              f"  criterion {a['criterion_deg']:.4f} (the profile {a['criterion_profile_deg']:.4f})",
              "  truth: " + " ".join(f"{_short(t)} {a['per_trial_deg'][t]:.2f}" for t in trials)
              + f"; mean {a['mean_deg']:.2f}, worst {a['worst_deg']:.2f}; {a['n_at_or_below_vqf']}/{n} at or below vqf"]
    d = r["diagnostics"]
    o = d["oracle_by_truth_mean"]
    lines += ["", f"diagnostics (truth, never used to choose): rank correlation criterion vs truth (mean over trials) "
              f"over the candidates {d['spearman_criterion_vs_truth_mean']:.2f}; best candidate by the truth's mean "
              f"{o['mean_deg']:.2f} (worst {o['worst_deg']:.2f}); {d['n_candidates_all_at_or_below_vqf']} of "
              f"{r['search']['n_candidates']} candidates at or below vqf on every trial"]
    for name, why in r.get("skipped_trials", {}).items():
        lines.append(f"skipped trial {name}: {why}")
    lines.append(f"wall time {r['wall_s']:.0f} s")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.heading_selection", description=__doc__.split("\n\n")[0])
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--trials", type=Path, default=None, help="directory of BROAD trial files (default data/broad)")
    p.add_argument("--factors", default=None, help="comma-separated factors on each searched value "
                   "(default 1/√2, 1, √2); 1 is always included")
    p.add_argument("--settings", default=None, help="comma-separated profile settings to search "
                   f"(default {','.join(SEARCH_SETTINGS)})")
    p.add_argument("--horizon-s", type=float, default=HORIZON_S,
                   help=f"the criterion's prediction horizon, s (default {HORIZON_S:g})")
    p.add_argument("--max-s", type=float, default=None, help="only the first this many seconds of each trial")
    a = p.parse_args(argv)
    try:
        factors = DEFAULT_FACTORS if a.factors is None else tuple(float(x) for x in a.factors.split(",") if x.strip())
    except ValueError:
        p.error(f"--factors must be comma-separated numbers, got {a.factors!r}")
    if not (np.isfinite(a.horizon_s) and a.horizon_s > 0):
        p.error(f"--horizon-s must be a number > 0, got {a.horizon_s}")
    if any(not np.isfinite(f) or f <= 0 for f in factors):
        p.error(f"--factors must be finite numbers > 0, got {a.factors!r}")
    factors = tuple(sorted(set(factors) | {1.0}))
    names = SEARCH_SETTINGS if a.settings is None else tuple(x.strip() for x in a.settings.split(",") if x.strip())
    skipped: dict[str, str] = {}
    try:
        candidates = make_grid(factors, names)
        trials = list(hb.scorable_trials(a.trials, a.max_s, skipped))
    except (ValueError, FileNotFoundError) as e:
        p.error(str(e))
    if len(trials) < 2:
        p.error("leave-one-out needs at least two scorable trials")
    r = run(trials, candidates, progress=None if a.json else (lambda m: print(m, file=sys.stderr, flush=True)),
            horizon_s=a.horizon_s)
    r.update(skipped_trials=skipped, max_s=a.max_s)
    print(json.dumps(r, indent=1, default=lambda o: dataclasses.asdict(o)) if a.json else format_text(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
