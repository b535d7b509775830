"""Differential magnetic compass (DMC): static compensation, features and the stage-1 threshold test.

Pure numpy; never imports zenoh. Method: docs/methods.md#dmc (Hao, Yang, Huang, NUAA).

Two compasses a few centimetres apart see a distant field (the Earth's) alike and a nearby source
differently. Per compass k the field is statically compensated, h_k = M_k (m_k − o_k), then at epoch i

    Δm_k  = |h_k| − R_k                                  field-strength error             (§1 eq. Δm)
    dΔm_k = [Δm_k(i) − Δm_k(j)] / [t(i) − t(j)]          its rate                          (§1 eq. dΔm)
    Δh    = h_1 − h_2 − Δh_r                             relative heading difference       (§1 eq. Δh)
    dΔh   = [Δh(i) − Δh(j)] / [t(i) − t(j)]              its rate                          (§1 eq. dΔh)

Stage 1 declares the heading valid only when |Δm_k| < V_Δm (both k), |dΔm_k| < V_dΔm, |Δh| < V_Δh and
|dΔh| < V_dΔh. The paper differentiates consecutive samples of an ~8 Hz compass; at 50 Hz that rate is
dominated by sensor noise, so here the rates are taken between the means of short windows
(``smooth_window_s``) ``rate_window_s`` apart. Every window is finite, so the output for an epoch is a
function of the last ``history_s`` of input only: two instances fed the same stream agree exactly.

Everything exists twice, with identical maths: a vectorised batch form (:func:`features_batch`,
:func:`threshold_test`) for training and evaluation, and a streaming form (:class:`FeatureTracker`,
:class:`ThresholdDetector`) for the service.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from magmesh import latch, maths
from magmesh.magcal import MagParams

TEST_NAMES = ("dm", "ddm", "dh", "ddh")


# ---- static compensation ----------------------------------------------------------------------


#: a compass's static compensation h = M (m − offset), |h| ≈ field_radius_nt undisturbed: the project's one parameter
#: type (magmesh.magcal.MagParams; "3d": the radius is the total field strength, a tilt-invariant Δm; "2d": the
#: horizontal one, the paper's ellipse fit, and Δm uses the horizontal components). The DMC's name for it.
CompassParams = MagParams


def compass_heading(h, declination_rad: float = 0.0):
    """Heading (rad, clockwise from true north) of a level FLU compass from its compensated field."""
    h = np.asarray(h, float)
    return maths.mag_heading_flu(h[..., 0], h[..., 1], declination_rad)


# ---- features ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class FeatureSettings:
    smooth_window_s: float = 0.2  # features are averaged over this window before differentiating
    rate_window_s: float = 0.5  # rates are taken between window means this far apart
    dh_ref_rad: float = 0.0  # static heading offset between the compasses Δh_r
    max_gap_s: float = 1.0  # a gap in the input longer than this restarts the windows

    def __post_init__(self):
        if not (0 < self.smooth_window_s <= 10):
            raise ValueError(f"smooth_window_s must be in (0, 10] s, got {self.smooth_window_s}")
        if not (0 < self.rate_window_s <= 30):
            raise ValueError(f"rate_window_s must be in (0, 30] s, got {self.rate_window_s}")
        if not (self.max_gap_s > 0):
            raise ValueError(f"max_gap_s must be positive, got {self.max_gap_s}")

    @property
    def history_s(self) -> float:
        """Input history that determines one epoch's output."""
        return self.smooth_window_s + self.rate_window_s


@dataclass
class Features:
    """Features of N epochs (arrays; N = 1 in the streaming form)."""

    t_s: np.ndarray
    dm_nt: np.ndarray  # N×2
    ddm_nt_s: np.ndarray  # N×2
    dh_rad: np.ndarray  # N
    ddh_rad_s: np.ndarray  # N
    heading_rad: np.ndarray  # N, compass 1
    heading2_rad: np.ndarray  # N, compass 2
    rates_ready: np.ndarray  # N bool: the rate windows were full


