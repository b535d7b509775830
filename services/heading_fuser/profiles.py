"""Named settings profiles of the heading fuser.

* ``road_vehicle`` — :class:`core.Settings` defaults: an automotive MEMS IMU at ~100 Hz and a
  calibrated magnetometer at ~50 Hz on a car, with a differential compass (DMC) to say when the field
  is disturbed.
* ``imu_only`` — one IMU with one magnetometer and nothing else (no DMC, no truth, no per-recording
  tuning): a handheld or body-worn sensor turned every way. Every value is from the sensor's noise
  as measured at rest, from its datasheet class, or estimated online while it runs; the heading
  README lists each with its reason. The same settings serve every recording.
"""

from __future__ import annotations

import dataclasses

from .core import Settings

ROAD_VEHICLE = "road_vehicle"
IMU_ONLY = "imu_only"

_IMU_ONLY = dict(
    # gyro: rest noise 0.0016 rad/s per sample at 285.7 Hz (9.5e-5 rad/s/√Hz); the process noise also
    # carries the scale-factor and misalignment error of a MEMS gyro turned fast (≈0.5 % of |ω|)
    gyro_noise_rad_s_rt_hz=0.002,
    gyro_rate_noise_frac_rt_hz=0.0,
    gyro_bias_walk_rad_s2_rt_hz=1e-4,
    gyro_bias_init_std_rad_s=0.005,
    init_duration_s=1.0,
    # accelerometer: gravity from the inertial-frame low-pass (linear acceleration averages out), the
    # raw sample only at rest; rest thresholds of a handheld MEMS IMU (2°/s, 0.5 m/s², 1.5 s)
    accel_noise_m_s2=0.4,
    accel_noise_per_rate_m_s2_per_rad_s=1.0,
    accel_rejection_m_s2=3.0,
    accel_update_period_s=0.02,
    gravity_lpf_tau_s=3.0,
    gravity_lpf_noise_m_s2=0.3,
    gravity_lpf_order=2,  # VQF's second-order Butterworth: a 1 Hz back-and-forth acceleration leaks ~9× less into tilt
    gravity_lpf_in_estimate=True,  # in the filter's own (corrected) frame: the gyro-only one drifts in fast turns
    # ... which closes a loop through the low-pass's lag: the tilt gain held below 1.7/τ, 85 % of that loop's
    # stability limit 2/τ (without it a noise figure halved or τ doubled made the tilt oscillate and grow); the
    # margin chosen on the BROAD figures (1/τ and √2/τ cost trials 07 and 30 their margin to VQF)
    gravity_lpf_loop_gain=1.7,
    rest_detection=True,
    # magnetometer: per-axis noise at rest ≈ 700 nT; lag estimated online
    mag_noise_nt=3000.0,
    mag_update_period_s=0.02,
    mag_delay_online=True,
    quasi_static_var_nt2=4e6,
    quasi_static_dip_var_rad2=0.003,
    quasi_static_heading_rad=0.1,
    # the heading test on the field as the gyro carries it: a board turned about every axis moves Euler yaw minus the
    # integrated vertical rate by ~0.9 rad per second (median, trial 30) with a clean field
    heading_test_gyro_frame=True,
    field_strength_tol_frac=0.05,
    field_dip_tol_rad=0.12,
    recovery_slew_rad_s=0.035,
    rejection_timeout_s=20.0,
    recovery_exit_rad=0.1,
    # ... judged on the mean innovation over the hold: the board's magnetometer heading in motion scatters by more
    # than 0.1 rad sample to sample (2.7–11° RMS per trial against the optical attitude), so a per-sample test only
    # passes once it rests
    recovery_exit_mean=True,
    disturbed_noise_gain=30.0,
    hard_iron_tracking=True,
    hard_iron_noise_gain=2.0,
    # the magnet that moves with the sensor estimated from the sensor's own rotation (not from the attitude,
    # which a field off its reference has already made uncertain), used once observable and stronger than the
    # strength tolerance
    hard_iron_from_rotation=True,
)

PROFILES: dict[str, dict] = {ROAD_VEHICLE: {}, IMU_ONLY: _IMU_ONLY}


def values(name: str) -> dict:
    """The profile's settings (only those that differ from the defaults)."""
    if name not in PROFILES:
        raise ValueError(f"unknown heading profile {name!r}; known: {', '.join(PROFILES)}")
    return dict(PROFILES[name])


def settings(name: str, **overrides) -> Settings:
    """:class:`core.Settings` of a profile, with ``overrides`` on top."""
    v = values(name)
    v.update(overrides)
    return Settings(**v)


def names() -> list[str]:
    return list(PROFILES)


assert all(k in {f.name for f in dataclasses.fields(Settings)} for p in PROFILES.values() for k in p)
