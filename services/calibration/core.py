"""Per-sensor and per-vehicle calibration logic of the service (pure numpy, no zenoh).

:class:`SensorCalibrator` keeps a decimated window of one magnetometer's samples, fits it
(Two-Step LS or ARLS, 2-D or 3-D, see two_step.py / arls.py) when the samples suffice
(sufficiency.py), and replaces its current parameter set only with a better one: the candidate
must fit the *current* window better than the set in use (robust relative residual, below
``improve_ratio`` of the current one's). A refused fit never replaces anything; its reason is kept
for the status and, while no usable set exists, published with ``status = "refused"``.

:class:`VehicleCalibration` adds the online GNSS-aided hard-iron EKF (online_ekf.py) for every
sensor of a vehicle: it feeds it the latest IMU attitude and each good GNSS epoch, and turns a
converged estimate into a parameter set (method "ekf") when it explains the GNSS course better than
the set in use.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from magmesh import magcal, maths

from . import arls, online_ekf, sufficiency, two_step

USABLE = ("ok", "manifest", "converging")  # statuses whose parameters cal/mag applies
#: window bound without decimation (``sample_interval_s = 0``) unless ``window_max_samples`` says otherwise
UNDECIMATED_WINDOW_SAMPLES = 100_000


@dataclass(frozen=True)
class CalibrationSettings:
    method: str = "arls"  # "arls" | "ls"
    model: str = "auto"  # "auto" (3-D when the attitude coverage allows, else 2-D) | "2d" | "3d"
    window_s: float = 600.0  # samples older than this leave the fit window
    sample_interval_s: float = 0.05  # keep at most one sample per interval (decimation)
    refit_interval_s: float = 5.0  # try a fit this often (sample time)
    field_radius_nt: float = 0.0  # > 0: scale the compensated field to this strength; 0: fitted radius
    improve_ratio: float = 0.95  # a new fit replaces the current set only below this residual ratio
    k0: float = 1.5  # IGG-III
    k1: float = 3.0  # IGG-III
    min_samples: int = 150
    min_coverage_2d: float = 0.75
    min_coverage_3d: float = 0.55
    max_axis_ratio: float = 3.0
    window_max_samples: int = 0  # samples the window keeps at most; 0: all a decimated window can hold (see below)

    def __post_init__(self):
        if self.method not in ("arls", "ls"):
            raise ValueError(f"method must be 'arls' or 'ls', got {self.method!r}")
        if self.model not in ("auto", "2d", "3d"):
            raise ValueError(f"model must be 'auto', '2d' or '3d', got {self.model!r}")
        if self.window_s <= 0 or self.sample_interval_s < 0 or self.refit_interval_s <= 0:
            raise ValueError("window_s and refit_interval_s must be > 0, sample_interval_s ≥ 0")
        if not 0 < self.improve_ratio <= 1:
            raise ValueError("improve_ratio must be in (0, 1]")
        if self.window_max_samples < 0:
            raise ValueError("window_max_samples must be ≥ 0 (0: derived from window_s and sample_interval_s)")

    @property
    def window_capacity(self) -> int:
        """Samples the fit window holds at most: ``window_max_samples``, or when 0 what decimation allows
        (kept samples are ≥ ``sample_interval_s`` apart, so ``window_s / sample_interval_s + 2`` never binds;
        without decimation :data:`UNDECIMATED_WINDOW_SAMPLES`). The oldest sample leaves first."""
        if self.window_max_samples > 0:
            return int(self.window_max_samples)
        if self.sample_interval_s > 0:
            return int(math.floor(self.window_s / self.sample_interval_s)) + 2
        return UNDECIMATED_WINDOW_SAMPLES

    @property
    def sufficiency(self) -> sufficiency.SufficiencySettings:
        return sufficiency.SufficiencySettings(
            min_samples=self.min_samples, min_coverage_2d=self.min_coverage_2d,
            min_coverage_3d=self.min_coverage_3d, max_axis_ratio=self.max_axis_ratio)

    @property
    def arls(self) -> arls.ArlsSettings:
        return arls.ArlsSettings(k0=self.k0, k1=self.k1)


@dataclass
class ParamRecord:
    """A parameter set with everything the ``cal_params`` message carries."""

    params: magcal.MagParams
    param_id: str
    status: str  # ok | refused | converging | manifest
    method: str  # ls | arls | ekf | manifest
    rmse_nt: float | None = None
    coverage_frac: float = 0.0
    n_samples: int = 0
    n_gross_rejected: int = 0
    fit_t_s: float = 0.0
    fit_duration_ms: float = 0.0
    reason: str = ""

    def message_fields(self, sensor: str) -> dict:
        p = self.params
        out = dict(
            sensor=sensor, param_id=self.param_id, status=self.status, model=p.model, method=self.method,
            offset_nt=list(p.offset_nt), matrix=list(p.matrix), field_radius_nt=float(p.field_radius_nt),
            rmse_nt=None if self.rmse_nt is None or not math.isfinite(self.rmse_nt) else float(self.rmse_nt),
            coverage_frac=float(min(max(self.coverage_frac, 0.0), 1.0)), n_samples=int(self.n_samples),
            n_gross_rejected=int(self.n_gross_rejected), observable=list(p.observable),
            fit_t_s=float(self.fit_t_s), fit_duration_ms=float(max(self.fit_duration_ms, 0.0)),
        )
        if self.reason:
            out["reason"] = self.reason
        return out

    def to_json(self) -> dict:
        d = asdict(self)
        d["params"] = {k: v for k, v in asdict(self.params).items() if k not in ("extra", "param_id")}  # (the record's)
        return d

    @classmethod
    def from_json(cls, d: dict) -> ParamRecord:
        p = d["params"]
        params = magcal.MagParams(tuple(p["offset_nt"]), tuple(p["matrix"]), float(p["field_radius_nt"]),
                                  p.get("model", "3d"), observable=tuple(p.get("observable", (True, True, True))))
        return cls(params, **{k: v for k, v in d.items() if k != "params"})


def new_param_id(sensor: str, method: str, t_s: float) -> str:
    """Unique, readable id of a parameter set: sensor, method, fit sample time, wall-clock ms."""
    return f"{sensor}-{method}-{t_s:.1f}-{int(time.time() * 1000) % 10**9:09d}"


def relative_residual(m_nt: np.ndarray, params: magcal.MagParams) -> float:
    """Robust spread of |h|/R − 1 over samples: 1.4826 · median |r − median r| (a gross error does
    not decide which parameter set is better)."""
    r = magcal.field_strength_residual(m_nt, params) / params.field_radius_nt
    return float(1.4826 * np.median(np.abs(r - np.median(r)))) if r.size else math.inf


@dataclass
class FitAttempt:
    accepted: bool
    reason: str
    record: ParamRecord | None = None  # the candidate (accepted or not)


class SensorCalibrator:
    """update(t, b) for every sample; fit(t) when due; ``current`` is the set in use.

    The window keeps each kept sample's field as float32 (what :class:`services.calibration.fleet.FleetCalibration`
    stores for a whole fleet): 24 significant bits, a few thousandths of a nT at the Earth's field, far below any
    magnetometer's noise. Both forms round identically, so their fits are the same.
    """

    def __init__(self, sensor: str, settings: CalibrationSettings = CalibrationSettings(),
                 initial: ParamRecord | None = None):
        self.sensor = sensor
        self.settings = settings
        self.capacity = settings.window_capacity
        self.current = initial
        self.reset_window()
        self.last_attempt: FitAttempt | None = None
        self.n_fits = 0
        self.n_refused = 0
        self.n_replaced = 0

    def reset_window(self):
        self.t: deque[float] = deque()
        self.m: deque[tuple[float, float, float]] = deque()
        self.last_kept_t = -math.inf
        self.last_fit_t = -math.inf

    def update(self, t_s: float, b_nt) -> None:
        st = self.settings
        if t_s < self.last_kept_t - 1.0:
            # the vehicle's clock went back (a replay restarted): the window starts again
            self.reset_window()
        if t_s - self.last_kept_t < st.sample_interval_s:
            return
        self.last_kept_t = t_s
        self.t.append(float(t_s))
        self.m.append(tuple(np.asarray(b_nt, np.float32).astype(float).tolist()))
        while self.t and self.t[0] < t_s - st.window_s:
            self.t.popleft()
            self.m.popleft()
        while len(self.t) > self.capacity:
            self.t.popleft()
            self.m.popleft()

    def due(self, t_s: float) -> bool:
        return t_s - self.last_fit_t >= self.settings.refit_interval_s

    def window(self) -> np.ndarray:
        return np.asarray(self.m, float).reshape(-1, 3)

    def choose_model(self, m: np.ndarray) -> tuple[str, sufficiency.Verdict]:
        return choose_model(m, self.settings)

    def fit(self, t_s: float) -> FitAttempt:
        """Fit the current window; replace the current set only when the candidate is better."""
        self.last_fit_t = t_s
        self.n_fits += 1
        attempt = fit_window(self.sensor, self.window(), t_s, self.current, self.settings)
        self.last_attempt = attempt
        if attempt.record is not None and attempt.record.status == "refused":
            self.n_refused += 1
        if attempt.accepted:
            self.current = attempt.record
            self.n_replaced += 1
        return attempt

    def is_better(self, cand: ParamRecord, m: np.ndarray) -> tuple[bool, str]:
        return is_better(cand, self.current, m, self.settings)

    @property
    def internal_states(self) -> dict:
        return sensor_states(len(self.t), self.n_fits, self.n_refused, self.n_replaced, self.current,
                             self.last_attempt)


def sensor_states(window_samples: int, fits: int, refused: int, replaced: int, current: ParamRecord | None,
                  attempt: FitAttempt | None) -> dict:
    """The status entry of one sensor's fits (``calibration.vehicles.{v}.sensors.{s}``)."""
    return {
        "window_samples": int(window_samples),
        "fits": int(fits),
        "refused": int(refused),
        "replaced": int(replaced),
        "current_param_id": current.param_id if current else None,
        "current_status": current.status if current else None,
        "current_method": current.method if current else None,
        "last_attempt": None if attempt is None else {"accepted": attempt.accepted, "reason": attempt.reason,
                                                      "coverage_frac": attempt.record.coverage_frac
                                                      if attempt.record else None},
    }