def _raw_features(h1, h2, p1: MagParams, p2: MagParams, declination_rad: float, dh_ref_rad: float):
    dm = np.stack([p1.strength(h1) - p1.field_radius_nt, p2.strength(h2) - p2.field_radius_nt], axis=-1)
    hd1 = compass_heading(h1, declination_rad)
    hd2 = compass_heading(h2, declination_rad)
    dh = maths.angle_diff(hd1, hd2 + dh_ref_rad)
    return dm, dh, hd1, hd2


def features_batch(
    t_s,
    b1_nt,
    b2_nt,
    p1: MagParams,
    p2: MagParams,
    declination_rad: float = 0.0,
    settings: FeatureSettings | None = None,
) -> Features:
    """All features of a paired recording at once (same maths as :class:`FeatureTracker`)."""
    s = settings or FeatureSettings()
    t = np.asarray(t_s, float)
    n = len(t)
    dm, dh, hd1, hd2 = _raw_features(p1.apply(b1_nt), p2.apply(b2_nt), p1, p2, declination_rad,
                                     s.dh_ref_rad)
    # segments split at gaps: windows never reach across a gap
    seg = np.concatenate([[0], np.cumsum(np.diff(t) > s.max_gap_s)]) if n else np.zeros(0, int)
    seg_start_idx = np.searchsorted(seg, seg, side="left")
    # window mean over (t − smooth_window_s, t] within the segment: cumulative sums
    lo = np.maximum(np.searchsorted(t, t - s.smooth_window_s, side="right"), seg_start_idx)
    idx = np.arange(n)
    # Δh is averaged as an angle unwrapped around each epoch's own value (it stays far from ±π in use)
    cs_dm = np.vstack([np.zeros((1, 2)), np.cumsum(dm, axis=0)])
    sin_c = np.concatenate([[0.0], np.cumsum(np.sin(dh))])
    cos_c = np.concatenate([[0.0], np.cumsum(np.cos(dh))])
    cnt = (idx + 1 - lo).astype(float)
    dm_s = (cs_dm[idx + 1] - cs_dm[lo]) / cnt[:, None]
    dh_s = np.arctan2(sin_c[idx + 1] - sin_c[lo], cos_c[idx + 1] - cos_c[lo])
    # rate: between the mean ending now and the mean ending rate_window_s earlier (the newest epoch
    # at or before t − rate_window_s), inside the segment
    j = np.searchsorted(t, t - s.rate_window_s, side="right") - 1
    # ready once the segment holds history_s of input (the streaming form's rule)
    ready = (j >= seg_start_idx) & (t - t[seg_start_idx] >= s.history_s - 1e-9)
    jj = np.where(ready, j, idx)
    dt = np.where(ready, t - t[jj], 1.0)
    ddm = np.where(ready[:, None], (dm_s - dm_s[jj]) / dt[:, None], 0.0)
    ddh = np.where(ready, maths.angle_diff(dh_s, dh_s[jj]) / dt, 0.0)
    return Features(t, dm, ddm, dh, ddh, hd1, hd2, ready)


