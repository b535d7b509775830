"""How the turntable simulator's free settings were chosen (``python -m bench.turntable_calibration``).

The paper (docs/methods.md#dmc-lab) gives neither its compass's field unit, nor its sources' sizes and distances,
nor how long a turn took. This search chooses them together on calibration runs only (cabinet and mixed runs,
seeds 101–103, 72 turns each; ``magmesh eval dmc`` judges other seeds) so that the paper's threshold rows come
within reach: the loss sums, over the four threshold sets of its Table 1 (DMC) and Table 2 (one compass), the
squared distance outside the paper's range of RP (per 5 points), MP (per 2 points) and WP read as a 95 % bound
(per 2°), plus the undisturbed heading error's 99th percentile outside 0.8–1.2° (per 0.1°: the paper's "better
than 1.2°"). Sources are held to plausible sizes (a hand-held magnet ≤ 15 A·m², a steel cabinet ≤ 200 A·m²,
brought from ≥ 1.5 m, no closer than 0.15 m), a turn to at least 36 s, and at least 5 % of the turns to no source.
The output unit is also the compass's resolution.

Two phases, every random draw seeded: ``--random N`` settings drawn over wide ranges, then ``--refine M`` steps
of a local search from the best (two settings perturbed per step, kept when the loss falls). Prints the best
settings as JSON (the unit as ``field_unit_nt``); the defaults of ``TurntableSettings`` are one such result,
rounded. A run takes about a second per evaluated setting.
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np

SEEDS = (101, 102, 103)
RUNS = ("cabinet", "mixed")
TURNS = 72
QUIET_P99_DEG = (0.8, 1.2)
#: plausible bounds: a hand-held magnet, a steel cabinet, brought from afar, no closer than the table's edge, a turn
#: "very slowly" (at least 36 s: a sample no more often than every second), some turns without a source
LIMITS = {"magnet_am2": 15.0, "cabinet_am2": 200.0, "approach_m": (1.5, 3.0), "closest_m": 0.15,
          "turn_s": (36.0, 288.0), "quiet": 0.05}
FREE = ("closest_m", "dwell_exponent", "magnet_moment_am2", "cabinet_moment_am2", "quiet_turn_probability",
        "approach_start_m", "height_span_m", "turn_s", "cal_offset_err_nt", "cal_matrix_err", "unit")


def rows(settings: dict, unit_nt: float, seeds=SEEDS, runs=RUNS, turns=TURNS) -> tuple[list, float]:
    """(per threshold set and detector: kind, set, RP, MP, WP95, paper range), undisturbed error p99."""
    from bench import dmc_training as T
    from bench import eval_dmc as E

    drives = [T.simulate_lab(r, s, turns=turns, mag_resolution_nt=unit_nt, **settings) for r in runs for s in seeds]
    err = np.concatenate([d.heading_err_deg for d in drives])
    quiet = ~np.concatenate([d.source_active for d in drives])
    q99 = float(np.percentile(err[quiet], 99)) if quiet.any() else float("nan")
    out = []
    for i, th in enumerate(E.paper_sets(unit_nt)):
        for kind, valid, paper in (("single", T.single_valid(drives, th), E.PAPER_TABLE2[i]),
                                   ("dmc", T.threshold_valid(drives, th), E.PAPER_TABLE1[i])):
            m = T.metrics(valid, err)
            out.append((kind, i + 1, m.rp_pct, m.mp_pct, m.wp_p95_deg, paper))
    return out, q99


def loss(rs: list, quiet_p99: float) -> float:
    total = 0.0 if quiet_p99 != quiet_p99 else (
        max(QUIET_P99_DEG[0] - quiet_p99, 0.0, quiet_p99 - QUIET_P99_DEG[1]) / 0.1) ** 2
    for _kind, _i, rp, mp, wp95, p in rs:
        for v, (lo, hi), scale in ((rp, p["rp_pct"], 5.0), (mp, p["mp_pct"], 2.0), (wp95, p["wp_deg"], 2.0)):
            total += 100.0 if v != v else (max(lo - v, 0.0, v - hi) / scale) ** 2
    return total


def _bounded(o: dict) -> dict:
    o = dict(o)
    lo, hi = o["closest_m"]
    lo = min(max(lo, LIMITS["closest_m"]), 1.0)
    o["closest_m"] = (lo, max(hi, lo + 0.01))
    a, b = sorted(o["magnet_moment_am2"])
    o["magnet_moment_am2"] = (min(max(a, 0.05), LIMITS["magnet_am2"]), min(max(b, a), LIMITS["magnet_am2"]))
    a, b = sorted(o["cabinet_moment_am2"])
    o["cabinet_moment_am2"] = (min(max(a, 1.0), LIMITS["cabinet_am2"]), min(max(b, a), LIMITS["cabinet_am2"]))
    # (some quiet turns always: the undisturbed error is what they show, and the loss holds it to the paper's)
    o["quiet_turn_probability"] = min(max(o["quiet_turn_probability"], LIMITS["quiet"]), 0.6)
    o["dwell_exponent"] = max(o["dwell_exponent"], 0.2)
    o["height_span_m"] = min(max(o["height_span_m"], 0.0), 0.6)
    o["approach_start_m"] = min(max(o["approach_start_m"], o["closest_m"][1] + 0.3, LIMITS["approach_m"][0]),
                                LIMITS["approach_m"][1])
    o["turn_s"] = min(max(o["turn_s"], LIMITS["turn_s"][0]), LIMITS["turn_s"][1])
    return o


def _draw(rng: np.random.Generator) -> dict:
    lo = rng.uniform(0.15, 0.5)
    return _bounded({
        "unit": float(np.exp(rng.uniform(math.log(10.0), math.log(150.0)))), "turn_s": float(rng.choice([36, 72, 144])),
        "closest_m": (lo, lo + rng.uniform(0.02, 1.2)), "dwell_exponent": rng.uniform(0.3, 8.0),
        "magnet_moment_am2": tuple(np.exp(rng.uniform(math.log(0.3), math.log(15.0), 2))),
        "cabinet_moment_am2": tuple(np.exp(rng.uniform(math.log(10.0), math.log(200.0), 2))),
        "quiet_turn_probability": rng.uniform(0.0, 0.4), "approach_start_m": rng.uniform(1.5, 3.0),
        "height_span_m": rng.uniform(0.0, 0.5), "cal_offset_err_nt": float(np.exp(rng.uniform(math.log(30), math.log(400)))),
        "cal_matrix_err": float(np.exp(rng.uniform(math.log(0.001), math.log(0.02))))})


def _perturb(rng: np.random.Generator, o: dict, step: float) -> dict:
    o = dict(o)
    for k in rng.choice(FREE, size=2, replace=False):
        if k == "quiet_turn_probability":
            o[k] = o[k] + rng.normal(0.0, 0.05)
        elif isinstance(o[k], tuple):
            o[k] = tuple(v * math.exp(rng.normal(0.0, 2 * step)) for v in o[k])
        else:
            o[k] = o[k] * math.exp(rng.normal(0.0, 2 * step))
    return _bounded(o)


def evaluate(o: dict, **kw) -> float:
    s = {k: v for k, v in o.items() if k != "unit"}
    return loss(*rows(s, o["unit"], **kw))


def search(n_random: int, n_refine: int, seed: int, start: dict | None = None, progress=None) -> tuple[dict, float]:
    rng = np.random.default_rng([seed, 0x7AB1E])
    best, best_l = (_bounded(start), evaluate(_bounded(start))) if start else (None, float("inf"))
    for _ in range(n_random):
        o = _draw(rng)
        v = evaluate(o)
        if v < best_l:
            best, best_l = o, v
    for i in range(n_refine):
        o = _perturb(rng, best, 0.15 if i < n_refine // 2 else 0.07)
        v = evaluate(o)
        if v < best_l:
            best, best_l = o, v
            if progress:
                progress(f"step {i}: loss {v:.2f}, {o['unit']:.1f} nT per unit")
    return best, best_l


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.turntable_calibration", description=__doc__.split("\n\n")[0])
    p.add_argument("--random", type=int, default=400, help="settings drawn at random first")
    p.add_argument("--refine", type=int, default=300, help="local-search steps from the best")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--start", help="settings (JSON, as printed) to start the local search from")
    a = p.parse_args(argv)
    start = None
    if a.start:
        try:
            raw = json.loads(a.start)
            start = {k: (tuple(v) if isinstance(v, list) else v) for k, v in raw.items() if k in FREE}
            start["unit"] = float(raw.get("field_unit_nt", raw.get("unit")))
            missing = [k for k in FREE if k not in start]
            if missing:
                raise ValueError(f"missing {', '.join(missing)}")
        except (ValueError, TypeError) as e:
            print(f"--start must be the JSON this command prints ({e}).", file=sys.stderr)
            return 2
    best, v = search(a.random, a.refine, a.seed, start, progress=lambda s: print(s, file=sys.stderr))
    out = {"loss": round(v, 3), "field_unit_nt": round(best["unit"], 2)}
    out.update({k: (list(x) if isinstance(x, tuple) else x) for k, x in best.items() if k != "unit"})
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
