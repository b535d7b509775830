"""bench.heading_selection: the criterion never sees the truth, leave-one-out never lets a fold see its
held-out trial, and the study's output (BROAD excerpts and a tiny grid)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench import heading_broad as hb
from bench import heading_selection as H
from services.heading_fuser import profiles

RATE = 285.714
FILES = ("07_undisturbed_fast_rotation_B", "10_undisturbed_slow_translation_A", "30_disturbed_stationary_magnet_C")


def _excerpt(name: str, seconds: float = 40.0) -> hb.Trial:
    return hb.load_trial(hb.BROAD_DIR / f"{name}.hdf5").sliced(int(seconds * RATE))


@pytest.fixture(scope="module")
def excerpts() -> list[hb.Trial]:
    return [_excerpt(n) for n in FILES]


def _scrambled(trial: hb.Trial, seed: int) -> hb.Trial:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=trial.quat_true.shape)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return hb.Trial(trial.name, trial.rate_hz, trial.gyro_rad_s, trial.accel_m_s2, trial.mag_nt, q,
                    rng.random(len(trial.movement)) < 0.5)


def test_strip_truth_keeps_the_sensors_and_nothing_else(excerpts):
    t = excerpts[0]
    s = H.strip_truth(t)
    assert np.isnan(s.quat_true).all() and s.quat_true.shape == t.quat_true.shape
    assert not s.movement.any() and len(s.movement) == len(t.movement)
    for k in ("gyro_rad_s", "accel_m_s2", "mag_nt"):
        assert np.array_equal(getattr(s, k), getattr(t, k))
    assert np.isfinite(t.quat_true).any() and t.movement.any()  # the original untouched


def test_criterion_unchanged_when_the_truth_is_scrambled(excerpts):
    t = excerpts[0]
    s = profiles.settings(profiles.IMU_ONLY)
    c = H.criterion(t, s)
    assert np.isfinite(c) and c > 0
    for seed in (1, 2):
        assert H.criterion(_scrambled(t, seed), s) == c
    # ... and it does depend on the sensors and the settings (the test above can fail)
    assert H.criterion(t, profiles.settings(profiles.IMU_ONLY, mag_noise_nt=300.0)) != c
    turned = hb.Trial(t.name, t.rate_hz, t.gyro_rad_s, t.accel_m_s2, t.mag_nt[:, [1, 0, 2]] * [1, -1, 1],
                      t.quat_true, t.movement)
    assert H.criterion(turned, s) != c


def test_grid_starts_with_the_profile_and_changes_only_the_searched_values():
    grid = H.make_grid((0.5, 1.0, 2.0), ("mag_noise_nt", "gravity_lpf_tau_s"))
    assert len(grid) == 9
    base = profiles.values(profiles.IMU_ONLY)
    assert grid[0].is_profile and grid[0].settings == profiles.settings(profiles.IMU_ONLY)
    assert sum(c.is_profile for c in grid) == 1
    for c in grid:
        assert c.settings == profiles.settings(profiles.IMU_ONLY, **c.values)
        assert c.values == {"mag_noise_nt": base["mag_noise_nt"] * c.factors[0],
                            "gravity_lpf_tau_s": base["gravity_lpf_tau_s"] * c.factors[1]}
    assert len(H.make_grid()) == 3 ** len(H.SEARCH_SETTINGS)
    with pytest.raises(ValueError):
        H.make_grid((1.0,), ("gravity_lpf_order",))  # an int: not searched


def test_leave_one_out_never_sees_the_held_out_trial(excerpts):
    grid = H.make_grid((0.25, 1.0, 4.0), ("mag_noise_nt",))
    clean = [e.sliced(int(20 * RATE)) for e in excerpts]
    bad = clean[2]
    rng = np.random.default_rng(0)
    poisoned = hb.Trial(bad.name, bad.rate_hz, bad.gyro_rad_s, bad.accel_m_s2,
                        bad.mag_nt + rng.normal(0.0, 8000.0, bad.mag_nt.shape) + [15000.0, 0.0, 0.0],
                        bad.quat_true, bad.movement)
    out = {}
    for label, trials in (("clean", clean), ("poisoned", [*clean[:2], poisoned])):
        table = H.Table(grid)
        for t in trials:
            table.add(t)
        out[label] = (table, H.leave_one_out(table, trials), trials)
    (tc, fc, trc), (tp, fp, trp) = out["clean"], out["poisoned"]
    assert not np.array_equal(tc.criterion(trc[2]), tp.criterion(trp[2]))  # the poison changes its own row
    for k in range(2):
        assert np.array_equal(tc.criterion(trc[k]), tp.criterion(trp[k]))  # ... and no other
    for f, t in zip(fc, trc, strict=True):
        assert t.name not in f["trained_on"] and len(f["trained_on"]) == 2
    # the fold that holds the poisoned trial out is exactly as without the poison
    assert fp[2] == fc[2]
    # the folds that train on it see it (their training criterion moves)
    for k in range(2):
        assert fp[k]["train_criterion_profile_deg"] != fc[k]["train_criterion_profile_deg"]
    # choose() on a list without a trial cannot reach its row
    j, mean = H.choose(tp, trp[:2])
    assert mean[j] == fp[2]["train_criterion_deg"] and j == fp[2]["chosen"]
    with pytest.raises(KeyError):
        H.choose(H.Table(grid), trp[:1])


def test_run_scores_the_chosen_candidate_on_the_held_out_trial(excerpts):
    grid = H.make_grid((2.0,), ("mag_noise_nt",))
    assert len(grid) == 2
    r = H.run(excerpts, grid)
    assert r["trials"] == [t.name for t in excerpts]
    lo = r["leave_one_out"]
    assert len(lo["folds"]) == 3
    for f, t in zip(lo["folds"], excerpts, strict=True):
        assert f["held_out"] == t.name and t.name not in f["trained_on"]
        q, _ = hb.run_magmesh(t, grid[f["chosen"]].settings)
        assert f["held_out_deg"] == hb.heading_rms_deg(q, t) == lo["per_trial_deg"][t.name]
        q, _ = hb.run_magmesh(t, profiles.settings(profiles.IMU_ONLY))
        assert f["profile_deg"] == hb.heading_rms_deg(q, t) == r["profile_now"]["per_trial_deg"][t.name]
        assert f["vqf_deg"] == r["vqf"]["per_trial_deg"][t.name]
        assert f["at_or_below_vqf"] == (f["held_out_deg"] <= f["vqf_deg"])
    assert r["vqf"]["per_trial_deg"][excerpts[0].name] == hb.heading_rms_deg(hb.run_vqf(excerpts[0]), excerpts[0])
    assert lo["worst_deg"] == max(lo["per_trial_deg"].values())
    a = r["all_trials"]
    assert a["chosen"] == H.choose(_table_of(grid, excerpts), excerpts)[0]
    assert set(a["per_trial_deg"]) == set(r["trials"])
    assert r["search"]["n_candidates"] == 2
    text = H.format_text(r)
    assert "held-out" in text and "chosen on all trials" in text
    json.dumps(r)


def _table_of(grid, trials):
    table = H.Table(grid)
    for t in trials:
        table.add(t)
    return table


def test_command_json(capsys):
    assert H.main(["--json", "--max-s", "40", "--settings", "mag_noise_nt", "--factors", "2"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["search"]["settings"] == ["mag_noise_nt"] and r["search"]["n_candidates"] == 2
    assert len(r["leave_one_out"]["folds"]) == len(r["trials"]) >= 2
    assert r["max_s"] == 40
