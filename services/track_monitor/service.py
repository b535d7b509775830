"""Track monitor: cross-track deviation, heading-innovation and combined magnetic-anomaly alarms.

What it consumes and produces is declared on :class:`TrackMonitorService` (``INPUTS``, ``OUTPUTS``; ``--help`` lists
them).

The logic lives in core.py. σ of the innovation is learned on the first undisturbed minute of each vehicle
and kept under ``state_dir()/track_monitor/`` for the next flights (``persist_sigma``). A vehicle's manifest
table may give ``attitude_mag_gain_per_s`` (the magnetometer gain of its attitude filter).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace

from magmesh import declare, paths
from magmesh.declare import Input, Output, setting
from magmesh.runtime import Service
from schemas import keys
from services.physical import refuse_unphysical

from .core import AlarmEvent, TrackMonitor, TrackMonitorSettings, mag_heading


@dataclass(frozen=True)
class Settings(TrackMonitorSettings):
    tick_s: float = setting(2.0, "persistence of learned σ runs from this tick", gt=0)
    persist_sigma: bool = setting(True, "save learned σ per vehicle and reuse it on the next start")
    state_subdir: str = setting("track_monitor", "directory of the saved σ and routes under state_dir()")
    mag_sensor: str = setting("1", "magnetometer whose field strength holds the combined verdict (\"\" to ignore)")
    mag_source: str = setting("clean", "clean: clean/mag/{sensor}; cal: cal/mag/{sensor} (calibration service output)",
                              choices=("clean", "cal"))
    mag_match_s: float = setting(0.05, "an attitude sample without a magnetometer heading takes it from a field sample "
                                 "at most this far in time (levelled with the attitude's roll/pitch, + the vehicle's "
                                 "declination_rad)")


class TrackMonitorService(Service):
    role = "track_monitor"
    impl = "track_monitor"
    Settings = Settings
    INPUTS = (
        Input("magmesh/{vehicle}/clean/route", "the planned line A → B"),
        Input("magmesh/{vehicle}/clean/gnss", "RTK position (pos_enu_m), velocity and fix quality"),
        Input("magmesh/{vehicle}/clean/attitude", "the vehicle's own heading and the magnetometer heading it fuses"),
        Input("magmesh/{vehicle}/clean/mag/{sensor}", "field strength: the combined verdict is held while |B| is off",
              sensors="mag_sensor", when=("mag_source", "clean")),
        Input("magmesh/{vehicle}/cal/mag/{sensor}", "the same from the calibration service's output",
              sensors="mag_sensor", when=("mag_source", "cal")),
    )
    OUTPUTS = (
        Output("magmesh/{vehicle}/track", "d, along-track progress, detector states (per GNSS epoch)"),
        declare.alarm("track", "d > track_threshold_m on trusted GNSS for track_persist_s; cleared below track_clear_m "
                      "for clear_hold_s"),
        declare.alarm("heading_innovation", "|ψ_mag − ψ_att| test (paper kσ, or robust median + CUSUM); cleared "
                      "within innovation_clear_sigma for clear_hold_s"),
        declare.alarm("mag_anomaly", "the combined verdict, naming the detector that fired; cleared after "
                      "anomaly_clear_hold_s of quiet"),
    )
    # a restored raised alarm is each detector's own latch again (new_vehicle): it clears on the detector's clear
    # condition held for its hold time, never because a restart has not seen the condition yet
    ADOPTS_RESTORED_ALARMS = True

    # ---- per-vehicle state --------------------------------------------------------------------
    def _sigma_path(self, vehicle: str):
        return paths.state_dir() / self.settings.state_subdir / f"{vehicle}.json"

    def _route_path(self, vehicle: str):
        return paths.state_dir() / self.settings.state_subdir / f"{vehicle}.route.{self.instance}.json"

    def new_vehicle(self, vehicle: str) -> TrackMonitor:
        s = self.settings
        gain = (self.vehicles_config.get(vehicle) or {}).get("attitude_mag_gain_per_s")
        if gain is not None:
            s = replace(s, fc_mag_gain_per_s=float(gain))
        mon = TrackMonitor(s)
        mon.saved_sigma = False
        mon.last_mag = None
        for source, latch in (("track", mon.track.state), ("heading_innovation", mon.innovation.state),
                              ("mag_anomaly", mon.anomaly)):
            if self.holds_alarm(vehicle, source):  # after a restart: the latch as the mesh knows it
                latch.adopt(True, self.held_alarm_raised_t_s(vehicle, source))
                if source == "mag_anomaly":
                    mon.anomaly_source = "an earlier run"
        if getattr(self._rt, "resumed_from", None) is not None:
            # restarted after a crash: the route in force before it (published once per leg, not again)
            try:
                r = json.loads(self._route_path(vehicle).read_text())
                mon.set_route(r["a_enu_m"], r["b_enu_m"], r["route_id"])
                self.log.info("%s: route %s restored from before the restart", vehicle, r["route_id"])
            except FileNotFoundError:
                pass
            except (ValueError, KeyError, TypeError) as e:
                self.log.warning("%s: ignoring unreadable saved route (%s)", vehicle, e)
        if s.persist_sigma and mon.innovation.learning:
            path = self._sigma_path(vehicle)
            try:
                saved = json.loads(path.read_text())
                if saved.get("innovation_test") == s.innovation_test:
                    mon.innovation.apply_sigmas(saved)
                    mon.saved_sigma = True
                    if mon.field.learning and saved.get("field_ref_nt") and saved.get("field_sigma_nt"):
                        mon.field.apply(saved["field_ref_nt"], saved["field_sigma_nt"])
                    self.log.info("%s: innovation σ %.3f° loaded from %s", vehicle,
                                  math.degrees(saved["innovation_sigma_rad"]), path)
            except FileNotFoundError:
                pass
            except (ValueError, KeyError, TypeError) as e:
                self.log.warning("%s: ignoring unreadable %s (%s); learning σ again", vehicle, path, e)
        return mon

    # ---- inputs -------------------------------------------------------------------------------
    def on_message(self, info, msg: dict, mon: TrackMonitor) -> None:
        if refuse_unphysical(self, info, msg):
            return
        stream = info.stream
        if stream == "route":
            mon.set_route(msg["a_enu_m"], msg["b_enu_m"], msg["route_id"])
            self.log.info("%s: route %s %s → %s", info.vehicle, msg["route_id"], msg["a_enu_m"], msg["b_enu_m"])
            try:  # for a restart after a crash (the route is published once per leg)
                path = self._route_path(info.vehicle)
                path.parent.mkdir(parents=True, exist_ok=True)
                paths.write_atomic(path, json.dumps({k: msg[k] for k in ("a_enu_m", "b_enu_m", "route_id")}))
            except OSError as e:
                self.log.warning("%s: could not save the route for a restart: %s", info.vehicle, e)
        elif stream == "gnss":
            if "pos_enu_m" not in msg:
                self.count_drop(info.key, "no pos_enu_m")
                return
            events = mon.update_gnss(msg["t_s"], msg["pos_enu_m"], msg["vel_enu_m_s"], msg["fix_type"],
                                     msg["num_sats"], msg["pdop"], msg.get("horiz_std_m"))
            self._emit(info.vehicle, events)
            if mon.route is None:
                self.count_drop(info.key, "no route yet")
            else:
                self._publish_track(info.vehicle, msg["t_s"], mon)
        elif stream == "mag":
            mon.last_mag = (msg["t_s"], msg["b_nt"])
            self._emit(info.vehicle, mon.update_mag(msg["t_s"], msg["b_nt"]))
        elif stream == "attitude":
            was_learning = mon.innovation.learning
            psi_m = msg["mag_heading_rad"]
            if psi_m is None and mon.last_mag is not None and abs(mon.last_mag[0] - msg["t_s"]) <= self.settings.mag_match_s:
                decl = float((self.vehicles_config.get(info.vehicle) or {}).get("declination_rad", 0.0))
                psi_m = mag_heading(mon.last_mag[1], msg["roll_rad"], msg["pitch_rad"], decl)
            if psi_m is None:
                self.count_drop(info.key, "no magnetometer heading")
            self._emit(info.vehicle, mon.update_attitude(msg["t_s"], msg["heading_rad"], psi_m))
            if was_learning and not mon.innovation.learning:
                self.log.info("%s: innovation σ learned: %.3f° (median %.3f°, block %.3f°)", info.vehicle,
                              math.degrees(mon.innovation.sigma_rad), math.degrees(mon.innovation.median_sigma_rad),
                              math.degrees(mon.innovation.block_sigma_rad))
        else:
            self.count_drop(info.key, "unexpected stream")

    def _emit(self, vehicle: str, events: list[AlarmEvent]) -> None:
        for ev in events:
            extra = {} if ev.raised_t_s is None else {"raised_t_s": ev.raised_t_s}
            self.alarm(vehicle, ev.source, ev.state, ev.severity, ev.reason, ev.value, ev.threshold, ev.t_s,
                       unit=ev.unit, **extra)

    def _publish_track(self, vehicle: str, t_s: float, mon: TrackMonitor) -> None:
        st, fl = mon.internal_states, mon.flags
        if st["cross_track_m"] is None:
            return
        fields = dict(
            cross_track_m=st["cross_track_m"], along_track_m=st["along_track_m"],
            progress_frac=st["progress_frac"], gnss_ok=fl["gnss_ok"],
            heading_innovation_rad=st["heading_innovation_rad"], innovation_sigma_rad=st["innovation_sigma_rad"],
            track_alarm=fl["track_alarm"], innovation_alarm=fl["innovation_alarm"],
            anomaly_alarm=fl["anomaly_alarm"], anomaly_source=mon.anomaly_source,
            cross_track_rate_m_s=st["cross_track_rate_m_s"], track_armed=fl["track_armed"],
            innovation_learning=fl["learning"], innovation_test_ratio=st["innovation_test_ratio"],
            route_id=mon.route.route_id,
        )
        if st["field_deviation_nt"] is not None:
            fields["field_deviation_nt"] = st["field_deviation_nt"]
        if mon.track.cross_track_signed_m is not None:
            fields["cross_track_signed_m"] = mon.track.cross_track_signed_m
        self.publish(keys.track(vehicle), "track", vehicle, t_s, **fields)

    # ---- periodic work and status -------------------------------------------------------------
    def on_tick(self) -> None:
        if self.settings.persist_sigma:
            for vehicle, mon in list(self.vehicle_states.items()):
                self._save_sigma(vehicle, mon)

    def on_stop(self) -> None:
        self.on_tick()

    def _save_sigma(self, vehicle: str, mon: TrackMonitor) -> None:
        inn = mon.innovation
        if mon is None or inn.learning or getattr(mon, "saved_sigma", True):
            return
        if self.settings.mag_sensor and mon.field.learning and mon.n_mag > 0:
            return  # wait for the field reference too, then save both
        path = self._sigma_path(vehicle)
        path.parent.mkdir(parents=True, exist_ok=True)
        paths.write_atomic(path, json.dumps({"innovation_test": self.settings.innovation_test,
                                             "innovation_sigma_rad": inn.sigma_rad,
                                             "median_sigma_rad": inn.median_sigma_rad,
                                             "block_sigma_rad": inn.block_sigma_rad, "field_ref_nt": mon.field.ref_nt,
                                             "field_sigma_nt": mon.field.sigma_nt}))
        mon.saved_sigma = True
        self.log.info("%s: innovation σ saved to %s", vehicle, path)

    def status_extra(self) -> dict:
        out = {}
        for vehicle, mon in list(self.vehicle_states.items()):
            if mon is None:
                continue
            st = mon.internal_states
            out[vehicle] = {
                "flags": mon.flags,
                "route_id": mon.route.route_id if mon.route else None,
                "cross_track_m": st["cross_track_m"],
                "innovation_sigma_deg": None if st["innovation_sigma_rad"] is None
                else math.degrees(st["innovation_sigma_rad"]),
                "anomaly_source": mon.anomaly_source,
                "gnss_untrusted": mon.n_gnss_untrusted,
                "bursts": st["bursts"],
                "field_ref_nt": st["field_ref_nt"],
                "field_deviation_nt": st["field_deviation_nt"],
            }
        return {"vehicles": out}