def choose_model(m: np.ndarray, st: CalibrationSettings, centre=None) -> tuple[str, sufficiency.Verdict]:
    """The model to fit and the sufficiency verdict (``centre``: the window's rough centre, if known)."""
    suf = st.sufficiency
    if st.model != "auto":
        return st.model, sufficiency.check_samples(m, st.model, suf, centre)
    v3 = sufficiency.check_samples(m, "3d", suf, centre)
    if v3.ok:
        return "3d", v3
    return "2d", sufficiency.check_samples(m, "2d", suf, centre)


def fit_window(sensor: str, m_all: np.ndarray, t_s: float, current: ParamRecord | None,
               st: CalibrationSettings) -> FitAttempt:
    """One fit attempt on a window of samples (N×3, oldest first): sufficiency, Two-Step LS or ARLS on the
    balanced subset, the fit checks, and whether the candidate is better than ``current``. Pure: the caller
    keeps the window, the counters and the set in use (:class:`SensorCalibrator`, and the fleet form)."""
    # the window's rough centre once (the sufficiency checks and the balanced subset each took it again)
    rough = sufficiency.rough_centre(m_all) if len(m_all) >= max(st.min_samples, 1) else None
    model, verdict = choose_model(m_all, st, rough)
    if not verdict.ok:
        return _refused(sensor, current, st, t_s, model, verdict.reason, verdict.coverage_frac, len(m_all))
    centre = current.params.offset if current is not None and current.status == "ok" else rough
    idx = sufficiency.balanced_subset(m_all, model, st.sufficiency, centre=centre)
    m = m_all[idx]
    radius = st.field_radius_nt if st.field_radius_nt > 0 else None
    if st.method == "arls":
        res = arls.fit_arls(m, model, radius, st.arls)
    else:
        res = two_step.fit_ls(m, model, radius)
    if not res.ok:
        return _refused(sensor, current, st, t_s, model, res.reason, verdict.coverage_frac, len(m))
    check = sufficiency.check_fit(m, res.params, st.sufficiency, res.weights)
    if not check.ok:
        return _refused(sensor, current, st, t_s, model, check.reason, check.coverage_frac, len(m))
    cand = ParamRecord(res.params, new_param_id(sensor, res.method, t_s), "ok", res.method, res.rmse_nt,
                       check.coverage_frac, len(m), res.n_gross_rejected, t_s, res.duration_ms)
    better, why = is_better(cand, current, m, st)
    return FitAttempt(better, why, cand)


