"""Ingest: validate every raw sample; republish accepted ones on clean keys, report the rest on rejects.

Garbage bytes, NaN, wrong versions, absurd values, duplicates and time going backwards are refused with a
reason on ``magmesh/{vehicle}/rejects`` and counted; nothing crashes the service.
"""

from __future__ import annotations

from magmesh.runtime import Service
from schemas import keys, messages

from .core import IngestSettings, Rejection, StreamState, VehicleState, accept, check_order, check_ranges


class Ingest(Service):
    role = "ingest"
    impl = "ingest"
    Settings = IngestSettings
    CONSUMES = ("raw/mag/{sensor}", "raw/imu", "raw/gnss", "raw/ins", "raw/route", "raw/attitude")
    PRODUCES = ("clean/mag/{sensor}", "clean/imu", "clean/gnss", "clean/ins", "clean/route", "clean/attitude",
                "rejects")

    def subscriptions(self) -> list[str]:
        return [keys.raw_all(self.vehicle_pattern)]

    def new_vehicle(self, vehicle: str) -> VehicleState:
        return VehicleState()

    def on_message(self, info, msg: dict, state: VehicleState) -> None:
        # the runtime has decoded the payload against the contract (schema, version, finite values, vehicle id
        # matching the key) and reported anything that failed on rejects; here: physics, time order, duplicates
        key = info.key
        st = state.streams.get(key)
        if st is None:
            st = state.streams[key] = StreamState()
        try:
            check_ranges(msg, self.settings, key)
            check_order(msg, st, self.settings, key)
        except Rejection as r:
            self.reject(key, r.code, r.reason, r.field, len(messages.encode(msg, check=False)), info.vehicle,
                        msg["t_s"], msg["type"])
            return
        accept(msg, st)
        self.republish(keys.raw_to_clean(key), msg)

    def status_extra(self) -> dict:
        gaps = {k: st.upstream_gaps for vs in list(self.vehicle_states.values()) if vs
                for k, st in list(vs.streams.items()) if st.upstream_gaps}
        return {"upstream_gaps": gaps}
