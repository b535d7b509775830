"""Calibration: fit each magnetometer's hard/soft iron and publish the compensated field.

What it consumes and produces is declared on :class:`Calibration` (``INPUTS``, ``OUTPUTS``; ``--help`` lists them).
Parameter sets persist as JSON under ``state_dir()/calibration/`` and are reloaded on start; the
manifest's ``mag_params`` table (status "manifest") is used until a fit or a saved set exists. A
fresh fit replaces the set in use only when it fits the current samples better (see core.py).

One implementation serves both inputs: :class:`services.calibration.fleet.FleetCalibration` holds every vehicle's
state. A fleet frame (``on_frame``) is handled in one call for all its vehicles and its compensated samples go out
as one ``cal`` frame (each row numbered on its per-vehicle ``cal/mag`` key); a single sample (``on_message``, when
ingest publishes singles) is the same call with one row, and goes out as one ``cal/mag`` message. Fits run within
``fit_budget_frac`` of a core (the most overdue first; fleet.py), parameter sets always go out on ``cal/params``.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass

import numpy as np

from magmesh import declare, magcal, paths
from magmesh.declare import Input, Output, setting
from magmesh.runtime import Service, shed_after_setting
from schemas import frame as fleetframe
from schemas import keys
from services.physical import refuse_unphysical

from . import online_ekf
from .core import USABLE, CalibrationSettings, OnlineSettings, ParamRecord
from .fleet import FleetCalibration, GnssIn, ImuIn, MagIn


@dataclass(frozen=True)
class Settings:
    tick_s: float = setting(1.0, "fit attempts that waited for the budget and persistence run from this tick", gt=0)
    method: str = setting("arls", "arls: ARLS with IGG-III weights (robust); ls: Two-Step least squares",
                          choices=("arls", "ls"))
    model: str = setting("auto", "auto: 3-D when the attitude coverage allows, else 2-D (horizontal ellipse)",
                         choices=("auto", "2d", "3d"))
    window_s: float = setting(600.0, "fit window: samples older than this (sample time) leave it", gt=0)
    sample_interval_s: float = setting(0.05, "decimation of the fit window: at most one sample per interval", lo=0)
    refit_interval_s: float = setting(5.0, "fit attempt period, sample time", gt=0)
    fit_budget_frac: float = setting(0.04, "share of one core fits may take (CPU time), split evenly among a "
                                     "group's members; 0: no limit (fit when due)", lo=0)
    window_max_samples: int = setting(0, "fit window bound; 0: what window_s / sample_interval_s allows", lo=0)
    field_radius_nt: float = setting(0.0, "> 0: scale the compensated field to this strength; 0: the fitted radius",
                                     lo=0)
    improve_ratio: float = setting(0.95, "a new set replaces the one in use only with a residual below this × its "
                                   "residual", gt=0, hi=1)
    k0: float = setting(1.5, "IGG-III lower threshold (standardised residuals): full weight below it")
    k1: float = setting(3.0, "IGG-III upper threshold: zero weight above it")
    min_samples: int = setting(150, "samples a fit needs at least")
    min_coverage_2d: float = setting(0.75, "share of the 10° heading bins a 2-D fit needs", lo=0, hi=1)
    min_coverage_3d: float = setting(0.55, "share of the sphere cells a 3-D fit needs", lo=0, hi=1)
    online_ekf: bool = setting(True, "run the GNSS-aided online hard-iron EKF")
    ekf_prior_std_nt: float = setting(5000.0, "EKF: 1-σ of the initial offset estimate, per axis", gt=0)
    ekf_heading_noise_deg: float = setting(2.0, "EKF: magnetometer heading noise + sideslip, 1-σ", gt=0)
    ekf_min_speed_m_s: float = setting(3.0, "EKF: below this speed the GNSS course is not the heading")
    ekf_gate_sigma: float = setting(3.0, "EKF: innovation gate, standard deviations", gt=0)
    ekf_random_walk_nt_sqrt_s: float = setting(30.0, "EKF process noise: how fast the hard iron may change")
    ekf_tilt: str = setting("level", "level: roll = pitch = 0 (as a car's 2-D compass is read); accel: IMU tilt",
                            choices=("level", "accel"))
    ekf_kinds: str = setting("car", "manifest vehicle kinds whose GNSS course is their heading (comma-separated); "
                             "vehicles without a manifest kind are served too")
    publish_cal_mag: bool = setting(True, "publish cal/mag (false: publish parameters only)")
    persist: bool = setting(True, "keep parameter sets on disk (state_dir()/state_subdir) and reload them on start")
    state_subdir: str = setting("calibration", "directory of the saved parameter sets under state_dir()")
    shed_after_s: float = shed_after_setting()

    def __post_init__(self) -> None:
        declare.check(self)


def _gist(reason: str) -> str:
    """A refusal reason without its numbers: "only 12 samples" and "only 13 samples" say the same."""
    return re.sub(r"[0-9.]+", "#", reason)


def _safe(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.\-]", "_", s)


class Calibration(Service):
    role = "calibration"
    impl = "calibration"
    Settings = Settings
    INPUTS = (
        Input("magmesh/{vehicle}/clean/mag/{sensor}", "samples to fit (Two-Step LS or ARLS, 2-D or 3-D) and to "
              "compensate", sensors="*"),
        Input("magmesh/{vehicle}/clean/imu", "roll/pitch for the online EKF", when="online_ekf"),
        Input("magmesh/{vehicle}/clean/gnss", "course for the online GNSS-aided hard-iron EKF", when="online_ekf"),
    )
    OUTPUTS = (
        Output("magmesh/{vehicle}/cal/mag/{sensor}", "h = M (m − offset), calibrated=true, param_id",
               when="publish_cal_mag"),
        Output("magmesh/fleet/{shard}/cal", "the compensated samples of a fleet frame's vehicles, per input frame",
               when="publish_cal_mag"),
        Output("magmesh/{vehicle}/cal/params/{sensor}", "the parameter set in use; republished on change and "
               "answered by query (late joiners)"),
    )

    # ---- wiring -----------------------------------------------------------------------------
    def queryables(self) -> dict:
        return {keys.cal_params(self.vehicle_pattern, "*"): self._answer_params}

    def on_start(self) -> None:
        s = self.settings
        self.cal_settings = CalibrationSettings(
            method=s.method, model=s.model, window_s=s.window_s, sample_interval_s=s.sample_interval_s,
            refit_interval_s=s.refit_interval_s, field_radius_nt=s.field_radius_nt, improve_ratio=s.improve_ratio,
            k0=s.k0, k1=s.k1, min_samples=s.min_samples, min_coverage_2d=s.min_coverage_2d,
            min_coverage_3d=s.min_coverage_3d, window_max_samples=s.window_max_samples)
        self.online_settings = OnlineSettings(
            enabled=s.online_ekf, tilt_source=s.ekf_tilt,
            ekf=online_ekf.EkfSettings(prior_std_nt=s.ekf_prior_std_nt,
                                       heading_noise_rad=math.radians(s.ekf_heading_noise_deg),
                                       min_speed_m_s=s.ekf_min_speed_m_s, gate_sigma=s.ekf_gate_sigma,
                                       random_walk_nt_sqrt_s=s.ekf_random_walk_nt_sqrt_s))
        # slots for the manifest's vehicles and their magnetometers made now (two per vehicle at least: a DMC car's
        # pair): growing them while a fleet first arrives copies every window array at once (about 1 s of the
        # loop at 500 vehicles), a stall the stages after see as seconds of queued input
        sensors = sum(max(2, len((c or {}).get("mag_params", {}) or {})) for c in self.vehicles_config.values())
        self.fleet = FleetCalibration(self.cal_settings, self.online_settings, fit_budget_frac=s.fit_budget_frac,
                                      capacity=max(16, sensors))
        from .fleet import warm

        warm()  # compile (or load from numba's disk cache) before serving: never on a sample
        self.fleet.declinations.warm()  # the IGRF coefficients read once now (0.8 s), not on the first GNSS fix
        self._by_name: dict[str, VehicleSlot] = {}
        self._vcache: list | None = None  # on_frame: the last frame's vehicle list and their slots
        self._unusable = np.zeros(0, np.int64)  # on_frame: rows without a usable set per sensor slot (to count)
        self._vgen = 0
        self.last_msgs: dict[str, dict] = {}  # cal/params key → last message published
        self.dirty: set[tuple[str, str]] = set()
        self.saved = self._load_saved()
        self.log.info("loaded %d saved parameter set(s) from %s", sum(len(v) for v in self.saved.values()),
                      self._dir())
        import zenoh

        served = zenoh.KeyExpr(keys.cal_params(self.vehicle_pattern, "*"))
        for vehicle in self.saved:
            if served.intersects(zenoh.KeyExpr(keys.cal_params(vehicle, "*"))):
                self.state_for(vehicle)  # publishes the saved sets now: a late joiner need not wait for data

    def on_stop(self) -> None:
        self._flush_unusable()
        self._persist()

    # ---- per vehicle ------------------------------------------------------------------------
    def new_vehicle(self, vehicle: str) -> VehicleSlot:
        cfg = self.vehicles_config.get(vehicle, {}) or {}
        initial: dict[str, ParamRecord] = {}
        for sid, table in (cfg.get("mag_params") or {}).items():
            try:
                p = magcal.MagParams.from_message(table)
                initial[str(sid)] = ParamRecord(p, f"{sid}-manifest", "manifest", "manifest",
                                                reason="from the mesh manifest")
            except (KeyError, TypeError, ValueError) as e:
                self.log.error("vehicle %s: manifest mag_params.%s unusable: %s", vehicle, sid, e)
        initial.update(self.saved.get(vehicle, {}))  # a saved fit outranks the manifest
        decl = cfg.get("declination_rad") if cfg.get("declination_source") == "manifest" else None
        kind = cfg.get("kind")
        kinds = {k.strip() for k in self.settings.ekf_kinds.split(",") if k.strip()}
        # a multirotor flies sideways, a replayed recording has no GNSS: course is not heading
        online = self.online_settings.enabled and (kind is None or kind in kinds)
        old = self._by_name.pop(vehicle, None)
        if old is not None:  # the runtime dropped its state (a group hand-over): start the vehicle afresh
            self._flush_unusable(list(self.fleet.sensors(old.vslot).values()))
            self.fleet.free_vehicle(old.vslot)
        vs = VehicleSlot(vehicle, self.fleet.add_vehicle(vehicle, online, decl, initial))
        self._by_name[vehicle] = vs
        self._vgen += 1
        self.log.info("vehicle %s (kind %s): online EKF %s", vehicle, kind or "unknown", "on" if online else "off")
        for sid in initial:
            self._publish_params(vehicle, sid, self.fleet.records[self.fleet.sensors(vs.vslot)[sid]],
                                 t_s=initial[sid].fit_t_s)
        return vs

    def evict_vehicle(self, vehicle: str, state: VehicleSlot) -> None:
        if self._by_name.get(vehicle) is state:
            del self._by_name[vehicle]
            self._flush_unusable(list(self.fleet.sensors(state.vslot).values()))
            self.fleet.free_vehicle(state.vslot)
            self._vgen += 1

    def on_message(self, info, msg, state: VehicleSlot) -> None:
        """One sample (contract v1, or the runtime's per-sample hand-out): the fleet core with one row."""
        if refuse_unphysical(self, info, msg):
            return
        stream = info.stream
        fc = self.fleet
        one = _ONE
        t = np.array([msg["t_s"]], float)
        if stream == "mag":
            sid = info.sensor
            slot = fc.add_sensor(state.vslot, sid)
            step = fc.step([MagIn(sid, one, np.array([slot], np.int64), t, np.array([msg["b_nt"]], float))])
            self._handle(step.events)
            if not self.settings.publish_cal_mag:
                return
            if not step.usable[0][0]:
                self.count_drop(info.key, "no_usable_params")
                return
            fields = {"sensor": sid, "b_nt": [float(x) for x in step.h[0][0]], "calibrated": True,
                      "param_id": step.param_ids(0)[0]}
            if "temp_c" in msg:
                fields["temp_c"] = msg["temp_c"]
            self.publish(keys.cal_mag(info.vehicle, sid), "mag", info.vehicle, msg["t_s"], **fields)
        elif stream == "imu":
            fc.step([ImuIn(one, np.array([state.vslot], np.int64), t, np.array([msg["gyro_rad_s"]], float),
                           np.array([msg["accel_m_s2"]], float))])
        elif stream == "gnss":
            cols = {k: [msg[k]] for k in _GNSS_FIELDS}
            self._handle(fc.step([GnssIn(one, np.array([state.vslot], np.int64), t, cols)]).events)

    def on_frame(self, fr) -> None:
        """A fleet frame: every vehicle's mag, imu and gnss rows in one call; the compensated samples out as one
        ``cal`` frame."""
        fc = self.fleet
        names = fr.vehicles
        vmap = self._vehicle_slots(names, fr.streams.values())
        inputs, mags, new = [], [], []
        for j, (name, st) in enumerate(fr.streams.items()):
            head, _, sid = name.partition("/")
            vsl = vmap[st.vi]
            if head == "mag":
                slots = fc.sensor_slots(vsl, sid)
                miss = np.flatnonzero(slots < 0)
                if miss.size:  # a vehicle's first rows of this sensor: its first row decides the creation order
                    first = miss[np.r_[True, st.vi[miss][1:] != st.vi[miss][:-1]]]
                    new += [(int(st.vi[i]), float(st.t_s[i]), j, int(vsl[i]), sid) for i in first.tolist()]
                x = MagIn(sid, st.vi, slots, st.t_s, st.cols["b_nt"])
                mags.append((x, st))
            elif head == "imu":
                x = ImuIn(st.vi, vsl, st.t_s, st.cols["gyro_rad_s"], st.cols["accel_m_s2"])
            elif head == "gnss":
                x = GnssIn(st.vi, vsl, st.t_s, st.cols)
            else:
                continue
            inputs.append(x)
        if new:
            for _, _, _, v, sid in sorted(new):
                fc.add_sensor(v, sid)
            for x, st in mags:
                x.slots = fc.sensor_slots(vmap[st.vi], x.sid)
        step = fc.step(inputs)
        self._handle(step.events)
        if not self.settings.publish_cal_mag or not mags:
            return
        out = {}
        for i, (x, st) in enumerate(mags):
            use = step.usable[i]
            every = bool(use.all())
            if not every:  # counted per sensor slot here, handed to the drop counts at the tick
                if self._unusable.shape[0] < fc.SF.shape[0]:
                    self._unusable = np.concatenate([self._unusable,
                                                     np.zeros(fc.SF.shape[0] - self._unusable.shape[0], np.int64)])
                np.add.at(self._unusable, x.slots[~use], 1)
            if every:  # (the common case: no copies)
                rows = None
                h, vi, t = step.h[i], st.vi, st.t_s
            else:
                rows = np.flatnonzero(use)
                if not rows.size:
                    continue
                h, vi, t = step.h[i][rows], st.vi[rows], st.t_s[rows]
            cols = {"sensor": x.sid, "b_nt": h, "calibrated": np.ones(len(t), np.uint8),
                    "param_id": step.param_id_column(i, rows)}
            temp = st.cols.get("temp_c")
            if isinstance(temp, np.ndarray):
                cols["temp_c"] = temp if rows is None else temp[rows]
            out[f"mag/{x.sid}"] = fleetframe.Stream(f"mag/{x.sid}", "mag", vi, t, None, cols)
        if out:
            self.publish_frame("cal", names, out)

    def _vehicle_slots(self, names: list[str], streams) -> np.ndarray:
        """Each frame vehicle's slot (−1: no rows seen yet), kept while the frame's vehicle list and the runtime's
        vehicle states stay the same (any new state goes through new_vehicle, any dropped one shrinks the table)."""
        states = self.vehicle_states
        c = self._vcache
        if c is None or c[1] != len(states) or c[2] != self._vgen or c[0] != names:
            c = self._vcache = [names, len(states), self._vgen, np.full(len(names), -1, np.int64)]
        vmap = c[3]
        for st in streams:
            miss = vmap[st.vi] < 0
            if miss.any():
                for i in np.unique(st.vi[miss]).tolist():
                    vs = states.get(names[i])
                    vmap[i] = (vs if vs is not None else self.state_for(names[i])).vslot
                c[1], c[2] = len(states), self._vgen
        return vmap

    def _handle(self, events) -> None:
        """Publish what the fleet core decided: fitted sets, refusals while nothing usable is in use, EKF sets."""
        for e in events:
            if e.kind == "ekf":
                rec = e.record
                self.log.info("vehicle %s sensor %s: %s parameter set %s (%s)", e.vehicle, e.sensor, rec.status,
                              rec.param_id, rec.reason)
                self._publish_params(e.vehicle, e.sensor, rec, e.t_s)
                continue
            a = e.attempt
            if a.accepted:
                r = a.record
                self.log.info("vehicle %s sensor %s: new %s %s fit %s, rmse %.0f nT, %d gross errors rejected (%s)",
                              e.vehicle, e.sensor, r.params.model, r.method, r.param_id, r.rmse_nt or -1,
                              r.n_gross_rejected, a.reason)
                self._publish_params(e.vehicle, e.sensor, r, e.t_s)
            elif e.had is None or e.had.status not in USABLE:
                # nothing usable yet: say why on cal/params (once per distinct reason)
                last = self.last_msgs.get(keys.cal_params(e.vehicle, e.sensor))
                if a.record is not None and (last is None or _gist(last.get("reason", "")) != _gist(a.reason)):
                    self.log.info("vehicle %s sensor %s: fit refused: %s", e.vehicle, e.sensor, a.reason)
                    self._publish_params(e.vehicle, e.sensor, a.record, e.t_s, persist=False)

    # ---- parameters: publish, answer, persist -----------------------------------------------
    def _publish_params(self, vehicle: str, sid: str, rec: ParamRecord | None, t_s: float, persist: bool = True):
        if rec is None:
            return
        key = keys.cal_params(vehicle, sid)
        self.last_msgs[key] = self.publish(key, "cal_params", vehicle, t_s, **rec.message_fields(sid))
        if persist and rec.status in ("ok", "converging"):
            self.dirty.add((vehicle, sid))

    def _answer_params(self, query_key: str, params: dict) -> list[tuple[str, dict]]:
        import zenoh

        qke = zenoh.KeyExpr(query_key)
        return [(k, m) for k, m in list(self.last_msgs.items()) if qke.intersects(zenoh.KeyExpr(k))]

    def on_tick(self) -> None:
        # in a group of N the role's budget is split: N members fit no more in all than one process would
        self.fleet.set_fit_budget(self.settings.fit_budget_frac * self.group_share)
        self._handle(self.fleet.run_queued())  # fits that waited for the budget
        self._flush_unusable()
        self._free_dropped()
        self._persist()

    def _free_dropped(self) -> None:
        """Give back the slots of vehicles whose state the runtime dropped without evicting them (a group member
        that handed a vehicle over forgets it)."""
        states = self.vehicle_states
        for name, vs in list(self._by_name.items()):
            if states.get(name) is not vs:
                del self._by_name[name]
                self._flush_unusable(list(self.fleet.sensors(vs.vslot).values()))
                self.fleet.free_vehicle(vs.vslot)
                self._vgen += 1

    def _flush_unusable(self, slots=None) -> None:
        """Frame rows that had no usable set, counted as drops (``no_usable_params``) on their clean key."""
        u = self._unusable
        fc = self.fleet
        for s in (np.flatnonzero(u) if slots is None else [s for s in slots if s < u.shape[0] and u[s]]):
            s = int(s)
            v = fc.vnames[fc.vslot_of(s)]
            if v is not None and fc.sids[s] is not None:
                self.count_drop(keys.clean_mag(v, fc.sids[s]), "no_usable_params", int(u[s]))
            u[s] = 0

    def _dir(self):
        return paths.state_dir() / _safe(self.settings.state_subdir)

    def _persist(self) -> None:
        if not self.settings.persist or not getattr(self, "dirty", None):
            return
        d = self._dir()
        d.mkdir(parents=True, exist_ok=True)
        for vehicle, sid in list(self.dirty):
            vs = self.vehicle_states.get(vehicle)
            slot = self.fleet.sensors(vs.vslot).get(sid) if vs else None
            cur = self.fleet.records[slot] if slot is not None else None
            if cur is None or cur.status not in ("ok", "converging"):
                continue
            path = d / f"{_safe(vehicle)}__{_safe(sid)}.json"
            paths.write_atomic(path, json.dumps({"vehicle": vehicle, "sensor": sid, "record": cur.to_json()}, indent=1))
        self.dirty.clear()

    def _load_saved(self) -> dict[str, dict[str, ParamRecord]]:
        out: dict[str, dict[str, ParamRecord]] = {}
        if not self.settings.persist:
            return out
        d = self._dir()
        if not d.is_dir():
            return out
        for path in sorted(d.glob("*.json")):
            try:
                obj = json.loads(path.read_text())
                rec = ParamRecord.from_json(obj["record"])
                out.setdefault(obj["vehicle"], {})[obj["sensor"]] = rec
            except (OSError, ValueError, KeyError, TypeError) as e:
                self.log.error("ignoring unreadable saved parameters %s: %s", path, e)
        return out

    def status_extra(self) -> dict:
        fc = self.fleet
        vehicles = {}
        rows = []
        for v, vs in list(self.vehicle_states.items()):
            if vs is None:
                continue
            sensors = {}
            for sid, slot in list(fc.sensors(vs.vslot).items()):
                cur = fc.records[slot]
                entry = fc.sensor_entry(slot)
                if cur is not None:
                    entry["params"] = {
                        "status": cur.status, "method": cur.method, "model": cur.params.model,
                        "offset_nt": [round(x, 1) for x in cur.params.offset_nt],
                        "field_radius_nt": round(cur.params.field_radius_nt, 1),
                        "rmse_nt": None if cur.rmse_nt is None else round(cur.rmse_nt, 1),
                        "coverage_frac": round(cur.coverage_frac, 3), "observable": list(cur.params.observable),
                        "n_gross_rejected": cur.n_gross_rejected,
                    }
                ekf = fc.ekf_states(slot)
                if ekf is not None:
                    entry["ekf"] = ekf
                sensors[sid] = entry
                rows.append((v, sid, cur))
            vehicles[v] = {"sensors": sensors, "gnss_unusable_reason": fc.gnss_reason(vs.vslot)}
        parts = []
        for v, sid, cur in sorted(rows, key=lambda r: (r[0], r[1])):
            if cur is None:
                parts.append(f"{v}/{sid} none")
            else:
                rmse = "" if cur.rmse_nt is None else f" {cur.rmse_nt:.0f}nT"
                parts.append(f"{v}/{sid} {cur.status} {cur.method} {cur.params.model}{rmse}")
        # "summary" first: `magmesh status` shows the start of this entry in its NOTE column
        return {"calibration": {"summary": "; ".join(parts), "vehicles": vehicles, "fits": fc.scheduler_status()}}


@dataclass(eq=False)
class VehicleSlot:
    """What the runtime keeps per vehicle: its slot in the fleet core (the state itself lives there)."""

    name: str
    vslot: int


_ONE = np.zeros(1, np.int64)
_GNSS_FIELDS = ("speed_m_s", "course_rad", "fix_type", "num_sats", "pdop", "lat_deg", "lon_deg", "alt_m")
