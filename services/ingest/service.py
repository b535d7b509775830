"""Ingest: validate every raw sample; republish accepted ones on clean keys, report the rest on rejects.

Garbage bytes, NaN, wrong versions, absurd values, duplicates and time going backwards are refused with a
reason on ``magmesh/{vehicle}/rejects`` and counted; nothing crashes the service.
"""

from __future__ import annotations

import time

from magmesh.declare import Input, Output
from magmesh.runtime import Service
from schemas import keys, messages

from .batching import BatchingIngest, IngestServiceSettings
from .core import (
    Rejection,
    StreamState,
    VehicleState,
    accept,
    check_order,
    check_ranges,
    note_refusal,
    rebase,
)
from .framing import FramingIngest


class Ingest(FramingIngest, BatchingIngest, Service):
    role = "ingest"
    impl = "ingest"
    Settings = IngestServiceSettings
    RAW_BATCHES = True  # raw/batch (contract v2): validated here on whole columns
    FRAME_INPUT = False
    INPUTS = (Input("magmesh/{vehicle}/raw/**", "every raw stream (mag/{sensor}, imu, gnss, ins, route, attitude) "
                    "and raw/batch, validated here"),)
    OUTPUTS = (
        *(Output(f"magmesh/{{vehicle}}/clean/{s}", f"accepted {s} samples", when=("output", "singles"))
          for s in ("mag/{sensor}", "imu", "gnss", "ins", "route", "attitude")),
        Output("magmesh/{vehicle}/clean/batch", "accepted samples of a vehicle per batch_window_s (contract v2)",
               when=("output", "batches")),
        Output("magmesh/fleet/{shard}/clean", "accepted samples of every vehicle per batch_window_s (contract v3)",
               when=("output", "frames")),
        Output("magmesh/{vehicle}/rejects", "every refused sample, with the field and a sentence"),
    )

    def new_vehicle(self, vehicle: str) -> VehicleState:
        return VehicleState()

    def on_message(self, info, msg: dict, state: VehicleState) -> None:
        # the runtime has decoded the payload against the contract (schema, version, finite values, vehicle id
        # matching the key) and reported anything that failed on rejects; here: physics, time order, duplicates
        if info.rest[0] == keys.BATCH:  # contract v2: many samples, validated on whole columns
            self.on_batch_input(info, msg, state)
            return
        if self.frame_output:  # decided with the whole window (framing.py)
            self.frame_single(info, msg)
            return
        key = info.key
        st = state.streams.get(key)
        if st is None:
            st = state.streams[key] = StreamState()
        now = time.monotonic()
        try:
            check_ranges(msg, self.settings, key)
            check_order(msg, st, self.settings, key, now)
        except Rejection as r:
            if not self.time_refusal(info, msg, st, r):
                if len(st.refused_seqs) < 1024:
                    st.refused_seqs.add(msg["seq"])
                return
        accept(msg, st, now, self.settings)
        self.emit(info, msg)

    def on_start(self) -> None:
        if self.frame_output:  # compile (or load from numba's disk cache) before serving: never on a sample
            from .fleet import warm

            warm()

    def on_tick(self) -> None:
        if self.frame_output:
            self.frame_flush()
            return
        self.flush()

    def on_stop(self) -> None:
        if self.frame_output:
            self.frame_flush(force=True)

    def time_refusal(self, info, msg: dict, st: StreamState, r: Rejection) -> bool:
        """A refused sample: reported (False), or (True) the one that re-bases a clock that really jumped."""
        key = info.key
        if r.code == "time_order" and note_refusal(msg, st, self.settings):
            # the stream kept contradicting its clock with samples that agree with each other: the clock
            # really jumped (a restarted source, a GNSS time step); start it again from this sample
            self.log.warning("%s: clock re-based at t_s = %.6f s after %d consistent samples refused on time",
                             key, msg["t_s"], self.settings.rebase_after)
            rebase(st)
            self._rt.count_rebase("clock")
            return True
        self.reject(key, r.code, r.reason, r.field, len(messages.encode(msg, check=False)), info.vehicle,
                    msg["t_s"], msg["type"])
        return False

    def evict_key(self, key: str) -> None:
        """The runtime freed an idle key: its stream's clock and seq go too."""
        vehicle = key.split("/")[1]
        vs = self.vehicle_states.get(vehicle)
        if vs is not None:
            vs.streams.pop(key, None)
        self.frame_evict_key(key)

    def evict_vehicle(self, vehicle: str, state) -> None:
        self.frame_evict_vehicle(vehicle)

    def status_extra(self) -> dict:
        gaps, seq_rebases, clock_rebases = {}, 0, 0
        per_key = [(k, st.upstream_gaps, st.seq_rebases, st.clock_rebases)
                   for vs in list(self.vehicle_states.values()) for k, st in list((vs.streams if vs else {}).items())]
        for k, g, sr, cr in per_key + self.frame_streams():
            if g:
                gaps[k] = g
            seq_rebases += sr
            clock_rebases += cr
        top = dict(sorted(gaps.items(), key=lambda kv: -kv[1])[:50])  # bounded: the largest 50
        return {"upstream_gaps": top, "upstream_gap_keys": len(gaps), "seq_rebases": seq_rebases,
                "clock_rebases": clock_rebases}
