"""Render the contract table (``schemas/README.md``) from :mod:`schemas.messages`.

``python -m schemas.doc > schemas/README.md``; a test checks the file is up to date.
"""

from __future__ import annotations

from .messages import HEADER, MESSAGES

INTRO = """# The magmesh wire contract

Generated from `schemas/messages.py` by `python -m schemas.doc`; do not edit by hand.

Every message is a **msgpack map**. Keys are built and parsed only by `schemas/keys.py`.
A subscriber outside this repository needs nothing but this page and a msgpack decoder.

- **Frames.** Navigation frame ENU (x east, y north, z up), local to the vehicle's origin; body frame FLU
  (x forward, y left, z up). `heading_rad` is clockwise from true north in [0, 2π); pitch is positive nose
  up, roll positive right side down. Quaternions are [w, x, y, z], body → ENU.
- **Units** are in every field name: `_nt` nanotesla, `_s` seconds, `_rad` radians, `_rad_s` rad/s,
  `_m` metres, `_m_s` m/s, `_m_s2` m/s², `_deg` degrees (geodetic only), `_frac` 0..1, `_ms` milliseconds.
- **Versions.** Each type has a version; a decoder refuses versions it does not know with a typed error.
  Unknown extra fields are ignored (forward compatible); a change that removes or re-means a field bumps the
  version.
- **Sequence numbers.** `seq` increases by exactly one per message on a key from one publishing instance. A
  gap means loss upstream; a restart of a publisher starts a new sequence, but a live swap of a role continues it.
- **Reliability.** Every magmesh publisher is reliable with blocking congestion control: a slow consumer slows
  the producer instead of losing data. Services answer queries on `magmesh/{vehicle}/alarm/**` with the alarms
  they currently hold raised, so a late joiner learns the current state at once.

## Keys

| key | message | published by | meaning |
|---|---|---|---|
| `magmesh/{vehicle}/raw/mag/{sensor}` | mag | vehicles, simulators, replays | magnetometer samples as measured |
| `magmesh/{vehicle}/raw/imu` | imu | vehicles | gyro + accelerometer |
| `magmesh/{vehicle}/raw/gnss` | gnss | vehicles | GNSS fixes |
| `magmesh/{vehicle}/raw/ins` | ins | survey vehicles | dead-reckoned INS navigation |
| `magmesh/{vehicle}/raw/route` | route | mission planners | the planned line A → B |
| `magmesh/{vehicle}/raw/attitude` | attitude | flight controllers | the vehicle's own attitude estimate |
| `magmesh/{vehicle}/clean/...` | same as raw | ingest | raw samples that passed validation |
| `magmesh/{vehicle}/rejects` | reject | any service | every refused input, with the reason |
| `magmesh/{vehicle}/cal/mag/{sensor}` | mag | calibration | compensated field (`calibrated` true, `param_id`) |
| `magmesh/{vehicle}/cal/params/{sensor}` | cal_params | calibration | current parameters; also answered by query |
| `magmesh/{vehicle}/dmc` | dmc | dmc_detector | interference features and validity per epoch |
| `magmesh/{vehicle}/heading` | heading | heading_fuser | fused attitude and heading |
| `magmesh/{vehicle}/fix/geomag` | geomag_fix | geomag_matcher | geomagnetic matching result |
| `magmesh/{vehicle}/track` | track | track_monitor | cross-track monitoring state |
| `magmesh/{vehicle}/alarm/{source}` | alarm | services | alarm transitions (raised / cleared) |
| `magmesh/{vehicle}/truth/{what}` | truth | simulators, replays | ground truth |
| `magmesh/svc/{role}/{instance}` | (liveliness token) | every service | present while the instance runs |
| `magmesh/svc/{role}/{instance}/status` | status (queryable) | every service | counts, rates, drops, settings, mode |
| `magmesh/svc/{role}/{instance}/control` | (queryable) | every service | hand-over control used by `magmesh swap` |

Alarm sources in use: `dmc` (dmc_detector), `heading` (heading_fuser), `match` (geomag_matcher), `track`,
`heading_innovation`, `mag_anomaly` (track_monitor).

## Header (every message)

| field | type | meaning |
|---|---|---|
"""


def _kind(f) -> str:
    k = f.kind
    if k == "floats" and f.length:
        k = f"float[{f.length}]"
    elif k == "bools" and f.length:
        k = f"bool[{f.length}]"
    elif k == "vec3":
        k = "float[3]"
    if f.choices:
        k += " ∈ {" + ", ".join(f.choices) + "}"
    if f.nullable:
        k += " or nil"
    return k


def render() -> str:
    out = [INTRO]
    for f in HEADER:
        out.append(f"| `{f.name}` | {_kind(f)} | {f.doc} |\n")
    out.append("\n## Message types\n")
    for mt in MESSAGES.values():
        out.append(f"\n### `{mt.name}` (version {mt.version})\n\n{mt.doc}. Keys: "
                   + ", ".join(f"`{k}`" for k in mt.keys) + "\n\n| field | type | required | meaning |\n|---|---|---|---|\n")
        for f in mt.fields:
            rng = ""
            if f.lo is not None or f.hi is not None:
                rng = f" (range {'' if f.lo is None else f'{f.lo:g}'}..{'' if f.hi is None else f'{f.hi:g}'})"
            out.append(f"| `{f.name}` | {_kind(f)} | {'yes' if f.required else 'no'} | {f.doc}{rng} |\n")
    out.append("""
## Status replies

`magmesh/svc/{role}/{instance}/status` answers a msgpack map: `role`, `impl`, `instance`, `pid`, `host`,
`magmesh_version`, `uptime_s`, `vehicle_pattern`, `vehicles`, `consumes`, `produces`, `in` and `out`
(`{key: {n, rate_hz}}`), `rejects`, `drops` (`{key: {reason: n}}`), `drops_total`, `queue_depth`,
`last_error`, `settings`, `alarms_raised`, `mode` (active, standby, retiring, retired), `holds_role`,
`suppressed`, plus service-specific entries.
""")
    return "".join(out)


if __name__ == "__main__":
    print(render(), end="")
