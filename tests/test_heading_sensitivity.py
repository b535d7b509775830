"""bench.heading_sensitivity: the variants change one setting each, and the baseline is the profile as
``magmesh eval heading`` runs it (a short slice of one BROAD trial)."""

from __future__ import annotations

import dataclasses

from bench import heading_broad as hb
from bench import heading_sensitivity as S
from services.heading_fuser import profiles


def _changed(a, b) -> set[str]:
    da, db = dataclasses.asdict(a), dataclasses.asdict(b)
    return {k for k in da if not (da[k] == db[k] or (da[k] != da[k] and db[k] != db[k]))}  # nan == nan


def test_every_variant_changes_its_one_setting():
    base = S.baseline_settings()
    assert base == profiles.settings(profiles.IMU_ONLY)
    variants, skipped = S.make_variants()
    values = profiles.values(profiles.IMU_ONLY)
    assert variants
    for v in variants:
        assert _changed(v.settings, base) == {v.setting}, v.name
        assert getattr(v.settings, v.setting) == v.value != values[v.setting]
    flipped = {v.setting for v in variants if isinstance(v.value, bool)}
    assert flipped == {k for k, x in values.items() if isinstance(x, bool)}
    assert "gravity_lpf_order = 1" in {v.name for v in variants}
    assert "gravity_lpf_order = 3" in skipped  # Settings accepts only 1 and 2
    assert "gyro_rate_noise_frac_rt_hz ×factor" in skipped  # 0 × any factor is the baseline


def test_study_on_a_slice_runs_baseline_and_variant():
    trial = hb.load_trial(hb.BROAD_DIR / "07_undisturbed_fast_rotation_B.hdf5").sliced(int(30 * 285.714))
    variants, _ = S.make_variants(factors=(2.0,), only=["mag_noise_nt"])
    assert [v.name for v in variants] == ["mag_noise_nt ×2"]
    (var,) = variants
    assert _changed(var.settings, profiles.settings(profiles.IMU_ONLY)) == {"mag_noise_nt"}
    assert var.settings.mag_noise_nt == 2 * profiles.values(profiles.IMU_ONLY)["mag_noise_nt"]

    r = S.study([trial], variants)
    q, _ = hb.run_magmesh(trial, profiles.settings(profiles.IMU_ONLY))
    base = hb.heading_rms_deg(q, trial)
    assert r["baseline"]["per_trial_deg"][trial.name] == base
    q, _ = hb.run_magmesh(trial, var.settings)
    mine = hb.heading_rms_deg(q, trial)
    (row,) = r["rows"]
    assert row["per_trial_deg"][trial.name] == mine
    assert mine != base  # the variant really ran with its own settings
    assert row["max_increase_deg"] == mine - base
    assert r["vqf"]["per_trial_deg"][trial.name] == hb.heading_rms_deg(hb.run_vqf(trial), trial)
    assert r["summary"]["n_variants"] == 1
    assert "mag_noise_nt ×2" in S.format_text(r)
