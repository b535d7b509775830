"""Geomagnetic matcher: match the last N total-field samples against an anomaly map and publish fix/geomag.

Consumes the scalar field (`f_nt` of clean/mag/{sensor}) and the INS navigation (clean/ins) of each
vehicle; every `match_every_samples` new samples it runs the paper's pipeline (one-cell pre-match
with SSDA early abandon at λ, bilinear fine match, Hausdorff score), classifies the match with the
M-of-N rule and publishes the outcome on fix/geomag — a rejected or ambiguous match is published as
such, never as an accepted fix. It raises alarm/match while the INS and the accepted fixes disagree
by more than `divergence_alarm_m`.

Per vehicle, the manifest's vehicle table may give `map` (a map spec: file under data/ or
`synthetic[:seed]`), `lat_deg`, `lon_deg`, `alt_m` (where the map lies, for the IGRF core field
subtracted from the total field) and a `geomag` table overriding any of the settings below for that
vehicle (λ, search radius, agreement radius... suit the map's cell size and field strength).
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from magmesh import declare
from magmesh.align import CoverWait
from magmesh.declare import Input, Output, setting
from magmesh.geomap import GridMap, core_field_enu_nt, load_map
from magmesh.latch import AlarmLatch
from magmesh.runtime import Service, build_settings
from schemas import keys
from services.physical import refuse_unphysical

from .core import AcceptSettings, FilterSettings, GeomagMatcher, MatcherSettings, MatchSettings


@dataclass(frozen=True)
class Settings:
    map: str = setting("synthetic:7", "default map spec: a file under data/ or synthetic[:seed] (a vehicle table's "
                       "`map` overrides it)")
    n_samples: int = setting(20, "match length N", lo=2)
    window_samples: int = setting(0, "Hausdorff pairing window along the strip; -1: the paper's unordered set")
    rank_frac: float = setting(1.0, "partial Hausdorff rank (1: classic)", gt=0, hi=1)
    lambda_nt: float = setting(8.4, "SSDA / feasibility threshold λ", gt=0)
    subdivisions: int = setting(3, "fine-match subdivisions per cell (the paper: 2–4)", lo=1, hi=16)
    prematch_score: str = setting("centre", "one-cell pre-match score at the cell centre or its corners (paper §3.1 a "
                                  "/ b)", choices=("centre", "corners"))
    search_radius_m: float = setting(3000.0, "half-width of the search square around the (corrected) INS start; 0: "
                                     "whole map")
    runner_up_exclusion_m: float = setting(200.0, "the runner-up must start farther than this from the match")
    demean: bool = setting(False, "match mean-removed sequences (unknown constant bias; slower: no SSDA pruning)")
    heading_search_deg: float = setting(0.0, "also try the INS track rotated by up to ± this (INS heading error)")
    heading_step_deg: float = setting(1.0, "rotation step of that search")
    match_every_samples: int = setting(5, "match each time this many new samples arrived")
    m_agree: int = setting(2, "M of the M-of-N rule: fixes that must agree (the current one included)", lo=1)
    n_window: int = setting(3, "N of the M-of-N rule: last fixes considered (≥ m_agree)", lo=1)
    agree_radius_m: float = setting(250.0, "fixes agree when their INS corrections differ by less", gt=0)
    min_margin_nt: float = setting(0.3, "runner-up margin below this: ambiguous, never a fix")
    max_hausdorff_nt: float = setting(30.0, "best distance above this: rejected")
    divergence_alarm_m: float = setting(1000.0, "raise alarm/match when |accepted fix − INS| exceeds this (cleared "
                                        "below 0.8 × this)")
    fix_std_m: float = setting(50.0, "INS-error filter: 1-σ of an accepted fix per axis", gt=0)
    gate_sigma: float = setting(5.0, "INS-error filter: innovation gate", gt=0)
    lat_deg: float = setting(45.4, "default reference place of the map (IGRF core field): latitude")
    lon_deg: float = setting(-75.7, "default reference place of the map: longitude")
    alt_m: float = setting(300.0, "default reference place of the map: altitude")
    ins_buffer: int = setting(200, "INS samples kept for time interpolation (and field samples waiting for the INS)")
    ins_max_wait_s: float = setting(10.0, "wall-clock seconds a field sample waits for the INS to reach its time")
    max_ins_gap_s: float = setting(30.0, "a field sample farther than this from any INS sample is dropped")
    restart_jump_s: float = setting(60.0, "INS time going back more than this: a new run, the vehicle's matcher "
                                    "restarts")

    def __post_init__(self) -> None:
        declare.check(self)


#: alarm/match clears when an accepted fix is within this fraction of divergence_alarm_m of the INS
CLEAR_FRAC = 0.8


class VehicleMatch:
    """Per-vehicle state: the matcher, recent INS samples, field samples waiting for INS."""

    def __init__(self, buffer: int, max_wait_s: float = 10.0):
        self.matcher: GeomagMatcher | None = None  # built on the first scalar field sample
        self.ins_t: deque = deque(maxlen=buffer)
        self.ins_p: deque = deque(maxlen=buffer)
        # field samples (t_s, f_nt) wait until the INS reaches their time (magmesh/align.py)
        self.wait = CoverWait(max_wait_s=max_wait_s, max_pending=buffer, stream="field")
        # alarm/match: raised at once when an accepted fix is beyond divergence_alarm_m of the INS, cleared at once
        # when one is within 0.8 × that (in between it stays as it is)
        self.alarm = AlarmLatch(0.0, 0.0)
        self.unusable = False  # its map or settings failed to load: its samples are counted as drops

    def reset(self) -> None:
        self.ins_t.clear()
        self.ins_p.clear()
        self.wait.reset()
        if self.matcher is not None:
            self.matcher.reset()

    def ins_at(self, t_s: float, max_gap_s: float) -> np.ndarray | None:
        """INS position at t_s by linear interpolation (None if t_s is not covered)."""
        ts = list(self.ins_t)
        if not ts or t_s > ts[-1] + 1e-9 or t_s < ts[0] - max_gap_s:
            return None
        k = bisect.bisect_left(ts, t_s)
        if k < len(ts) and abs(ts[k] - t_s) < 1e-9:
            return self.ins_p[k]
        if k == 0:
            return self.ins_p[0] if ts[0] - t_s <= max_gap_s else None
        t0, t1 = ts[k - 1], ts[k]
        if t1 - t0 > max_gap_s:
            return None
        w = (t_s - t0) / (t1 - t0)
        return (1 - w) * self.ins_p[k - 1] + w * self.ins_p[k]


class GeomagMatcherService(Service):
    role = "geomag_matcher"
    impl = "hausdorff_ssda"
    Settings = Settings
    INPUTS = (
        Input("magmesh/{vehicle}/clean/mag/{sensor}", "the scalar total field (f_nt) to match", sensors="*"),
        Input("magmesh/{vehicle}/clean/ins", "the INS navigation the field samples are placed on"),
    )
    OUTPUTS = (
        Output("magmesh/{vehicle}/fix/geomag", "every match's outcome: accepted, rejected or ambiguous"),
        declare.alarm("match", "raised while an accepted fix is more than divergence_alarm_m from the INS, cleared "
                      "below 0.8 × that"),
    )
    ADOPTS_RESTORED_ALARMS = True  # a restored raised match alarm stays until a fix shows the divergence gone

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self._maps: dict[str, GridMap] = {}

    def _map(self, spec: str) -> GridMap:
        if spec not in self._maps:
            self._maps[spec] = load_map(spec)
            self.log.info("loaded map %s: %s cells of %.0f m, std %.2f nT", spec, self._maps[spec].shape,
                          self._maps[spec].dx_m, self._maps[spec].std_nt)
        return self._maps[spec]

    def vehicle_settings(self, vcfg: dict) -> Settings:
        """The service settings with the vehicle table's ``geomag`` overrides (e.g. λ for its map)."""
        over = dict(vcfg.get("geomag", {}) or {})
        return build_settings(Settings, {**dataclasses.asdict(self.settings), **over})

    def matcher_settings(self, vcfg: dict) -> MatcherSettings:
        s = self.vehicle_settings(vcfg)
        core = core_field_enu_nt(vcfg.get("lat_deg", s.lat_deg), vcfg.get("lon_deg", s.lon_deg),
                                 vcfg.get("alt_m", s.alt_m))
        return MatcherSettings(
            match=MatchSettings(
                n_samples=s.n_samples, window_samples=None if s.window_samples < 0 else s.window_samples,
                rank_frac=s.rank_frac, lambda_nt=s.lambda_nt, subdivisions=s.subdivisions,
                prematch_score=s.prematch_score, search_radius_m=s.search_radius_m,
                heading_search_deg=s.heading_search_deg, heading_step_deg=s.heading_step_deg,
                runner_up_exclusion_m=s.runner_up_exclusion_m, demean=s.demean),
            accept=AcceptSettings(m_agree=s.m_agree, n_window=s.n_window, agree_radius_m=s.agree_radius_m,
                                  min_margin_nt=s.min_margin_nt, max_hausdorff_nt=s.max_hausdorff_nt),
            filter=FilterSettings(fix_std_m=s.fix_std_m, gate_sigma=s.gate_sigma),
            match_every_samples=s.match_every_samples,
            divergence_alarm_m=s.divergence_alarm_m,
            main_field_nt=float(vcfg.get("main_field_nt", np.linalg.norm(core))),
        )

    def new_vehicle(self, vehicle: str) -> VehicleMatch:
        st = VehicleMatch(self.settings.ins_buffer, self.settings.ins_max_wait_s)
        st.alarm.adopt(self.holds_alarm(vehicle, "match"))  # after a restart: the latch as the mesh knows it
        return st

    def _build_matcher(self, vehicle: str) -> GeomagMatcher | None:
        vcfg = self.vehicles_config.get(vehicle, {}) or {}
        try:
            grid = self._map(str(vcfg.get("map", self.settings.map)))
            ms = self.matcher_settings(vcfg)
        except (OSError, ValueError, TypeError, KeyError) as e:
            self.log.error("vehicle %s: cannot match (map or settings): %s", vehicle, e)
            return None
        self.log.info("vehicle %s: map %s, core field %.1f nT subtracted, λ %.2f nT, search ±%.0f m", vehicle,
                      grid.name, ms.main_field_nt, ms.match.lambda_nt, ms.match.search_radius_m)
        return GeomagMatcher(grid, ms)

    def on_message(self, info, msg, state: VehicleMatch) -> None:
        if refuse_unphysical(self, info, msg):
            return
        if info.kind == "clean" and info.stream == "ins":
            t = msg["t_s"]
            if state.ins_t and t < state.ins_t[-1] - self.settings.restart_jump_s:
                # the vehicle's clock went far back: a new run (e.g. a restarted source); start over
                self.log.warning("%s: INS time went back from %.1f s to %.1f s: matcher reset",
                                 info.vehicle, state.ins_t[-1], t)
                state.reset()
            elif state.ins_t and t <= state.ins_t[-1]:
                self.count_drop(info.key, "ins_out_of_order")
                return
            state.ins_t.append(t)
            state.ins_p.append(np.asarray(msg["pos_enu_m"][:2], float))
            released, gave = state.wait.advance(t)
        elif info.kind == "clean" and info.stream == "mag":
            if "f_nt" not in msg:
                self.count_drop(info.key, "no_scalar_field")  # a vector-only vehicle: nothing to match
                return
            if state.matcher is None and not state.unusable:
                state.matcher = self._build_matcher(info.vehicle)
                state.unusable = state.matcher is None
            if state.unusable:
                self.count_drop(info.key, "vehicle_map_or_settings_unusable")
                return
            released, gave = state.wait.push(msg["t_s"], msg["f_nt"])
        else:
            self.count_drop(info.key, "unexpected_key")
            return
        for g in gave:  # the oldest waiting sample went (overflow), or the INS stayed behind too long (expired)
            self.count_drop(info.key, f"waiting_for_ins_{g.reason}")
        if state.matcher is not None:
            self._drain(info, state, released)

    def _drain(self, info, state: VehicleMatch, released: list) -> None:
        for t, f in released:
            p = state.ins_at(t, self.settings.max_ins_gap_s)
            if p is None:
                self.count_drop(keys.clean_ins(info.vehicle), "no_ins_at_field_time")
                continue
            fix = state.matcher.update(t, f, p)
            if fix is not None:
                self._publish_fix(info.vehicle, fix, state)

    def _publish_fix(self, vehicle: str, fix, state: VehicleMatch) -> None:
        r = fix.result
        ms = state.matcher.settings
        ins3 = [float(fix.ins_end_m[0]), float(fix.ins_end_m[1]), 0.0]
        pos3 = [float(r.end_m[0]), float(r.end_m[1]), 0.0] if r.found else ins3
        fields = dict(
            status=fix.status, accepted=fix.accepted, pos_enu_m=pos3, ins_pos_enu_m=ins3,
            hausdorff_nt=float(r.hausdorff_nt) if r.found else 0.0,
            margin_nt=None if r.margin_nt is None else float(r.margin_nt),
            search_area_m2=float(r.search_area_m2), n_samples=int(ms.match.n_samples),
            lambda_nt=float(r.lambda_nt), feasible_cells=int(r.n_feasible),
            match_ms=float(state.matcher.last_match_ms),
        )
        if r.found:
            fields["correction_enu_m"] = [pos3[0] - ins3[0], pos3[1] - ins3[1], 0.0]
        if fix.filtered_correction_m is not None:
            fields["filtered_correction_enu_m"] = [float(fix.filtered_correction_m[0]),
                                                   float(fix.filtered_correction_m[1]), 0.0]
        if fix.accepted:
            fields["innovation_test_ratio"] = fix.test_ratio
        self.publish(keys.fix_geomag(vehicle), "geomag_fix", vehicle, fix.t_s, **fields)
        if fix.status != "accepted":
            self.log.debug("%s: match %s (d_H %.2f nT, margin %s)", vehicle, fix.status, r.hausdorff_nt, r.margin_nt)
            return
        thr = ms.divergence_alarm_m
        change = state.alarm.update(fix.t_s, fix.divergence_m < CLEAR_FRAC * thr, fix.divergence_m > thr)
        if change == "raised":
            self.alarm(vehicle, "match", "raised", "warning",
                       f"INS position is {fix.divergence_m:.0f} m from the accepted geomagnetic fix "
                       f"(limit {thr:.0f} m)", fix.divergence_m, thr, fix.t_s, unit="m")
        elif change == "cleared":
            self.alarm(vehicle, "match", "cleared", "warning",
                       f"INS position within {fix.divergence_m:.0f} m of the accepted geomagnetic fix",
                       fix.divergence_m, thr, fix.t_s, unit="m")

    def status_extra(self) -> dict:
        out = {}
        for v, st in self.vehicle_states.items():
            if st.matcher is None:
                continue
            s = st.matcher.internal_states
            out[v] = {**{k: (None if isinstance(x, float) and not math.isfinite(x) else x) for k, x in s.items()},
                      **st.matcher.flags, "alarm": st.alarm.raised}
        return {"matchers": out}
