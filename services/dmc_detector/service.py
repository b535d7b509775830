"""DMC detector: recognises dynamic magnetic interference from two compasses (docs/methods.md#dmc).

What it consumes and produces is declared on the service class (``INPUTS``, ``OUTPUTS``; ``--help`` lists them).
Until ``cal/params`` arrive, the compensation comes from the mesh manifest's vehicle table
(``mag_params.{sensor}`` with offset_nt, matrix, field_radius_nt; ``declination_rad``; optional
``dh_ref_rad``). A 2-D (horizontal) ``cal/params`` set does not replace a 3-D one already held: its
field strength is the horizontal one, which pitch and roll move by hundreds of nT. A vehicle with no
parameters has its epochs counted as dropped, never guessed at.
This module holds the ``threshold`` implementation; the other implementations of the role subclass
:class:`DmcDetectorService` in ``impls.py``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from magmesh import declare
from magmesh.align import REASONS, TimeAligner
from magmesh.declare import Input, Output, setting
from magmesh.magcal import MagParams
from magmesh.runtime import Service, shed_after_setting
from schemas import keys
from services.physical import refuse_unphysical

from . import core, fleet
from .core import FeatureSettings, HysteresisSettings, Thresholds

# ---- settings every implementation shares (one declaration each) ------------------------------------


def pair_tolerance_setting() -> Any:
    return setting(0.005, "samples of the two compasses closer than this form an epoch", lo=0)


def raise_after_setting() -> Any:
    return setting(HysteresisSettings.raise_after_s, "alarm/dmc is raised after this long of invalid epochs without "
                   "interruption", lo=0)


def clear_after_setting() -> Any:
    return setting(HysteresisSettings.clear_after_s, "alarm/dmc is cleared after this long of valid epochs without "
                   "interruption", lo=0)


def severity_setting() -> Any:
    return setting("warning", "severity of alarm/dmc", choices=("warning", "critical"))


@dataclass(frozen=True)
class Settings:
    sensor_a: str = setting("1", "the reference compass (its heading is published)")
    sensor_b: str = setting("2", "the second compass of the differential pair")
    pair_tolerance_s: float = pair_tolerance_setting()
    pair_max_wait_s: float = setting(10.0, "wall-clock seconds a compass sample waits for its partner (then counted "
                                     "as unpaired)", gt=0)
    dm_threshold_nt: float = setting(Thresholds.dm_nt, "V_Δm: a valid epoch has |Δm| (field-strength error) below "
                                     "this on both compasses", gt=0)
    ddm_threshold_nt_s: float = setting(Thresholds.ddm_nt_s, "V_dΔm: a valid epoch has |dΔm| (rate of the "
                                        "field-strength error) below this", gt=0)
    dh_threshold_deg: float = setting(Thresholds.dh_deg, "V_Δh: a valid epoch has |Δh| (relative heading difference "
                                      "of the two compasses) below this", gt=0)
    ddh_threshold_deg_s: float = setting(Thresholds.ddh_deg_s, "V_dΔh: a valid epoch has |dΔh| (its rate) below this",
                                         gt=0)
    smooth_window_s: float = setting(FeatureSettings.smooth_window_s, "features are averaged over this window before "
                                     "differentiating", gt=0, hi=10)
    rate_window_s: float = setting(FeatureSettings.rate_window_s, "rates are taken between window means this far "
                                   "apart", gt=0, hi=30)
    raise_after_s: float = raise_after_setting()
    clear_after_s: float = clear_after_setting()
    severity: str = severity_setting()
    shed_after_s: float = shed_after_setting()

    def __post_init__(self):
        declare.check(self)
        keys.check_id(self.sensor_a, "sensor_a")
        keys.check_id(self.sensor_b, "sensor_b")
        self.thresholds()  # range checks
        self.feature_settings()
        self.hysteresis()

    def thresholds(self) -> Thresholds:
        return Thresholds(self.dm_threshold_nt, self.ddm_threshold_nt_s, self.dh_threshold_deg,
                          self.ddh_threshold_deg_s)

    def feature_settings(self, dh_ref_rad: float = 0.0) -> FeatureSettings:
        return FeatureSettings(self.smooth_window_s, self.rate_window_s, dh_ref_rad)

    def hysteresis(self) -> HysteresisSettings:
        return HysteresisSettings(self.raise_after_s, self.clear_after_s)


@dataclass
class VehicleState:
    aligner: TimeAligner | None  # joins the two compasses of single samples by sample time (magmesh/align.py)
    detector: Any  # the per-vehicle detector of an implementation without a fleet core (quasistatic), else None
    declination_rad: float = 0.0
    params: dict[str, MagParams] = field(default_factory=dict)
    param_origin: dict[str, str] = field(default_factory=dict)  # sensor → "manifest" | "cal"
    ignored_2d: dict[str, str] = field(default_factory=dict)  # sensor → 2-D cal/params id not used (3-D held)
    warned_2d: bool = False
    epochs: int = 0
    n_valid: int = 0
    warned_no_params: bool = False
    slot: int = -1  # the vehicle's slot in the fleet core (fleet.py)
    dh_ref_rad: float = 0.0


class DmcDetectorService(Service):
    """Common wiring of every two-compass implementation: pairing, parameters, publishing.

    Implementations with a fleet core (:meth:`make_fleet`: threshold, fcm, single) decide every epoch there —
    a fleet frame's epochs of all its vehicles in one call (:meth:`on_frame`), a single sample's epoch as a
    call of one row — and publish through ``publish_rows``; the ``dmc`` rows also go out as one frame
    (``magmesh/fleet/{instance}/dmc``) for the heading fuser."""

    role = "dmc_detector"
    impl = "threshold"
    Settings = Settings
    INPUTS = (
        Input("magmesh/{vehicle}/clean/mag/{sensor}", "the two compasses of the DMC, paired by time",
              sensors=("sensor_a", "sensor_b")),
        Input("magmesh/{vehicle}/cal/params/{sensor}", "static compensation; overrides the manifest's mag_params",
              sensors=("sensor_a", "sensor_b")),
    )
    OUTPUTS = (
        Output("magmesh/{vehicle}/dmc", "features, credibility and validity per epoch"),
        Output("magmesh/fleet/{shard}/dmc", "the same verdicts of every vehicle per input frame, with the same seqs"),
        declare.alarm("dmc", "raised after raise_after_s of invalid epochs, cleared after clear_after_s of valid "
                      "ones"),
    )
    ADOPTS_RESTORED_ALARMS = True  # the latch takes the mesh's alarm state (_sync_latches)

    # ---- hooks for implementations ---------------------------------------------------------
    def make_fleet(self) -> Any:
        """The implementation's fleet core (:mod:`services.dmc_detector.fleet`), or None (per-vehicle only)."""
        return fleet.FleetDetector(self.settings, capacity=64)

    def make_detector(self, vehicle: str, dh_ref_rad: float) -> Any:
        """The per-vehicle detector of an implementation without a fleet core."""
        return None

    # ---- service --------------------------------------------------------------------------
    def on_start(self) -> None:
        if self.fleet is not None:  # compile (or load from numba's disk cache) before serving: never on a sample
            fleet.warm()

    @property
    def sensors(self) -> tuple[str, str]:
        return (self.settings.sensor_a, self.settings.sensor_b)

    @property
    def required_sensors(self) -> tuple[str, ...]:
        """Sensors whose compensation parameters an epoch needs."""
        return self.sensors

    @property
    def fleet(self) -> Any:
        f = self.__dict__.get("_fleet", _UNSET)
        if f is _UNSET:
            f = self.__dict__["_fleet"] = self.make_fleet()
            s = self.settings
            self.__dict__["_pairer"] = None if f is None else fleet.FleetPairer(
                self.sensors, float(getattr(s, "pair_tolerance_s", 0.005)), float(getattr(s, "pair_max_wait_s", 10.0)))
            self.__dict__["_slot_vehicle"] = {}  # slot -> vehicle
            self.__dict__["_slot_state"] = {}  # slot -> its VehicleState
            self.__dict__["_slot_key"] = {}  # slot -> the vehicle's dmc key
            self.__dict__["_slots_cache"] = (None, -1, None)  # (vehicles list, generation, vehicle index -> slot)
            self.__dict__["_slots_gen"] = 0
            self.__dict__["_slot_source"] = {}  # slot -> param_source of its parameters
            self.__dict__["_alarm_seen"] = -1
        return f

    def new_vehicle(self, vehicle: str) -> VehicleState:
        cfg = self.vehicles_config.get(vehicle, {}) or {}
        dh_ref = float(cfg.get("dh_ref_rad", 0.0))
        f = self.fleet
        s = self.settings
        st = VehicleState(TimeAligner(self.sensors, s.pair_tolerance_s, float(getattr(s, "pair_max_wait_s", 10.0))),
                          None if f is not None else self.make_detector(vehicle, dh_ref),
                          declination_rad=float(cfg.get("declination_rad", 0.0)), dh_ref_rad=dh_ref)
        if f is not None:
            old = self._slot_of.pop(vehicle, None)
            if old is not None:  # the vehicle's state was dropped (handed over, taken back): its slot goes too
                self._free_slot(old)
            st.slot = f.add()
            self._slot_of[vehicle] = st.slot
            self._slot_vehicle[st.slot] = vehicle
            self._slot_state[st.slot] = st
            self._slot_key[st.slot] = keys.dmc(vehicle)
            self.__dict__["_slots_gen"] += 1
        self._load_manifest_params(vehicle, cfg, st)
        self._apply_params(st)
        self._adopt_published_alarm(vehicle, st)
        return st

    @property
    def _slot_of(self) -> dict:
        d = self.__dict__.get("_slot_of_d")
        if d is None:
            d = self.__dict__["_slot_of_d"] = {}
        return d

    def _free_slot(self, slot: int) -> None:
        self.fleet.free(slot)
        self.__dict__["_pairer"].free(slot)
        self._slot_vehicle.pop(slot, None)
        self._slot_state.pop(slot, None)
        self._slot_key.pop(slot, None)
        self.__dict__["_slots_gen"] += 1
        self._slot_source.pop(slot, None)

    def evict_vehicle(self, vehicle: str, state: VehicleState) -> None:
        if self.fleet is not None and self._slot_of.get(vehicle) == state.slot and state.slot >= 0:
            del self._slot_of[vehicle]
            self._free_slot(state.slot)

    def _load_manifest_params(self, vehicle: str, cfg: dict, st: VehicleState) -> None:
        for sensor, table in (cfg.get("mag_params") or {}).items():
            sensor = str(sensor)
            if sensor in self.required_sensors:
                try:
                    st.params[sensor] = MagParams.from_mapping(table, param_id="manifest")
                    st.param_origin[sensor] = "manifest"
                except (KeyError, ValueError, TypeError) as e:
                    self.log.error("vehicle %s: manifest mag_params.%s unusable: %s", vehicle, sensor, e)

    def _apply_params(self, st: VehicleState) -> None:
        """The vehicle's parameters into its fleet slot (once every required sensor has a set)."""
        f = self.fleet
        if f is None or any(s not in st.params for s in self.required_sensors):
            return
        a, b = self.sensors
        f.set_params(st.slot, st.params[a], st.params.get(b, st.params[a]), st.declination_rad, st.dh_ref_rad)
        self._slot_source[st.slot] = self._param_source(st)

    def on_message(self, info, msg: dict, state: VehicleState) -> None:
        if refuse_unphysical(self, info, msg):
            return
        if info.sensor not in self.sensors:
            self.count_drop(info.key, "sensor_not_used")
            return
        if info.kind == "cal":
            self._on_params(info, msg, state)
            return
        joined, gave = state.aligner.push(info.sensor, msg["t_s"], msg["b_nt"])
        for g in gave:  # its partner never came (passed), came too late (expired), or too many waited
            self.count_join_loss(keys.clean_mag(info.vehicle, g.stream), info.vehicle,
                                 "unpaired" if g.reason == "passed" else f"unpaired_{g.reason}")
        a, b = self.sensors
        for j in joined:
            self._on_epoch(info, state, j.t_s, np.asarray(j.values[a], float), np.asarray(j.values[b], float))

    def _on_params(self, info, msg: dict, state: VehicleState) -> None:
        if msg["status"] not in ("ok", "manifest"):
            self.log.info("vehicle %s sensor %s: ignoring cal/params %s with status %s", info.vehicle, info.sensor,
                          msg["param_id"], msg["status"])
            return
        try:
            p = MagParams.from_mapping(msg)
        except (KeyError, ValueError) as e:
            self.count_drop(info.key, "unusable_params")
            self.log.error("vehicle %s sensor %s: unusable cal/params: %s", info.vehicle, info.sensor, e)
            return
        current = state.params.get(info.sensor)
        if p.model == "2d" and current is not None and current.model == "3d":
            # a horizontal fit leaves z uncalibrated, so its Δm can only be the horizontal field strength,
            # which moves with every bit of pitch and roll (B_v sin θ ≈ 300 nT per half degree) and
            # raises false alarms; the 3-D set already held is the better reference for these tests
            state.ignored_2d[info.sensor] = p.param_id
            if not state.warned_2d:
                state.warned_2d = True
                self.log.info("vehicle %s: 2-D cal/params (%s) kept out of the interference tests: a 3-D set is "
                              "held", info.vehicle, p.param_id)
            return
        if current == p:
            return
        state.params[info.sensor] = p
        state.param_origin[info.sensor] = "cal" if msg["status"] == "ok" else "manifest"
        # new compensation: the feature windows restart so no rate spans two parameter sets
        if self.fleet is not None:
            self._apply_params(state)
            if state.slot >= 0 and self.fleet.params(state.slot) is not None:
                self.fleet.restart_features(state.slot)
        else:
            state.detector.restart_features()
        self.log.info("vehicle %s sensor %s: compensation %s from cal/params", info.vehicle, info.sensor,
                      p.param_id)

    def _param_source(self, state: VehicleState) -> str:
        origins = {state.param_origin.get(s) for s in self.required_sensors}
        return "cal" if origins == {"cal"} else "manifest"

    def _on_epoch(self, info, state: VehicleState, t_s: float, b_a, b_b) -> None:
        if not self._have_params(info, state):
            return
        if self.fleet is None:
            a, b = self.sensors
            d = state.detector.update(t_s, b_a, b_b, state.params[a], state.params[b], state.declination_rad)
            self._publish(info.vehicle, state, d, self._param_source(state))
            return
        self._sync_latches()
        self._decide(np.array([state.slot], np.int32), np.array([t_s]), np.asarray(b_a, float).reshape(1, 3),
                     np.asarray(b_b, float).reshape(1, 3))

    def _have_params(self, info, state: VehicleState) -> bool:
        missing = [s for s in self.required_sensors if s not in state.params]
        if not missing:
            return True
        self.count_drop(info.key, "no_compensation_params")
        if not state.warned_no_params:
            state.warned_no_params = True
            self.log.warning("vehicle %s: no compensation parameters for sensor(s) %s (manifest mag_params or "
                             "cal/params); epochs are dropped until they arrive", info.vehicle, ", ".join(missing))
        return False

    # ---- fleet frames ---------------------------------------------------------------------------------
    def on_frame(self, fr) -> None:
        """A frame's compass rows of every vehicle: paired, decided and published in a few calls."""
        f = self.fleet
        self._sync_latches()
        epochs = self._frame_epochs(fr)
        if epochs is None or not len(epochs):
            return
        ok = f._usable[epochs.slot]
        if not ok.all():
            for s in np.unique(epochs.slot[~ok]).tolist():
                v = self._slot_vehicle.get(int(s))
                if v is not None:
                    n = int((epochs.slot[~ok] == s).sum())
                    self.count_drop(keys.clean_mag(v, self.sensors[0]), "no_compensation_params", n)
                    st = self._slot_state.get(int(s))
                    if st is not None and not st.warned_no_params:
                        st.warned_no_params = True
                        missing = [x for x in self.required_sensors if x not in st.params]
                        self.log.warning("vehicle %s: no compensation parameters for sensor(s) %s (manifest "
                                         "mag_params or cal/params); epochs are dropped until they arrive", v,
                                         ", ".join(missing))
            keep = np.flatnonzero(ok)
            if not keep.size:
                return
            self._decide(epochs.slot[keep], epochs.t_s[keep], epochs.b_a_nt[keep], epochs.b_b_nt[keep])
            return
        self._decide(epochs.slot, epochs.t_s, epochs.b_a_nt, epochs.b_b_nt)

    def _frame_epochs(self, fr) -> Any:
        """The frame's epochs: each vehicle's two compasses paired by sample time (with samples still waiting
        from earlier frames); what is given up is counted as the single-sample path counts it."""
        a, b = self.sensors
        sa, sb = fr.streams.get(f"mag/{a}"), fr.streams.get(f"mag/{b}")
        if sa is None and sb is None:
            return None
        vi2slot = self._frame_slots(fr, [s for s in (sa, sb) if s is not None])
        empty_i, empty_t, empty_b = np.zeros(0, np.int32), np.zeros(0), np.zeros((0, 3))
        cols_a = (vi2slot[sa.vi], sa.t_s, sa.cols["b_nt"]) if sa is not None else (empty_i, empty_t, empty_b)
        cols_b = (vi2slot[sb.vi], sb.t_s, sb.cols["b_nt"]) if sb is not None else (empty_i, empty_t, empty_b)
        pairer = self.__dict__["_pairer"]
        epochs, given = pairer.pair(*cols_a, *cols_b)
        for g in (given, pairer.expire()):
            self._count_given_up(g)
        return epochs

    def _frame_slots(self, fr, streams_: list) -> np.ndarray:
        """Slot of each vehicle index of the frame that has rows here (-1 elsewhere); kept while the frame's
        vehicle list and this instance's vehicles stay the same."""
        vs, gen, cached = self._slots_cache
        present = np.unique(np.concatenate([s.vi for s in streams_])) if streams_ else np.zeros(0, np.uint32)
        if cached is not None and gen == self._slots_gen and vs == fr.vehicles and (cached[present] >= 0).all():
            return cached
        vi2slot = np.full(len(fr.vehicles), -1, np.int32) if cached is None or vs != fr.vehicles or \
            gen != self._slots_gen else cached
        slot_of = self._slot_of
        states = self.vehicle_states
        for i in present.tolist():
            v = fr.vehicles[i]
            s = slot_of.get(v)
            if s is None or states.get(v) is None:
                s = self.state_for(v).slot
            vi2slot[i] = s
        self.__dict__["_slots_cache"] = (fr.vehicles, self._slots_gen, vi2slot)
        return vi2slot

    def _count_given_up(self, g) -> None:
        if not len(g):
            return
        sensors = self.sensors
        for s, stream, reason in zip(g.slot.tolist(), g.stream.tolist(), g.reason.tolist(), strict=True):
            v = self._slot_vehicle.get(int(s))
            if v is None:
                continue
            r = REASONS[reason]
            self.count_join_loss(keys.clean_mag(v, sensors[stream]), v, "unpaired" if r == "passed" else f"unpaired_{r}")

    def _decide(self, slot: np.ndarray, t_s: np.ndarray, b_a: np.ndarray, b_b: np.ndarray) -> None:
        """Epochs (rows of slots in time order) through the fleet core; every decision published."""
        f = self.fleet
        out = f.step(slot, t_s, b_a, b_b)
        sv, sk = self._slot_vehicle, self._slot_key
        slots = out.slot.tolist()
        vehicles = [sv[s] for s in slots]
        src = self._slot_source
        cols = {"dm_nt": out.dm_nt, "ddm_nt_s": out.ddm_nt_s, "dh_rad": out.dh_rad, "ddh_rad_s": out.ddh_rad_s,
                "heading_rad": out.heading_rad, "stage1_pass": out.stage1_pass,
                "credibility": np.clip(out.credibility, 0.0, 1.0), "valid": out.valid, "impl": self.impl,
                "param_source": [src.get(s, "manifest") for s in slots]}
        self.publish_rows("dmc", [sk[s] for s in slots], vehicles, out.t_s, cols, mirror="dmc")
        stats = self._slot_state
        for s, ok in zip(slots, out.valid.tolist(), strict=True):
            st = stats[s]
            st.epochs += 1
            st.n_valid += ok
        for i in np.flatnonzero(out.transition).tolist():
            v = vehicles[i]
            transition = fleet.TRANSITIONS[int(out.transition[i])]
            reason, value, threshold, unit = f.describe(out, i)
            raised_t = out.raised_t_s[i]
            extra = {"raised_t_s": float(raised_t)} if not np.isnan(raised_t) else {}
            self.alarm(v, "dmc", transition, self.settings.severity, reason, value, threshold, float(out.t_s[i]),
                       unit=unit, **extra)

    def _sync_latches(self) -> None:
        """After a live swap, a group hand-over or a restart the runtime carries an alarm state the latches did
        not decide: align each vehicle's latch with it (this instance then clears an alarm it did not raise
        itself, and never raises one twice)."""
        rt = self._runtime
        if rt.alarm_adopted == self.__dict__.get("_alarm_seen", -1):
            return
        self.__dict__["_alarm_seen"] = rt.alarm_adopted
        for v, st in list(self.vehicle_states.items()):
            if st is not None:
                self._adopt_published_alarm(v, st)

    def _adopt_published_alarm(self, vehicle: str, state: VehicleState) -> None:
        """Align one vehicle's latch with the alarm state the mesh knows (live swap, hand-over, restart)."""
        rt = self._runtime
        if rt.mode != "active":
            return
        published = rt.alarm_published.get(keys.alarm(vehicle, "dmc"))
        f = self.fleet
        raised_now = bool(f.raised[state.slot]) if f is not None else state.detector.latch.raised
        if published is None or (published == "raised") == raised_now:
            return
        raised_msg = rt.raised_alarm(keys.alarm(vehicle, "dmc"))
        t = raised_msg.get("raised_t_s", raised_msg.get("t_s"))
        if f is not None:
            f.adopt(state.slot, published == "raised", t)
        else:
            state.detector.latch.adopt(published == "raised", t)
        self.log.info("vehicle %s: alarm state %s adopted from the mesh", vehicle, published)

    def _publish(self, vehicle: str, state: VehicleState, d: core.Decision, param_source: str) -> None:
        """One decision of a per-vehicle detector (implementations without a fleet core)."""
        state.epochs += 1
        state.n_valid += int(d.valid)
        # per vehicle, and as a one-row dmc frame (the heading fuser takes verdicts from the frames)
        self.publish_rows("dmc", [keys.dmc(vehicle)], [vehicle], [d.t_s], {
            "dm_nt": [d.dm_nt], "ddm_nt_s": [d.ddm_nt_s], "dh_rad": [d.dh_rad], "ddh_rad_s": [d.ddh_rad_s],
            "heading_rad": [d.heading_rad], "stage1_pass": [d.stage1_pass], "credibility": [d.credibility],
            "valid": [d.valid], "impl": self.impl, "param_source": [param_source]}, mirror="dmc")
        if d.transition is None:
            self._sync_latches()
            self._adopt_published_alarm(vehicle, state)
        else:
            reason, value, threshold, unit = state.detector.describe(d)
            raised_t = state.detector.latch.raised_t_s
            extra = {"raised_t_s": raised_t} if raised_t is not None else {}
            self.alarm(vehicle, "dmc", d.transition, self.settings.severity, reason, value, threshold, d.t_s,
                       unit=unit, **extra)

    def status_extra(self) -> dict:
        out = {}
        f = self.fleet
        pairer = self.__dict__.get("_pairer")
        for v, st in list(self.vehicle_states.items()):
            if st is None:
                continue
            al = st.aligner.counts() if st.aligner is not None else {"joined": 0, "gave_up": {}, "gave_up_total": 0}
            if pairer is not None and st.slot >= 0:
                fc = pairer.counts(st.slot)
                al = {"joined": al["joined"] + fc["joined"], "gave_up_total": al["gave_up_total"] + fc["gave_up_total"],
                      "gave_up": {r: {k: al["gave_up"].get(r, {}).get(k, 0) + fc["gave_up"].get(r, {}).get(k, 0)
                                      for k in set(al["gave_up"].get(r, {})) | set(fc["gave_up"].get(r, {}))}
                                  for r in set(al["gave_up"]) | set(fc["gave_up"])}}
            if f is not None:
                flags, internal = f.flags(st.slot), f.internal_states(st.slot)
            else:
                flags, internal = st.detector.flags, st.detector.internal_states
            out[v] = {"epochs": st.epochs, "valid_frac": round(st.n_valid / st.epochs, 4) if st.epochs else None,
                      "params": {s: {"origin": st.param_origin.get(s), "param_id": p.param_id, "model": p.model}
                                 for s, p in st.params.items()},
                      "cal_params_2d_not_used": dict(st.ignored_2d),
                      "aligner": al, "flags": flags, "internal_states": internal}
        return {"detector": out}


_UNSET = object()


class ThresholdDmcDetector(DmcDetectorService):
    """Stage 1 only: the four threshold tests of the differential compass (docs/methods.md#dmc)."""

    impl = "threshold"
