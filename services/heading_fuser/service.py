"""Heading fuser service: clean IMU + calibrated magnetometer + DMC verdict → fused heading.

What it consumes and produces is declared on :class:`HeadingFuser` (``INPUTS``, ``OUTPUTS``; ``--help`` lists
them); the clean/, cal/mag and dmc streams also arrive as fleet frames (magmesh/fleet/{shard}/{clean,cal,dmc}:
on_frame).

The filter is :class:`services.heading_fuser.core.HeadingFilter` (``--impl ekf``, the default; run by its compiled
twin: every vehicle a slot of one shared :class:`services.heading_fuser.compiled.FleetHeading`, unless
``compiled = false``) or the ``vqf`` library's VQF (``--impl vqf``, :mod:`services.heading_fuser.vqf_impl`).
The time join of the streams and the output rules are :mod:`services.heading_fuser.fleet` (compiled, state in
per-vehicle slots): a fleet frame's rows of every vehicle in one call, a single sample as a call of one row; this
file is wiring only.
Manifest vehicle keys used: ``declination_rad``, ``heading_profile`` (a name from
:mod:`services.heading_fuser.profiles`, e.g. ``imu_only``) and ``mag_params.{sensor}`` (offset_nt,
matrix, field_radius_nt). New calibration parameters re-base the filter's field reference.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np

from magmesh import declare
from magmesh.declare import Input, Output, setting
from magmesh.magcal import MagParams
from magmesh.runtime import Service, shed_after_setting
from schemas import keys
from services.physical import refuse_unphysical

from . import compiled, core, fleet, profiles

MAX_PENDING = fleet.MAX_PENDING
#: samples given up in frames are reported (``count_drop``) at most this often, wall clock, and on every tick
DROP_REPORT_S = 1.0
#: events up to this many go through each vehicle's filter row by row (the per-sample path: a bulk step of the
#: shared fleet costs more for a few rows); more go through the fleet in one call
ROWWISE_MAX = 4
#: mode changes logged per second at most (the rest are counted and named in the next line logged)
TRANSITION_LOGS_PER_S = 20.0
_MODE_CODE = {m: i for i, m in enumerate(core.MODES)}


@dataclass(frozen=True)
class Settings(core.Settings):
    """Service settings: every filter setting (see core.Settings: described by its comments) plus the wiring ones
    below."""

    sensor: str = setting("1", "which magnetometer steers the heading")
    profile: str = setting("", "base settings (profiles.py); \"\" → the vehicle's heading_profile, else road_vehicle",
                           choices=("", *profiles.PROFILES))
    publish_period_s: float = setting(0.1, "heading messages at most this often (sample time; 0: every IMU sample)",
                                      lo=0)
    cal_timeout_s: float = setting(1.0, "without cal/mag for this long, fall back to clean/mag + parameters", lo=0)
    dmc_timeout_s: float = setting(2.0, "a DMC verdict older than this is ignored (the filter's own checks remain)",
                                   lo=0)
    dmc_wait_wall_s: float = setting(1.0, "a magnetometer sample waits at most this long (wall clock) for its verdict",
                                     lo=0)
    mag_wait_s: float = setting(0.2, "the IMU waits at most this long (sample time) for the magnetometer stream; "
                                "later samples are levelled with the attitude of their own time (kept for a few "
                                "seconds)", lo=0)
    max_imu_gap_s: float = setting(1.0, "a longer gap in the IMU stream restarts the filter", lo=0)
    alarm_clear_frac: float = setting(0.8, "clear the alarm below this fraction of heading_alarm_std_rad", lo=0)
    compiled: bool = setting(True, "the compiled filter (compiled.py, numba; same results); false: core.HeadingFilter")
    shed_after_s: float = shed_after_setting()
    # filter settings whose comment in core.Settings is only its group's heading: described here (default: core's)
    init_tilt_std_rad: float = setting(core.Settings.init_tilt_std_rad, "initial 1-σ of roll and pitch", lo=0)
    init_heading_std_rad: float = setting(core.Settings.init_heading_std_rad, "initial 1-σ of the heading", lo=0)
    use_field_check: bool = setting(core.Settings.use_field_check, "judge the field's strength and dip against the "
                                    "reference (window means and each sample): a field off by more than the "
                                    "tolerances is not fused")
    adaptive_noise: bool = setting(core.Settings.adaptive_noise, "adaptive magnetometer noise (§2): R_m multiplied by "
                                   "adaptive_gain_variance or adaptive_gain_heading while the field is not quasi-static")
    quasi_static_window_s: float = setting(core.Settings.quasi_static_window_s, "sliding window of the quasi-static "
                                           "field test (strength and dip variance, heading change against the gyro)",
                                           gt=0)
    adaptive_gain_variance: float = setting(core.Settings.adaptive_gain_variance, "k1: R_m multiplier while the "
                                            "variance test fails", lo=0)
    adaptive_gain_heading: float = setting(core.Settings.adaptive_gain_heading, "k2: R_m multiplier while the "
                                           "heading-change test fails", lo=0)
    use_dmc: bool = setting(core.Settings.use_dmc, "follow the DMC verdict (§1): the gyro alone while it says the "
                            "magnetic heading is invalid")

    def __post_init__(self) -> None:
        super().__post_init__()
        declare.check(self)


class VehicleState:
    """A vehicle's place in the service: its join slot (fleet.py), its filter — a view of its slot in the shared
    compiled fleet, or a filter object of its own (the reference, VQF) — and its calibration parameters."""

    def __init__(self, join: fleet.FleetJoin, slot: int, filt, fleet_slot: int, vehicle: str, sensor: str):
        self.join, self.slot, self.filter, self.fleet_slot = join, slot, filt, fleet_slot
        self.params: MagParams | None = None
        self.param_source = "none"
        self.n_transitions_logged = 0
        self.imu_key = keys.clean_imu(vehicle)
        self.cal_key = keys.cal_mag(vehicle, sensor)
        self.clean_key = keys.clean_mag(vehicle, sensor)
        self.heading_key = keys.heading(vehicle)

    @property
    def alarm_raised(self) -> bool:
        return self.join.alarm_raised(self.slot)

    @property
    def dmc_valid(self) -> bool | None:
        return self.join.dmc(self.slot)[0]

    @property
    def last_imu_t(self) -> float | None:
        return self.join.last_imu_t(self.slot)

    @property
    def pending_mag(self) -> list[tuple[float, list[float], str, float]]:
        """Magnetometer samples waiting for the IMU or their DMC verdict: (t_s, field nT, stream, arrived)."""
        return self.join.pending_mag(self.slot)


def _opt(x: float) -> float | None:
    return None if x != x else x


class HeadingFuser(Service):
    """The project's quaternion EKF with DMC switching and guarded re-acquisition (core.py).

    Every vehicle has a slot in the service's join (fleet.py: its IMU, magnetometer and DMC verdict streams
    joined by time, state in arrays) and, with the compiled filter, a slot in one shared
    :class:`compiled.FleetHeading`: a fleet frame's rows of every vehicle go through the join in one compiled call
    and the filters in another (:meth:`on_frame`); a single sample is a call of one row (:meth:`on_message`).
    """

    role = "heading_fuser"
    impl = "ekf"
    Settings = Settings
    INPUTS = (
        Input("magmesh/{vehicle}/clean/imu", "gyro + accelerometer (drives the filter's clock)"),
        Input("magmesh/{vehicle}/cal/mag/{sensor}", "calibrated field from the calibration service", sensors="sensor"),
        Input("magmesh/{vehicle}/clean/mag/{sensor}", "fallback when no cal/mag arrives: compensated here with the "
              "latest cal/params, else the manifest's mag_params", sensors="sensor"),
        Input("magmesh/{vehicle}/cal/params/{sensor}", "parameters for that fallback", sensors="sensor"),
        Input("magmesh/{vehicle}/dmc", "the DMC's valid flag (docs/methods.md#dmc)"),
    )
    OUTPUTS = (
        Output("magmesh/{vehicle}/heading", "heading/pitch/roll, 1-σ, mode, mag innovation and test ratio"),
        declare.alarm("heading", "raised when the heading σ passes heading_alarm_std_rad while not magnetic; cleared "
                      "when magnetic again or σ below alarm_clear_frac × that"),
    )
    ADOPTS_RESTORED_ALARMS = True  # a restored raised heading alarm stays until the filter's σ falls again

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        s = self.settings
        self.join = fleet.FleetJoin(16, cal_timeout_s=s.cal_timeout_s, dmc_timeout_s=s.dmc_timeout_s,
                                    dmc_wait_wall_s=s.dmc_wait_wall_s, mag_wait_s=s.mag_wait_s,
                                    max_imu_gap_s=s.max_imu_gap_s, publish_period_s=s.publish_period_s,
                                    alarm_clear_std_rad=s.alarm_clear_frac * s.heading_alarm_std_rad)
        self.filters: compiled.FleetHeading | None = None  # the shared compiled fleet (made on first use)
        self._slot_of: dict[str, int] = {}  # vehicle -> join slot
        self._slot_state: dict[int, VehicleState] = {}
        self._slot_vehicle: dict[int, str] = {}
        self._fslot = np.full(16, -1, np.int64)  # join slot -> compiled fleet slot (−1: a filter of its own)
        self._gen = 0  # bumped when slots change (frame vehicle maps are rebuilt)
        self._vmaps: dict[tuple[str, str], list] = {}
        self._log_window = [-math.inf, 0, 0]  # transition logs: window start, lines in it, lines not logged
        self._drops_at = -math.inf  # when the samples given up were last reported

    #: the tick reports what the frames gave up since the last report (see :data:`DROP_REPORT_S`)
    tick_override_s = DROP_REPORT_S

    def on_tick(self) -> None:
        self._report_drops()

    def on_stop(self) -> None:
        self._report_drops()
        super().on_stop()

    def profile_name(self, vehicle: str) -> str:
        cfg = self.vehicles_config.get(vehicle, {}) or {}
        return self.settings.profile or str(cfg.get("heading_profile") or profiles.ROAD_VEHICLE)

    def core_settings(self, vehicle: str) -> core.Settings:
        """The profile's settings, then every filter setting given to this service (one that differs
        from the default) on top, then the vehicle's declination."""
        values = profiles.values(self.profile_name(vehicle))
        for f in dataclasses.fields(core.Settings):
            v = getattr(self.settings, f.name)
            if v != f.default and not (isinstance(v, float) and math.isnan(v) and math.isnan(f.default)):
                values[f.name] = v
        cfg = self.vehicles_config.get(vehicle, {}) or {}
        if "declination_rad" in cfg:
            values["declination_rad"] = float(cfg["declination_rad"])
        return core.Settings(**values)

    def make_filter(self, settings: core.Settings):
        """A filter of the vehicle's own: the compiled filter (``compiled``, the default) once its kernels are
        compiled or cached; until then (a cold numba cache) the reference, while a background process compiles
        them: same results. (Vehicles normally get a slot of the shared compiled fleet instead: see
        :meth:`new_vehicle`.)"""
        if self.settings.compiled:
            if compiled.kernels_ready():
                return compiled.CompiledHeadingFilter(settings)
            compiled.warm_in_background(self.log)
        return core.HeadingFilter(settings)

    def _fleet_filter(self) -> bool:
        """Whether a new vehicle gets a slot of the shared compiled fleet (the ekf implementation with its
        kernels compiled or cached)."""
        return (self.settings.compiled and type(self).make_filter is HeadingFuser.make_filter
                and compiled.kernels_ready())

    def on_start(self) -> None:
        super().on_start()
        for vehicle in self.vehicles_config:
            name = self.profile_name(vehicle)
            if name not in profiles.PROFILES:
                raise SystemExit(f"heading_fuser: vehicle {vehicle}: unknown heading profile {name!r}; known: "
                                 f"{', '.join(profiles.PROFILES)}")
        fleet.warm()  # the join's kernels: compiled or loaded now, never on a sample
        if self.settings.compiled and type(self).make_filter is HeadingFuser.make_filter:
            if compiled.kernels_ready():
                compiled.warm()  # loaded from numba's disk cache (a fraction of a second)
            else:
                compiled.warm_in_background(self.log)

    def new_vehicle(self, vehicle: str) -> VehicleState:
        old = self._slot_of.pop(vehicle, None)
        if old is not None:  # the vehicle's state was dropped (handed over, taken back): its slots go too
            self._free(old)
        settings = self.core_settings(vehicle)
        slot = self.join.add()
        if slot >= len(self._fslot):
            self._fslot = np.concatenate([self._fslot, np.full(self.join.capacity - len(self._fslot), -1, np.int64)])
        if self._fleet_filter():
            if self.filters is None:
                self.filters = compiled.FleetHeading(16)
            fslot = self.filters.add(settings)
            filt = fleet.SlotFilter(self.filters, fslot)
        else:
            fslot, filt = -1, self.make_filter(settings)
        self._fslot[slot] = fslot
        st = VehicleState(self.join, slot, filt, fslot, vehicle, self.settings.sensor)
        # after a restart: the latch as the mesh knows it (its clear names the raise time)
        self.join.set_alarm(slot, self.holds_alarm(vehicle, "heading"), self.held_alarm_raised_t_s(vehicle, "heading"))
        table = ((self.vehicles_config.get(vehicle, {}) or {}).get("mag_params") or {}).get(self.settings.sensor)
        if table:
            try:
                st.params, st.param_source = MagParams.from_message(table), "manifest"
                self.join.set_params(slot, st.params.offset, st.params.M)
            except (TypeError, ValueError) as e:
                self.log.error("vehicle %s: manifest mag_params.%s unusable: %s", vehicle, self.settings.sensor, e)
        self._slot_of[vehicle] = slot
        self._slot_state[slot] = st
        self._slot_vehicle[slot] = vehicle
        self._gen += 1
        self.log.info("vehicle %s: heading filter %s started (profile %s, declination %.2f°, fallback parameters: %s)",
                      vehicle, self.impl, self.profile_name(vehicle), math.degrees(settings.declination_rad),
                      st.param_source)
        return st

    def _free(self, slot: int) -> None:
        self.join.free(slot)
        fs = int(self._fslot[slot])
        if fs >= 0 and self.filters is not None:
            self.filters.free(fs)
        self._fslot[slot] = -1
        self._slot_state.pop(slot, None)
        self._slot_vehicle.pop(slot, None)
        self._gen += 1

    def evict_vehicle(self, vehicle: str, state: VehicleState) -> None:
        if self._slot_of.get(vehicle) == state.slot:
            del self._slot_of[vehicle]
            self._free(state.slot)

    # ---- inputs: single samples -----------------------------------------------------------------
    def on_message(self, info, msg: dict, state: VehicleState) -> None:
        if refuse_unphysical(self, info, msg):
            return
        kind, stream = info.kind, info.stream
        if info.sensor is not None and info.sensor != self.settings.sensor:
            self.count_drop(info.key, f"not the fused magnetometer (sensor {self.settings.sensor})")
            return
        if kind == "clean" and stream == "imu":
            code, v, w = fleet.R_IMU, msg["gyro_rad_s"], msg["accel_m_s2"]
        elif kind == "cal" and stream == "mag":
            code, v, w = fleet.R_CAL, msg["b_nt"], None
        elif kind == "clean" and stream == "mag":
            code, v, w = fleet.R_CLEAN, msg["b_nt"], None
        elif kind == "dmc":
            code, v, w = fleet.R_DMC, (1.0 if msg["valid"] else 0.0, msg["credibility"], 0.0), None
        elif kind == "cal" and stream == "params":
            self._on_params(info, msg, state)
            return
        else:
            return
        rows = self.join.push_one(state.slot, code, msg["t_s"], v, w, time.monotonic())
        self._report_drops(state.slot)
        if rows:
            self._handle_rowwise(rows)

    def _on_params(self, info, msg: dict, state: VehicleState) -> None:
        if msg["status"] in ("ok", "manifest"):
            new = MagParams.from_message(msg)
            changed = state.params is not None and not _same_params(state.params, new)
            state.params, state.param_source = new, "cal"
            self.join.set_params(state.slot, new.offset, new.M)
            if changed:
                # the calibrated field changes scale and direction with the parameters: the field
                # reference learned under the old ones is re-learned, the magnetometer stays in use
                self.log.info("vehicle %s: new calibration parameters at t=%.2f s: field reference re-based",
                              info.vehicle, msg["t_s"])
                state.filter.rebase_field_reference()
                self.join.set_mode(state.slot, _MODE_CODE[state.filter.mode])  # a re-base may end gyro_only
                self._log_transitions(info.vehicle, state)
        else:
            self.count_drop(info.key, f"parameters with status {msg['status']!r} not used")

    # ---- inputs: fleet frames -------------------------------------------------------------------
    def on_frame(self, fr) -> None:
        """A fleet frame (clean: imu + mag/{sensor}; cal: mag/{sensor}; dmc: dmc): every vehicle's rows through
        the join in one call, the filters in another, the heading messages out through ``publish_rows``."""
        mag = f"mag/{self.settings.sensor}"
        kind = fr.kind
        parts = []
        for pos, (name, st) in enumerate(fr.streams.items()):
            if st.n == 0:
                continue
            if name == "imu" and kind == "clean":
                parts.append((pos, fleet.R_IMU, st, st.cols["gyro_rad_s"], st.cols["accel_m_s2"]))
            elif name == mag and kind in ("clean", "cal"):
                b = st.cols["b_nt"]
                parts.append((pos, fleet.R_CAL if kind == "cal" else fleet.R_CLEAN, st, b, b))
            elif name == "dmc" and kind == "dmc":
                v = np.zeros((st.n, 3))
                v[:, 0] = st.cols["valid"]
                v[:, 1] = st.cols["credibility"]
                parts.append((pos, fleet.R_DMC, st, v, v))
        if not parts:
            return
        vmap = self._frame_slots(fr, [p[2] for p in parts])
        if len(parts) == 1:
            _, code, st, v, w = parts[0]
            slot = vmap[st.vi]
            codes = np.full(st.n, code, np.int8)
            t = np.array(st.t_s, float)
            v = np.array(v, float)
            w = v if w is v else np.array(w, float)
        else:  # each vehicle's rows in time order, ties in the frame's stream order (the per-sample order)
            t_all = np.concatenate([p[2].t_s for p in parts])
            pos = np.concatenate([np.full(p[2].n, p[0], np.int64) for p in parts])
            order = np.lexsort((pos, t_all))
            slot = np.concatenate([vmap[p[2].vi] for p in parts])[order]
            codes = np.concatenate([np.full(p[2].n, p[1], np.int8) for p in parts])[order]
            t = t_all[order]
            v = np.concatenate([p[3] for p in parts])[order]
            w = np.concatenate([p[4] for p in parts])[order]
        now = time.monotonic()
        ev = self.join.push(slot, codes, t, v, w, now)
        if now - self._drops_at >= DROP_REPORT_S:
            self._report_drops()
        if ev.n:
            self._handle(ev, rows_out=True)

    def _frame_slots(self, fr, streams_: list) -> np.ndarray:
        """Join slot of each vehicle index of the frame that has rows here (−1 elsewhere); kept per frame key while
        the frame's vehicle list and the vehicles served stay the same."""
        states = self.vehicle_states
        ck = (fr.shard, fr.kind)
        c = self._vmaps.get(ck)
        if c is None or c[1] != self._gen or c[2] != len(states) or c[0] != fr.vehicles:
            if len(self._vmaps) > 64:
                self._vmaps.clear()
            c = self._vmaps[ck] = [fr.vehicles, self._gen, len(states), np.full(len(fr.vehicles), -1, np.int64)]
        vmap = c[3]
        for st in streams_:
            miss = vmap[st.vi] < 0
            if miss.any():
                for i in np.unique(st.vi[miss]).tolist():
                    v = fr.vehicles[i]
                    vs = states.get(v)
                    vmap[i] = (vs if vs is not None else self.state_for(v)).slot
                c[1], c[2] = self._gen, len(states)  # new vehicles made above are in the map already
        return vmap

    # ---- the events: filters, outputs ------------------------------------------------------------
    def _report_drops(self, slot: int | None = None) -> None:
        """Samples the join gave up (of one slot, or of all since the last report), counted on their keys."""
        if slot is None:
            self._drops_at = time.monotonic()
        slots, counts = self.join.take_drops(slot)
        if not len(slots):
            return
        for c, (stream, reason) in fleet.DROPS.items():
            col = counts[:, c]
            for i in np.flatnonzero(col).tolist():
                st = self._slot_state.get(int(slots[i]))
                if st is not None:
                    key = st.imu_key if stream == "imu" else (st.cal_key if stream == "cal" else st.clean_key)
                    self.count_drop(key, reason, int(col[i]))

    def _handle(self, ev: fleet.Events, rows_out: bool) -> None:
        """Events released by the join: each through its vehicle's filter, then the output rules (the alarm
        latch, a heading message per vehicle per ``publish_period_s``, the mode changes). Rows of vehicles of the
        shared compiled fleet go through it in bulk (one call per run of rows) unless there are only a few (a
        single sample's); the others row by row through their filter's API (a filter of the vehicle's own: the
        reference, VQF) — the same kernels and rules either way."""
        n = ev.n
        if n > ROWWISE_MAX:
            bulk = self._fslot[ev.slot] >= 0
            if bulk.all():
                self._handle_bulk(ev, None, rows_out)
                return
            if bulk.any():
                self._handle_bulk(ev, np.flatnonzero(bulk), rows_out)
            self._handle_rowwise(ev.rows(np.flatnonzero(~bulk).tolist()))
            return
        self._handle_rowwise(ev.rows())

    def _handle_rowwise(self, rows: list[tuple]) -> None:
        """Events (:meth:`fleet.FleetJoin.push_one`'s tuples) one by one through each vehicle's filter's API."""
        join = self.join
        touched = {}
        for k, kind, dmc, reset, t, a, b, dt, gap in rows:
            st = self._slot_state[k]
            f = st.filter
            touched[k] = st
            if kind != fleet.E_IMU:
                f.update_mag(a, None if dmc < 0 else bool(dmc), t_s=t)
                join.set_mode(k, _MODE_CODE[f.mode])
                continue
            if reset:
                self._gap_warning(k, gap, t)
                f.reset()
                st.n_transitions_logged = 0
            f.update_imu(a, b, dt, t_s=t)
            mode = _MODE_CODE[f.mode]
            if mode == fleet.M_INIT:
                join.decide_one(k, fleet.E_IMU, t, reset, mode, False, math.nan)
                continue
            s, fl = f.internal_states, f.flags
            pub, alarm, raised_t = join.decide_one(k, fleet.E_IMU, t, reset, mode, fl.heading_uncertain,
                                                   s.heading_std_rad)
            if alarm >= 0:
                self._alarm(self._slot_vehicle[k], alarm, t, s.heading_std_rad, s.time_since_mag_fused_s, mode,
                            raised_t)
            if pub:
                h, p, ro = f.euler()
                hs, ps, rs = f.attitude_std()
                self.publish(st.heading_key, "heading", self._slot_vehicle[k], t, heading_rad=h, pitch_rad=p,
                             roll_rad=ro, heading_std_rad=hs, pitch_std_rad=ps, roll_std_rad=rs, mode=core.MODES[mode],
                             mag_innovation_rad=s.mag_innovation_rad, mag_test_ratio=s.mag_test_ratio,
                             mag_fused=fl.mag_fused)
        for k, st in touched.items():
            self._log_transitions(self._slot_vehicle[k], st)

    def _handle_bulk(self, ev: fleet.Events, idx: np.ndarray | None, rows_out: bool) -> None:
        """Rows ``idx`` of the events (all when None), vehicles of the shared fleet: one step call per run of rows
        (a filter restart splits it), the output rules in one call, the heading messages in one ``publish_rows``."""
        if idx is not None:
            ev = fleet.Events(len(idx), *(a[idx] for a in ev[1:]))
        fs = self._fslot[ev.slot]
        fh = self.filters
        resets = np.flatnonzero(ev.reset).tolist()
        for r in resets:
            self._gap_warning(int(ev.slot[r]), ev.gap_s[r], float(ev.t_s[r]))
        outs, a = [], 0
        for r in resets:
            if r > a:
                outs.append(fh.step(fs[a:r], ev.kind[a:r], ev.t_s[a:r], ev.a[a:r], ev.b[a:r], ev.dt_s[a:r],
                                    ev.dmc[a:r]))
            fh.reset(int(fs[r]))
            a = r
        outs.append(fh.step(fs[a:], ev.kind[a:], ev.t_s[a:], ev.a[a:], ev.b[a:], ev.dt_s[a:], ev.dmc[a:]))
        o = outs[0] if len(outs) == 1 else compiled.StepOutput(*(np.concatenate(x) for x in zip(*outs, strict=True)))
        dec = self.join.decide(ev, o.mode, o.heading_uncertain, o.heading_std_rad, o.reason)
        if len(dec.transition_row) or resets:
            self._note_transitions(ev, o, dec)
        for r, state, raised_t in zip(dec.alarm_row.tolist(), dec.alarm_state.tolist(),
                                      dec.alarm_raised_t_s.tolist(), strict=True):
            self._alarm(self._slot_vehicle[int(ev.slot[r])], state, float(ev.t_s[r]), float(o.heading_std_rad[r]),
                        float(o.time_since_mag_fused_s[r]), int(o.mode[r]), raised_t)
        if len(dec.publish):
            self._publish_rows(dec.publish, ev, o, rows_out)

    def _gap_warning(self, slot: int, gap_s: float, t: float) -> None:
        self.log.warning("vehicle %s: IMU gap of %.2f s at t=%.2f s: restarting the heading filter",
                         self._slot_vehicle.get(slot), float(gap_s), float(t))

    def _note_transitions(self, ev: fleet.Events, o: compiled.StepOutput, dec: fleet.Decisions) -> None:
        """The mode changes of rows stepped in bulk into each vehicle's ``filter.transitions`` (a restart clears
        them, as the filter's reset does), then logged."""
        marks = [(r, 1, f) for r, f in zip(dec.transition_row.tolist(), dec.transition_from.tolist(), strict=True)]
        marks += [(r, 0, 0) for r in np.flatnonzero(ev.reset).tolist()]
        marks.sort()
        touched = {}
        for r, what, frm in marks:
            slot = int(ev.slot[r])
            st = self._slot_state[slot]
            f = st.filter
            if what == 0:
                f.transitions = []
                st.n_transitions_logged = 0
            else:
                f.transitions.append((float(o.t_s[r]), core.MODES[frm], core.MODES[int(o.mode[r])],
                                      compiled.REASONS[int(o.reason[r])]))
            touched[slot] = st
        for slot, st in touched.items():
            st.filter._ntr = self.filters.mode_changes(st.fleet_slot)
            self._log_transitions(self._slot_vehicle[slot], st)

    def _alarm(self, vehicle: str, state: int, t: float, h_std: float, since_fused_s: float, mode: int,
               raised_t: float) -> None:
        """``_check_alarm``: the heading alarm raised (``state`` 1) or cleared (0) at ``t``."""
        s = self.settings
        m = core.MODES[mode]
        if state:
            self.alarm(vehicle, "heading", "raised", "warning",
                       f"heading uncertainty {math.degrees(h_std):.1f}° after {since_fused_s:.0f} s without a usable "
                       f"magnetometer (mode {m})", h_std, s.heading_alarm_std_rad, t, unit="rad")
        else:
            self.alarm(vehicle, "heading", "cleared", "warning",
                       f"heading uncertainty back to {math.degrees(h_std):.1f}° (mode {m})",
                       h_std, s.heading_alarm_std_rad, t, unit="rad", raised_t_s=_opt(raised_t))

    # ---- outputs ------------------------------------------------------------------------------
    def _publish_rows(self, idx: np.ndarray, ev: fleet.Events, o: compiled.StepOutput, rows_out: bool) -> None:
        """Heading messages after event rows ``idx``: one ``publish_rows`` call (frames), or one message each."""
        slots = ev.slot[idx].tolist()
        vehicles = [self._slot_vehicle[s] for s in slots]
        t = ev.t_s[idx].tolist()
        cols = {"heading_rad": o.heading_rad[idx].tolist(), "pitch_rad": o.pitch_rad[idx].tolist(),
                "roll_rad": o.roll_rad[idx].tolist(), "heading_std_rad": o.heading_std_rad[idx].tolist(),
                "pitch_std_rad": o.pitch_std_rad[idx].tolist(), "roll_std_rad": o.roll_std_rad[idx].tolist(),
                "mode": [core.MODES[m] for m in o.mode[idx].tolist()],
                "mag_innovation_rad": [_opt(x) for x in o.mag_innovation_rad[idx].tolist()],
                "mag_test_ratio": [_opt(x) for x in o.mag_test_ratio[idx].tolist()],
                "mag_fused": o.mag_fused[idx].tolist()}
        if rows_out:
            self.publish_rows("heading", [self._slot_state[s].heading_key for s in slots], vehicles, t, cols)
            return
        names = list(cols)
        for i, (s, v) in enumerate(zip(slots, vehicles, strict=True)):
            self.publish(self._slot_state[s].heading_key, "heading", v, t[i], **{k: cols[k][i] for k in names})

    def _log_transitions(self, vehicle: str, st: VehicleState) -> None:
        tr = st.filter.transitions
        w = self._log_window
        while st.n_transitions_logged < len(tr):
            t, a, b, why = tr[st.n_transitions_logged]
            now = time.monotonic()
            if now - w[0] >= 1.0:
                if w[2]:
                    self.log.info("%d more heading mode changes not logged in the last second", w[2])
                w[0], w[1], w[2] = now, 0, 0
            if w[1] < TRANSITION_LOGS_PER_S:
                self.log.info("vehicle %s: t=%.2f s heading mode %s → %s (%s)", vehicle, t, a, b, why)
                w[1] += 1
            else:
                w[2] += 1
            st.n_transitions_logged += 1
        if len(tr) > 1000:  # keep the list short on long runs
            del tr[:500]
            st.n_transitions_logged -= 500

    def status_extra(self) -> dict:
        out = {}
        for vehicle, st in self.vehicle_states.items():
            if st is None:
                continue
            f = st.filter
            out[vehicle] = {
                "mode": f.mode,
                "heading_deg": round(math.degrees(f.heading_rad()), 2) if f.aligned else None,
                "heading_std_deg": round(math.degrees(f.internal_states.heading_std_rad), 2),
                "mag_test_ratio": f.internal_states.mag_test_ratio,
                "param_source": st.param_source,
                "profile": self.profile_name(vehicle),
                "field_rebases": getattr(f, "n_rebases", 0),
                "dmc_valid": st.dmc_valid,
                "alarm_raised": st.alarm_raised,
                "waiting": {"mag": self.join.IS[st.slot, fleet.I_PM_N].item(),
                            "imu": self.join.pending_imu(st.slot)},
                "join": self.join.counts(st.slot),
            }
        return {"vehicles": out}


REBASE_CHANGE_FRAC = 0.005  # parameters that move the calibrated field by less than this do not re-base


def _same_params(a: MagParams, b: MagParams) -> bool:
    """Whether two parameter sets calibrate alike: the largest change of the calibrated field, over
    raw fields on the sphere of ``a`` (its offset ± radius along each axis), relative to the radius,
    is below :data:`REBASE_CHANGE_FRAC`."""
    r = float(a.field_radius_nt) or 50_000.0
    raw = a.offset + r * np.vstack([np.eye(3), -np.eye(3)])
    d = np.linalg.norm(a.apply(raw) - b.apply(raw), axis=1)
    return bool(np.max(d) / r < REBASE_CHANGE_FRAC)