class FeatureTracker:
    """Streaming features for one vehicle: ``update(t, h1, h2)`` per paired epoch."""

    def __init__(self, settings: FeatureSettings | None = None):
        self.settings = settings or FeatureSettings()
        self.reset()

    def reset(self):
        self._raw: deque[tuple[float, np.ndarray, float]] = deque()  # (t, dm(2), dh) inside smooth window
        self._means: deque[tuple[float, np.ndarray, float]] = deque()  # (t, mean dm, mean dh)
        self._seg_start_t: float | None = None
        self._last_t: float | None = None

    def update(self, t_s: float, b1_nt, b2_nt, p1: MagParams, p2: MagParams,
               declination_rad: float = 0.0) -> Features:
        s = self.settings
        if self._last_t is not None and (t_s - self._last_t > s.max_gap_s or t_s <= self._last_t):
            self.reset()
        if self._seg_start_t is None:
            self._seg_start_t = t_s
        self._last_t = t_s
        dm, dh, hd1, hd2 = _raw_features(p1.apply(b1_nt), p2.apply(b2_nt), p1, p2, declination_rad,
                                         s.dh_ref_rad)
        dh = float(dh)
        self._raw.append((t_s, dm, dh))
        while self._raw and self._raw[0][0] <= t_s - s.smooth_window_s:
            self._raw.popleft()
        dm_mean = np.mean([r[1] for r in self._raw], axis=0)
        dh_mean = math.atan2(sum(math.sin(r[2]) for r in self._raw), sum(math.cos(r[2]) for r in self._raw))
        self._means.append((t_s, dm_mean, dh_mean))
        # keep the newest mean at or before t − rate_window_s, and everything after it
        while len(self._means) >= 2 and self._means[1][0] <= t_s - s.rate_window_s:
            self._means.popleft()
        ready = t_s - self._seg_start_t >= s.history_s - 1e-9 and self._means[0][0] <= t_s - s.rate_window_s
        if ready:
            t0, dm0, dh0 = self._means[0]
            ddm = (dm_mean - dm0) / (t_s - t0)
            ddh = float(maths.angle_diff(dh_mean, dh0)) / (t_s - t0)
        else:
            ddm, ddh = np.zeros(2), 0.0
        return Features(np.array([t_s]), dm[None, :], np.asarray(ddm)[None, :], np.array([dh]), np.array([ddh]),
                        np.array([float(hd1)]), np.array([float(hd2)]), np.array([ready]))


# ---- stage 1: thresholds ----------------------------------------------------------------------


