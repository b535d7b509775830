"""Physical plausibility of a decoded input, for services that consume ``clean/`` and ``cal/`` keys.

Ingest refuses samples outside physical ranges before they reach ``clean/``; a service still meets such a
sample when something publishes on those keys directly (a misconfigured tool, a replay, a fault). A value
such as |b| = 1e300 nT passes the message contract (a finite number) but overflows a filter and poisons its
state, so each service refuses it at the door with the same ranges and reasons as ingest (a reject on
``magmesh/{vehicle}/rejects``, code ``range``) instead of failing inside its logic.
"""

from __future__ import annotations

import math
from typing import Any

from services.ingest.core import IngestSettings, Rejection, check_ranges

_DEFAULT = IngestSettings()
#: |entry| bound of a soft-iron matrix M (h = M (m − offset)); real ones are within a few tenths of identity
MAX_MATRIX_ENTRY = 100.0
#: |det M| below this: M is singular, the compensated field would collapse or explode
MIN_MATRIX_DET = 1e-6
#: a route leg shorter than this (horizontally) has no direction to measure a cross-track distance from
MIN_ROUTE_LENGTH_M = 0.01


def _det3(m: list[float]) -> float:
    return (m[0] * (m[4] * m[8] - m[5] * m[7]) - m[1] * (m[3] * m[8] - m[5] * m[6])
            + m[2] * (m[3] * m[7] - m[4] * m[6]))


def check_params(msg: dict, s: IngestSettings, where: str) -> None:
    """Raise :class:`Rejection` when calibration parameters cannot describe a magnetometer."""
    def bad(fld: str, what: str) -> Rejection:
        return Rejection("range", fld, f"field '{fld}' of {where} {what}")

    if not 0 < msg["field_radius_nt"] <= s.max_field_nt:
        raise bad("field_radius_nt", f"is {msg['field_radius_nt']:.4g} nT, outside (0, {s.max_field_nt:.4g}] nT")
    if math.sqrt(sum(x * x for x in msg["offset_nt"])) > s.max_field_nt:
        raise bad("offset_nt", f"is beyond the {s.max_field_nt:.4g} nT a magnetometer can read")
    m = msg["matrix"]
    if max(abs(x) for x in m) > MAX_MATRIX_ENTRY:
        raise bad("matrix", f"has an entry beyond ±{MAX_MATRIX_ENTRY:g}")
    if abs(_det3(m)) < MIN_MATRIX_DET:
        raise bad("matrix", f"is singular (|det| = {abs(_det3(m)):.3g})")


def check_route(msg: dict, where: str) -> None:
    """Raise :class:`Rejection` when a route leg has no length."""
    a, b = msg["a_enu_m"], msg["b_enu_m"]
    d = math.hypot(b[0] - a[0], b[1] - a[1])
    if not d >= MIN_ROUTE_LENGTH_M:
        raise Rejection("range", "b_enu_m", f"field 'b_enu_m' of {where} is {d:.3g} m from a_enu_m horizontally: "
                        f"a route leg needs two points at least {MIN_ROUTE_LENGTH_M:g} m apart")


def problem(msg: dict, key: str, settings: IngestSettings = _DEFAULT) -> Rejection | None:
    """The reason ``msg`` (decoded, valid under the contract) is not physical, or None."""
    try:
        check_ranges(msg, settings, key)  # ingest's ranges and reasons
        if msg["type"] == "cal_params":
            check_params(msg, settings, key)
        elif msg["type"] == "route":
            check_route(msg, key)
    except Rejection as r:
        return r
    return None


def refuse_unphysical(svc: Any, info: Any, msg: dict) -> bool:
    """Report a non-physical input on rejects through ``svc.reject`` and return True; else False."""
    r = problem(msg, info.key)
    if r is None:
        return False
    svc.reject(info.key, r.code, r.reason, r.field, 0, info.vehicle, msg["t_s"], msg["type"])
    return True
