"""Calibration: fit each magnetometer's hard/soft iron and publish the compensated field.

Consumes  magmesh/{vehicle}/clean/mag/{sensor}   samples to fit (Two-Step LS or ARLS, 2-D or 3-D)
          magmesh/{vehicle}/clean/imu            roll/pitch for the online EKF
          magmesh/{vehicle}/clean/gnss           course for the online GNSS-aided hard-iron EKF
Produces  magmesh/{vehicle}/cal/mag/{sensor}     h = M (m − offset), calibrated=true, param_id
          magmesh/{vehicle}/cal/params/{sensor}  the parameter set in use; republished on change and
                                                 answered by query (late joiners)

Parameter sets persist as JSON under ``state_dir()/calibration/`` and are reloaded on start; the
manifest's ``mag_params`` table (status "manifest") is used until a fit or a saved set exists. A
fresh fit replaces the set in use only when it fits the current samples better (see core.py).
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass, replace

from magmesh import magcal, paths
from magmesh.runtime import Service
from schemas import keys
from services.physical import refuse_unphysical

from . import online_ekf
from .core import USABLE, CalibrationSettings, OnlineSettings, ParamRecord, VehicleCalibration


@dataclass(frozen=True)
class Settings:
    tick_s: float = 1.0  # fit attempts and persistence run from the tick
    method: str = "arls"  # arls | ls
    model: str = "auto"  # auto | 2d | 3d
    window_s: float = 600.0  # fit window, s of sample time
    sample_interval_s: float = 0.05  # decimation of the fit window, s
    refit_interval_s: float = 5.0  # fit attempt period, s of sample time
    field_radius_nt: float = 0.0  # > 0: scale |h| to this; 0: the fitted radius
    improve_ratio: float = 0.95  # a new set must have a residual below this × the current one's
    k0: float = 1.5  # IGG-III lower threshold, standardised residuals
    k1: float = 3.0  # IGG-III upper threshold
    min_samples: int = 150
    min_coverage_2d: float = 0.75  # share of 10° heading bins a 2-D fit needs
    min_coverage_3d: float = 0.55  # share of sphere cells a 3-D fit needs
    online_ekf: bool = True  # run the GNSS-aided hard-iron EKF
    ekf_prior_std_nt: float = 5000.0
    ekf_heading_noise_deg: float = 2.0
    ekf_min_speed_m_s: float = 3.0
    ekf_gate_sigma: float = 3.0
    ekf_random_walk_nt_sqrt_s: float = 30.0  # how fast the hard iron may change (process noise)
    ekf_tilt: str = "level"  # level (roll = pitch = 0, as a car's 2-D compass is read) | accel (IMU tilt)
    ekf_kinds: str = "car"  # manifest vehicle kinds whose GNSS course is their heading (comma-separated);
    #                         vehicles without a manifest kind are served too
    publish_cal_mag: bool = True  # publish cal/mag (set false to publish parameters only)
    persist: bool = True  # keep parameter sets on disk
    state_subdir: str = "calibration"


def _gist(reason: str) -> str:
    """A refusal reason without its numbers: "only 12 samples" and "only 13 samples" say the same."""
    return re.sub(r"[0-9.]+", "#", reason)


def _safe(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.\-]", "_", s)


class Calibration(Service):
    role = "calibration"
    impl = "calibration"
    Settings = Settings
    CONSUMES = ("clean/mag/{sensor}", "clean/imu", "clean/gnss")
    PRODUCES = ("cal/mag/{sensor}", "cal/params/{sensor}")

    # ---- wiring -----------------------------------------------------------------------------
    def subscriptions(self) -> list[str]:
        p = self.vehicle_pattern
        subs = [keys.clean_mag(p, "*")]
        if self.settings.online_ekf:
            subs += [keys.clean_imu(p), keys.clean_gnss(p)]
        return subs

    def queryables(self) -> dict:
        return {keys.cal_params(self.vehicle_pattern, "*"): self._answer_params}

    def on_start(self) -> None:
        s = self.settings
        self.cal_settings = CalibrationSettings(
            method=s.method, model=s.model, window_s=s.window_s, sample_interval_s=s.sample_interval_s,
            refit_interval_s=s.refit_interval_s, field_radius_nt=s.field_radius_nt, improve_ratio=s.improve_ratio,
            k0=s.k0, k1=s.k1, min_samples=s.min_samples, min_coverage_2d=s.min_coverage_2d,
            min_coverage_3d=s.min_coverage_3d)
        if s.ekf_tilt not in ("level", "accel"):
            raise ValueError(f"ekf_tilt must be 'level' or 'accel', got {s.ekf_tilt!r}")
        self.online_settings = OnlineSettings(
            enabled=s.online_ekf, tilt_source=s.ekf_tilt,
            ekf=online_ekf.EkfSettings(prior_std_nt=s.ekf_prior_std_nt,
                                       heading_noise_rad=math.radians(s.ekf_heading_noise_deg),
                                       min_speed_m_s=s.ekf_min_speed_m_s, gate_sigma=s.ekf_gate_sigma,
                                       random_walk_nt_sqrt_s=s.ekf_random_walk_nt_sqrt_s))
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
        self._persist()

    # ---- per vehicle ------------------------------------------------------------------------
    def new_vehicle(self, vehicle: str) -> VehicleCalibration:
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
        online = self.online_settings
        if kind is not None and kind not in kinds:
            # a multirotor flies sideways, a replayed recording has no GNSS: course is not heading
            online = replace(online, enabled=False)
        vc = VehicleCalibration(vehicle, self.cal_settings, online, initial, decl)
        self.log.info("vehicle %s (kind %s): online EKF %s", vehicle, kind or "unknown",
                      "on" if online.enabled else "off")
        for sid in initial:
            vc.sensor(sid)
            self._publish_params(vehicle, sid, vc.sensors[sid].current, t_s=initial[sid].fit_t_s)
        return vc

    def on_message(self, info, msg, state: VehicleCalibration) -> None:
        if refuse_unphysical(self, info, msg):
            return
        stream = info.stream
        if stream == "mag":
            self._on_mag(info, msg, state)
        elif stream == "imu":
            state.on_imu(msg["t_s"], msg["gyro_rad_s"], msg["accel_m_s2"])
        elif stream == "gnss":
            for sid, rec in state.on_gnss(msg["t_s"], msg):
                self.log.info("vehicle %s sensor %s: %s parameter set %s (%s)", info.vehicle, sid, rec.status,
                              rec.param_id, rec.reason)
                self._publish_params(info.vehicle, sid, rec, msg["t_s"])

    def _on_mag(self, info, msg, state: VehicleCalibration) -> None:
        sid = info.sensor
        sc = state.on_mag(sid, msg["t_s"], msg["b_nt"])
        if sc.due(msg["t_s"]):
            had = sc.current
            attempt = sc.fit(msg["t_s"])
            if attempt.accepted:
                self.log.info("vehicle %s sensor %s: new %s %s fit %s, rmse %.0f nT, %d gross errors rejected (%s)",
                              info.vehicle, sid, attempt.record.params.model, attempt.record.method,
                              attempt.record.param_id, attempt.record.rmse_nt or -1, attempt.record.n_gross_rejected,
                              attempt.reason)
                self._publish_params(info.vehicle, sid, sc.current, msg["t_s"])
            elif had is None or had.status not in USABLE:
                # nothing usable yet: say why on cal/params (once per distinct reason)
                last = self.last_msgs.get(keys.cal_params(info.vehicle, sid))
                if attempt.record is not None and (last is None or _gist(last.get("reason", "")) != _gist(attempt.reason)):
                    self.log.info("vehicle %s sensor %s: fit refused: %s", info.vehicle, sid, attempt.reason)
                    self._publish_params(info.vehicle, sid, attempt.record, msg["t_s"], persist=False)
        cur = sc.current
        if not self.settings.publish_cal_mag:
            return
        if cur is None or cur.status not in USABLE:
            self.count_drop(info.key, "no_usable_params")
            return
        h = cur.params.apply(msg["b_nt"])
        fields = {"sensor": sid, "b_nt": [float(x) for x in h], "calibrated": True, "param_id": cur.param_id}
        if "temp_c" in msg:
            fields["temp_c"] = msg["temp_c"]
        self.publish(keys.cal_mag(info.vehicle, sid), "mag", info.vehicle, msg["t_s"], **fields)

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
        self._persist()

    def _dir(self):
        return paths.state_dir() / _safe(self.settings.state_subdir)

    def _persist(self) -> None:
        if not self.settings.persist or not getattr(self, "dirty", None):
            return
        d = self._dir()
        d.mkdir(parents=True, exist_ok=True)
        for vehicle, sid in list(self.dirty):
            vc = self.vehicle_states.get(vehicle)
            sc = vc.sensors.get(sid) if vc else None
            if sc is None or sc.current is None or sc.current.status not in ("ok", "converging"):
                continue
            path = d / f"{_safe(vehicle)}__{_safe(sid)}.json"
            tmp = path.with_suffix(".tmp")
            tmp.write_text(json.dumps({"vehicle": vehicle, "sensor": sid, "record": sc.current.to_json()}, indent=1))
            os.replace(tmp, path)  # atomic: a crash never leaves half a file
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
        vehicles = {}
        for v, vc in list(self.vehicle_states.items()):
            if vc is None:
                continue
            sensors = {}
            for sid, sc in list(vc.sensors.items()):
                cur = sc.current
                entry = dict(sc.internal_states)
                if cur is not None:
                    entry["params"] = {
                        "status": cur.status, "method": cur.method, "model": cur.params.model,
                        "offset_nt": [round(x, 1) for x in cur.params.offset_nt],
                        "field_radius_nt": round(cur.params.field_radius_nt, 1),
                        "rmse_nt": None if cur.rmse_nt is None else round(cur.rmse_nt, 1),
                        "coverage_frac": round(cur.coverage_frac, 3), "observable": list(cur.params.observable),
                        "n_gross_rejected": cur.n_gross_rejected,
                    }
                onl = vc.onl.get(sid)
                if onl is not None:
                    entry["ekf"] = {**onl.ekf.internal_states, **onl.ekf.flags}
                sensors[sid] = entry
            vehicles[v] = {"sensors": sensors, "gnss_unusable_reason": vc.gnss_reason}
        parts = []
        for v, vc in sorted(list(self.vehicle_states.items())):
            for sid, sc in sorted(list(vc.sensors.items()) if vc else []):
                cur = sc.current
                if cur is None:
                    parts.append(f"{v}/{sid} none")
                else:
                    rmse = "" if cur.rmse_nt is None else f" {cur.rmse_nt:.0f}nT"
                    parts.append(f"{v}/{sid} {cur.status} {cur.method} {cur.params.model}{rmse}")
        # "summary" first: `magmesh status` shows the start of this entry in its NOTE column
        return {"calibration": {"summary": "; ".join(parts), "vehicles": vehicles}}