def is_better(cand: ParamRecord, cur: ParamRecord | None, m: np.ndarray, st: CalibrationSettings) -> tuple[bool, str]:
    if cur is None or cur.status != "ok":
        return True, "first fitted parameter set"
    if cur.params.model == "3d" and cand.params.model == "2d":
        return False, "keeps the 3-D parameter set: a 2-D fit cannot replace it"
    if cur.params.model == "2d" and cand.params.model == "3d":
        return True, "3-D fit replaces the 2-D parameter set"
    r_new = relative_residual(m, cand.params)
    r_old = relative_residual(m, cur.params)
    if r_new < st.improve_ratio * r_old:
        return True, f"residual {100 * r_new:.2f}% < {100 * r_old:.2f}% of the set in use"
    return False, f"residual {100 * r_new:.2f}% not below {st.improve_ratio:g} × {100 * r_old:.2f}%"


def _refused(sensor: str, current: ParamRecord | None, st: CalibrationSettings, t_s: float, model: str, reason: str,
             coverage: float, n: int) -> FitAttempt:
    base = current.params if current is not None else magcal.MagParams(model=model)
    rec = ParamRecord(replace(base, model=model), new_param_id(sensor, "refused", t_s), "refused",
                      st.method, None, coverage, n, 0, t_s, 0.0, reason)
    return FitAttempt(False, reason, rec)