@dataclass(frozen=True)
class Thresholds:
    """Stage-1 thresholds (V_Δm, V_dΔm, V_Δh, V_dΔh) in the project's units.

    The defaults sit above what a compass calibrated to ~1 % (offset ~300 nT, scale/misalignment
    ~0.5 %) shows undisturbed (|Δm| up to ~700 nT, |Δh| up to ~1.5°) and well below the simulated
    urban sources (median |Δm| of samples with > 5° heading error: ~8000 nT).
    """

    dm_nt: float = 1000.0
    ddm_nt_s: float = 1000.0
    dh_deg: float = 3.0
    ddh_deg_s: float = 3.0

    def __post_init__(self):
        for name in ("dm_nt", "ddm_nt_s", "dh_deg", "ddh_deg_s"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise ValueError(f"threshold {name} must be a positive finite number, got {v!r}")

    def scaled(self, k: float) -> Thresholds:
        return Thresholds(self.dm_nt * k, self.ddm_nt_s * k, self.dh_deg * k, self.ddh_deg_s * k)


#: the paper's Table 1 threshold sets (V_Δm, V_dΔm, V_Δh, V_dΔh), field in HMR3300 units, headings in degrees
PAPER_TABLE1_SETS = ((200, 100, 8, 8), (100, 50, 6, 6), (60, 30, 4, 4), (40, 20, 3, 3))


def test_ratios(f: Features, th: Thresholds) -> np.ndarray:
    """|feature| / threshold for the four tests (N×4; the field tests take the worse compass).

    A test passes when its ratio is < 1. Rates that are not ready yet count as 0 (unknown, not failing).
    """
    r = np.empty((len(f.t_s), 4))
    r[:, 0] = np.max(np.abs(f.dm_nt), axis=-1) / th.dm_nt
    r[:, 1] = np.max(np.abs(f.ddm_nt_s), axis=-1) / th.ddm_nt_s
    r[:, 2] = np.abs(np.degrees(f.dh_rad)) / th.dh_deg
    r[:, 3] = np.abs(np.degrees(f.ddh_rad_s)) / th.ddh_deg_s
    return r


def threshold_test(f: Features, th: Thresholds) -> np.ndarray:
    """Stage 1 (§1): True where all four tests pass."""
    return np.all(test_ratios(f, th) < 1.0, axis=-1)


def single_compass_ratios(f: Features, th: Thresholds, compass: int = 0) -> np.ndarray:
    """The single-compass baseline (§1 Table 2): |Δm| and dΔm of one compass only (N×2)."""
    r = np.empty((len(f.t_s), 2))
    r[:, 0] = np.abs(f.dm_nt[:, compass]) / th.dm_nt
    r[:, 1] = np.abs(f.ddm_nt_s[:, compass]) / th.ddm_nt_s
    return r


# ---- alarm hysteresis -------------------------------------------------------------------------


@dataclass(frozen=True)
class HysteresisSettings:
    raise_after_s: float = 0.3  # invalid this long without interruption → raise
    clear_after_s: float = 3.0  # valid this long without interruption → clear

    def __post_init__(self):
        if self.raise_after_s < 0 or self.clear_after_s < 0:
            raise ValueError("raise_after_s and clear_after_s must be ≥ 0")


def AlarmLatch(settings: HysteresisSettings | None = None) -> latch.AlarmLatch:
    """The detector's alarm latch: :class:`magmesh.latch.AlarmLatch` (the project's one) with the hold times of
    ``settings``: raised after ``raise_after_s`` of continuous invalid epochs, cleared after ``clear_after_s`` of
    valid ones; ``update(t_s, valid)`` returns "raised", "cleared" or None. The fleet kernel (fleet.py) is the
    same rule compiled and is tested against this."""
    s = settings or HysteresisSettings()
    return latch.AlarmLatch(s.raise_after_s, s.clear_after_s)


def latch_batch(t_s, valid, settings: HysteresisSettings | None = None) -> np.ndarray:
    """Alarm state per epoch for a whole recording (loop over :class:`AlarmLatch`)."""
    latch = AlarmLatch(settings)
    out = np.zeros(len(t_s), bool)
    for i, (t, v) in enumerate(zip(np.asarray(t_s, float), np.asarray(valid, bool), strict=False)):
        latch.update(float(t), bool(v))
        out[i] = latch.raised
    return out


# ---- the threshold detector (stage 1 only) ----------------------------------------------------


@dataclass(frozen=True)
class Decision:
    """What a detector concluded at one epoch (published as the ``dmc`` message + alarm transitions)."""

    t_s: float
    dm_nt: list[float]
    ddm_nt_s: list[float]
    dh_rad: float
    ddh_rad_s: float
    heading_rad: float
    stage1_pass: bool
    credibility: float
    valid: bool
    ready: bool = True  # the rate windows were full (before that the rates read 0)
    ratios: dict = field(default_factory=dict)  # test name → |feature| / threshold
    failed: tuple[str, ...] = ()  # names of the failing tests, worst first
    transition: str | None = None  # "raised" | "cleared" | None


_TEST_TEXT = {
    "dm": ("field-strength error |Δm|", "nT"),
    "ddm": ("field-strength rate |dΔm|", "nT/s"),
    "dh": ("relative heading difference |Δh|", "deg"),
    "ddh": ("relative heading rate |dΔh|", "deg/s"),
    "kc": ("credibility K_c", ""),
    "var": ("field variance", "nT²"),
    "dpsi": ("magnetometer-vs-gyro heading change", "deg"),
    "track": ("compass heading off the heading the gyro carried from trusted epochs", "deg"),
}


def test_value_and_threshold(name: str, ratio: float, th: Thresholds) -> tuple[float, float, str]:
    """(|value|, threshold, unit) of a named stage-1 test from its ratio."""
    thr = {"dm": th.dm_nt, "ddm": th.ddm_nt_s, "dh": th.dh_deg, "ddh": th.ddh_deg_s}[name]
    return ratio * thr, thr, _TEST_TEXT[name][1]


def reason_sentence(failed: tuple[str, ...], ratios: Mapping[str, float], units: Mapping[str, tuple]) -> str:
    """A sentence naming the failing tests, worst first, with value and threshold."""
    parts = []
    for name in failed:
        text, unit = _TEST_TEXT.get(name, (name, ""))
        value, thr = units[name]
        u = f" {unit}" if unit else ""
        parts.append(f"{text} {value:.3g}{u} exceeds {thr:.3g}{u}")
    if not parts:
        return "Magnetic heading is trustworthy again: every interference test passes."
    return "Magnetic interference suspected: " + "; ".join(parts) + "."


@dataclass(frozen=True)
class ThresholdDetectorSettings:
    thresholds: Thresholds = Thresholds()
    features: FeatureSettings = FeatureSettings()
    hysteresis: HysteresisSettings = HysteresisSettings()


class ThresholdDetector:
    """Stage 1 only: valid ⇔ the four threshold tests pass. Per vehicle; ``update`` per paired epoch."""

    impl = "threshold"

    def __init__(self, settings: ThresholdDetectorSettings | None = None):
        self.settings = settings or ThresholdDetectorSettings()
        self.tracker = FeatureTracker(self.settings.features)
        self.latch = AlarmLatch(self.settings.hysteresis)
        self.last: Decision | None = None

    def reset(self):
        self.tracker.reset()
        self.latch.reset()
        self.last = None

    def restart_features(self):
        """Parameters changed: the feature windows restart, the alarm keeps its state."""
        self.tracker.reset()

    def _decide(self, f: Features, th: Thresholds) -> tuple[bool, dict, tuple[str, ...]]:
        r = test_ratios(f, th)[0]
        ratios = dict(zip(TEST_NAMES, (float(x) for x in r), strict=False))
        failed = tuple(sorted((k for k, v in ratios.items() if v >= 1.0), key=lambda k: -ratios[k]))
        return not failed, ratios, failed

    def update(self, t_s: float, b1_nt, b2_nt, p1: MagParams, p2: MagParams,
               declination_rad: float = 0.0) -> Decision:
        f = self.tracker.update(t_s, b1_nt, b2_nt, p1, p2, declination_rad)
        ok, ratios, failed = self._decide(f, self.settings.thresholds)
        return self._finish(f, ok, 1.0 if ok else 0.0, ok, ratios, failed)

    def _finish(self, f: Features, stage1: bool, credibility: float, valid: bool, ratios: dict,
                failed: tuple[str, ...]) -> Decision:
        t = float(f.t_s[0])
        transition = self.latch.update(t, valid)
        self.last = Decision(
            t_s=t,
            dm_nt=[float(x) for x in f.dm_nt[0]],
            ddm_nt_s=[float(x) for x in f.ddm_nt_s[0]],
            dh_rad=float(f.dh_rad[0]),
            ddh_rad_s=float(f.ddh_rad_s[0]),
            heading_rad=float(f.heading_rad[0]),
            stage1_pass=bool(stage1),
            credibility=float(min(1.0, max(0.0, credibility))),
            valid=bool(valid),
            ready=bool(f.rates_ready[0]),
            ratios=ratios,
            failed=failed,
            transition=transition,
        )
        return self.last

    def describe(self, d: Decision) -> tuple[str, float | None, float | None, str]:
        """(reason, value, threshold, unit) for an alarm transition at decision ``d``."""
        th = self.settings.thresholds
        if d.transition == "cleared" or not d.failed:
            return reason_sentence((), {}, {}), None, None, ""
        units = {n: test_value_and_threshold(n, d.ratios[n], th)[:2] for n in d.failed}
        value, thr, unit = test_value_and_threshold(d.failed[0], d.ratios[d.failed[0]], th)
        return reason_sentence(d.failed, d.ratios, units), value, thr, unit

    @property
    def internal_states(self) -> dict:
        d = self.last
        return {} if d is None else {"ratios": d.ratios, "credibility": d.credibility}

    @property
    def flags(self) -> dict:
        d = self.last
        return {"alarm_raised": self.latch.raised, "valid": bool(d and d.valid),
                "warming": bool(d is None or not d.ready)}


# ---- pairing the two compasses' streams by time -----------------------------------------------


class Pairer:
    """Pairs samples of two sensors by time (|t1 − t2| ≤ tolerance_s), whatever order they arrive in.

    Each sensor's stream must be in time order (ingest guarantees it). A sample that can no longer find
    a partner (its partner stream has moved past it) is dropped and counted in the return value.
    The pair takes the reference (first) sensor's time. The two streams reach a service through
    separate subscribers, so one may run seconds ahead of the other under load (a replay at full
    speed): ``max_pending`` samples per sensor are held for their partner (8192 ≈ 160 s at 50 Hz).
    """

    def __init__(self, sensors: tuple[str, str] = ("1", "2"), tolerance_s: float = 0.005, max_pending: int = 8192):
        if len(sensors) != 2 or sensors[0] == sensors[1]:
            raise ValueError(f"need two different sensor ids, got {sensors!r}")
        if not tolerance_s >= 0:
            raise ValueError(f"tolerance_s must be ≥ 0, got {tolerance_s}")
        self.sensors = tuple(sensors)
        self.tolerance_s = float(tolerance_s)
        self.max_pending = int(max_pending)
        self.pending: dict[str, deque] = {s: deque() for s in self.sensors}

    def reset(self):
        for q in self.pending.values():
            q.clear()

    def push(self, sensor: str, t_s: float, b_nt) -> tuple[list[tuple[float, np.ndarray, np.ndarray]], int]:
        """Add one sample; returns (pairs formed [(t, b_first, b_second)], samples dropped)."""
        if sensor not in self.pending:
            raise ValueError(f"sensor {sensor!r} is not one of {self.sensors}")
        other = self.sensors[1] if sensor == self.sensors[0] else self.sensors[0]
        q_other = self.pending[other]
        dropped = 0
        # partner samples older than this one by more than the tolerance can never pair any more
        while q_other and q_other[0][0] < t_s - self.tolerance_s:
            q_other.popleft()
            dropped += 1
        b = np.asarray(b_nt, float)
        if q_other and abs(q_other[0][0] - t_s) <= self.tolerance_s:
            t_o, b_o = q_other.popleft()
            if sensor == self.sensors[0]:
                return [(t_s, b, b_o)], dropped
            return [(t_o, b_o, b)], dropped
        q_self = self.pending[sensor]
        q_self.append((t_s, b))
        while len(q_self) > self.max_pending:
            q_self.popleft()
            dropped += 1
        return [], dropped


# ---- the single-compass baseline (§1 Table 2) -------------------------------------------------


class SingleCompassDetector(ThresholdDetector):
    """One compass only: |Δm| < V_Δm and |dΔm| < V_dΔm (no differential tests). The paper's baseline.

    Published with compass 2's entries and the heading-difference features set to 0.
    """

    impl = "single"

    def update(self, t_s: float, b1_nt, b2_nt, p1: MagParams, p2: MagParams,
               declination_rad: float = 0.0) -> Decision:
        f = self.tracker.update(t_s, b1_nt, b1_nt, p1, p1, declination_rad)
        f.dm_nt[:, 1] = 0.0
        f.ddm_nt_s[:, 1] = 0.0
        th = self.settings.thresholds
        r = single_compass_ratios(f, th)[0]
        ratios = {"dm": float(r[0]), "ddm": float(r[1])}
        failed = tuple(sorted((k for k, v in ratios.items() if v >= 1.0), key=lambda k: -ratios[k]))
        ok = not failed
        return self._finish(f, ok, 1.0 if ok else 0.0, ok, ratios, failed)