# ---- vehicle: sensors + online EKF ------------------------------------------------------------


@dataclass(frozen=True)
class OnlineSettings:
    enabled: bool = True
    gnss_window: int = 150  # fused epochs kept to judge a converged EKF estimate
    min_change_nt: float = 500.0  # an EKF offset closer than this (and than 4σ) to the set in use is not published
    improve_ratio: float = 0.8  # an EKF set must cut the GNSS heading residual of the set in use to this
    min_mount_yaw_rad: float = math.radians(0.5)  # a mounting yaw below this does not replace a fitted set
    min_interval_s: float = 30.0  # at most one EKF "ok" set per sensor in this time
    converging_publish_s: float = 5.0  # publish "converging" sets at most this often
    tilt_source: str = "level"  # "level": roll = pitch = 0 (as a car's 2-D compass is read); "accel": IMU
    imu_window_s: float = 1.0  # IMU averaging window, s (matches the GNSS speed-rate window)
    ekf: online_ekf.EkfSettings = field(default_factory=online_ekf.EkfSettings)


@dataclass
class _Epoch:
    m_nt: np.ndarray
    course_rad: float
    roll_rad: float
    pitch_rad: float
    declination_rad: float


class SensorOnline:
    """The EKF of one sensor, with the fused epochs kept to compare parameter sets."""

    def __init__(self, sensor: str, st: OnlineSettings, base: ParamRecord | None):
        self.sensor = sensor
        self.st = st
        self.epochs: deque[_Epoch] = deque(maxlen=st.gnss_window)
        self.last_converging_t = -math.inf
        self.last_ok_t = -math.inf
        self.rebase(base)

    def rebase(self, base: ParamRecord | None):
        """Restart the EKF around a parameter set (its matrix, its offset as prior)."""
        p = base.params if base is not None else magcal.IDENTITY
        self.base_id = base.param_id if base is not None else None
        self.ekf = online_ekf.HardIronEkf(self.st.ekf, p.offset, p.M)
        self.epochs.clear()

    def heading_rms(self, offset, M) -> float:
        """RMS of GNSS course − magnetic heading over the kept epochs, rad."""
        if not self.epochs:
            return math.inf
        ekf = online_ekf.HardIronEkf(self.st.ekf, offset, M)
        errs = [maths.wrap_pi(e.course_rad - ekf.heading(e.m_nt, np.asarray(offset, float), e.roll_rad,
                                                          e.pitch_rad, e.declination_rad)[0]) for e in self.epochs]
        return float(np.sqrt(np.mean(np.square(errs))))


class VehicleCalibration:
    """All sensors of one vehicle, plus its latest IMU attitude and GNSS state."""

    def __init__(self, vehicle: str, settings: CalibrationSettings, online: OnlineSettings,
                 initial: dict[str, ParamRecord] | None = None, declination_rad: float | None = None):
        self.vehicle = vehicle
        self.settings = settings
        self.online = online
        self.sensors: dict[str, SensorCalibrator] = {}
        self.onl: dict[str, SensorOnline] = {}
        self.initial = dict(initial or {})
        self.declination_override = declination_rad
        self.imu: deque[tuple[float, np.ndarray, np.ndarray]] = deque()  # (t, gyro, accel) over imu_window_s
        self.speed_rate = online_ekf.SpeedRate()
        self.mag_recent: dict[str, deque] = {}
        self.gnss_reason = ""

    def sensor(self, sid: str) -> SensorCalibrator:
        sc = self.sensors.get(sid)
        if sc is None:
            sc = self.sensors[sid] = SensorCalibrator(sid, self.settings, self.initial.get(sid))
            self.mag_recent[sid] = deque(maxlen=64)
            if self.online.enabled:
                self.onl[sid] = SensorOnline(sid, self.online, sc.current)
        return sc

    def on_mag(self, sid: str, t_s: float, b_nt) -> SensorCalibrator:
        sc = self.sensor(sid)
        sc.update(t_s, b_nt)
        self.mag_recent[sid].append((t_s, np.asarray(b_nt, float)))
        return sc

    def on_imu(self, t_s: float, gyro_rad_s, accel_m_s2) -> None:
        self.imu.append((float(t_s), np.asarray(gyro_rad_s, float), np.asarray(accel_m_s2, float)))
        while self.imu and self.imu[0][0] < t_s - self.online.imu_window_s:
            self.imu.popleft()

    def imu_mean(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Mean gyro and accelerometer over the IMU window (the span the GNSS speed rate covers)."""
        if not self.imu:
            return None
        return np.mean([g for _, g, _ in self.imu], axis=0), np.mean([a for _, _, a in self.imu], axis=0)

    def declination(self, lat_deg: float, lon_deg: float, alt_m: float) -> float:
        if self.declination_override is not None:
            return self.declination_override
        b = maths.earth_field_enu_nt(round(lat_deg, 2), round(lon_deg, 2), round(alt_m, -2))
        return maths.declination_rad(b)

    def on_gnss(self, t_s: float, g: dict) -> list[tuple[str, ParamRecord]]:
        """Feed one GNSS epoch to every sensor's EKF; return parameter sets to publish."""
        out: list[tuple[str, ParamRecord]] = []
        if not self.online.enabled:
            return out
        speed = float(g["speed_m_s"])
        rate = self.speed_rate.update(t_s, speed)
        ok, why = online_ekf.gnss_usable(g["fix_type"], int(g["num_sats"]), float(g["pdop"]), speed,
                                         self.online.ekf)
        self.gnss_reason = why
        imu = self.imu_mean()
        yaw_rate = float(imu[0][2]) if imu is not None else 0.0
        roll = pitch = 0.0
        if self.online.tilt_source == "accel" and imu is not None:
            roll, pitch = online_ekf.car_roll_pitch(imu[1], rate, speed, yaw_rate)
        decl = self.declination(float(g["lat_deg"]), float(g["lon_deg"]), float(g["alt_m"]))
        for sid, onl in self.onl.items():
            recent = [b for (tb, b) in self.mag_recent[sid] if t_s - 0.25 <= tb <= t_s + 0.05]
            if not recent:
                continue
            m = np.mean(recent, axis=0)
            sc = self.sensors[sid]
            if sc.current is not None and sc.current.param_id != onl.base_id and sc.current.method != "ekf":
                onl.rebase(sc.current)  # a new static fit: restart the EKF around it
            fused = onl.ekf.update(t_s, m, float(g["course_rad"]), roll, pitch, decl, speed, yaw_rate, ok)
            if fused:
                onl.epochs.append(_Epoch(m, float(g["course_rad"]), roll, pitch, decl))
            rec = self._maybe_ekf_record(sid, sc, onl, t_s)
            if rec is not None:
                out.append((sid, rec))
        return out

    def _maybe_ekf_record(self, sid: str, sc: SensorCalibrator, onl: SensorOnline, t_s: float) -> ParamRecord | None:
        ekf = onl.ekf
        if ekf.n_fused == 0:
            return None
        base = sc.current.params if sc.current is not None else magcal.IDENTITY
        offset = ekf.applied_offset()
        obs = ekf.observable
        observable = tuple(bool(o) for o in obs)
        if sc.current is not None and sc.current.status in ("ok", "manifest"):
            # components the EKF cannot see keep the trusted set's value, and its observability
            observable = tuple(a or b for a, b in zip(observable, base.observable, strict=True))
        M_applied = ekf.applied_matrix()
        params = magcal.MagParams.from_arrays(offset, M_applied, base.field_radius_nt, base.model, observable)
        if not ekf.converged:
            # "converging" estimates are published only while no trusted set (fitted, saved or from the
            # manifest) is in use: an estimate still converging must not displace one
            has_fit = sc.current is not None and sc.current.status in ("ok", "manifest")
            if has_fit or t_s - onl.last_converging_t < self.online.converging_publish_s:
                return None
            onl.last_converging_t = t_s
            rec = ParamRecord(params, new_param_id(sid, "ekf", t_s), "converging", "ekf", None, 0.0,
                              ekf.n_fused, ekf.n_rejected, t_s, 0.0,
                              f"online hard-iron EKF converging: offset σ {np.round(ekf.std_nt).tolist()} nT")
            sc.current = rec
            onl.base_id = rec.param_id
            return rec
        in_use_ok = sc.current is not None and sc.current.status in ("ok", "manifest")
        if in_use_ok:
            # a fitted set is replaced only on clear evidence of a changed hard iron: a shift beyond
            # min_change_nt and 4σ of the estimate, that explains the GNSS course clearly better
            shift = offset - base.offset
            sig = float(np.linalg.norm(ekf.std_nt[np.array(obs)])) if any(obs) else math.inf
            yaw_change = ekf.mount_yaw_observable and abs(ekf.mount_yaw_rad) > max(
                self.online.min_mount_yaw_rad, 4.0 * ekf.mount_yaw_std_rad)
            if np.linalg.norm(shift) < max(self.online.min_change_nt, 4.0 * sig) and not yaw_change:
                return None
            if t_s - onl.last_ok_t < self.online.min_interval_s:
                return None
        if len(onl.epochs) < min(30, self.online.gnss_window):
            return None
        rms_new = onl.heading_rms(offset, M_applied)
        rms_old = onl.heading_rms(base.offset, base.M) if sc.current is not None else math.inf
        if in_use_ok and not rms_new < self.online.improve_ratio * rms_old:
            return None
        onl.last_ok_t = t_s
        rec = ParamRecord(params, new_param_id(sid, "ekf", t_s), "ok", "ekf", None, 1.0, ekf.n_fused, ekf.n_rejected,
                          t_s, 0.0, f"GNSS heading residual {math.degrees(rms_new):.2f}° (was "
                          f"{math.degrees(rms_old):.2f}°); vertical offset "
                          f"{'estimated' if observable[2] else 'not observable, kept'}")
        sc.current = rec
        onl.base_id = rec.param_id
        # continue from the new set: same matrix, the estimate becomes the prior
        onl.ekf.prior = offset.copy()
        if in_use_ok:
            # the hard iron changed: the window's older samples describe the old one, so the next
            # static fit must come from fresh coverage (else it would restore the old offset)
            last_fit = sc.last_fit_t
            sc.reset_window()
            sc.last_fit_t = last_fit
        return rec
