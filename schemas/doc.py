"""Render the contract table (``schemas/README.md``) from :mod:`schemas.streams` and :mod:`schemas.messages`.

``python -m schemas.doc > schemas/README.md``; a test checks the file is up to date.
"""

from __future__ import annotations

from . import batch, frame, streams
from .messages import HEADER, MESSAGES

INTRO = """# The magmesh wire contract

Generated from the streams table `schemas/streams.py` (keys, encodings, ranges) and `schemas/messages.py`
(fields) by `python -m schemas.doc`; do not edit by hand.

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
- **Encodings.** Every put carries a Zenoh encoding naming the message type and its version:
  `application/msgpack;magmesh/{type}/v{version}` (e.g. `application/msgpack;magmesh/mag/v1`; batches
  `application/msgpack;magmesh/batch/v2`; fleet frames `application/msgpack;magmesh/frame/v3`; status replies
  `application/msgpack;magmesh/status/v1`).
  `schemas.streams.json_schema(type)` gives the JSON Schema of each type.
- **Contract version {CONTRACT}.** Version 1: one sample per message. Version 2 adds batches (below) beside the
  single samples, which stay valid on every key. Version 3 adds fleet frames (below): the services' own hop
  between ingest and the stages, many vehicles per message; it reserves the chunk `fleet` (no vehicle may be
  named `fleet`) and adds the binary form of batches (version 3). Everything outside users subscribe to per vehicle
  stays on the per-vehicle keys.

## Keys

| key | message | encoding | published by | meaning |
|---|---|---|---|---|
{STREAM_ROWS}| `magmesh/svc/{role}/{instance}` | (liveliness token) | - | every service | present while the instance runs |
| `magmesh/svc/{role}/{instance}/status` | status (queryable) | `application/msgpack;magmesh/status/v1` | every service | counts, rates, drops, settings, mode |
| `magmesh/svc/{role}/{instance}/control` | (queryable) | `application/msgpack;magmesh/control/v1` | every service | hand-over control used by `magmesh swap` |

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


def _stream_rows() -> str:
    rows = []
    for st in streams.STREAMS.values():
        rows.append(f"| `{st.template}` | {st.msg_type} | `{st.encoding}` | {st.publisher} | {st.meaning} |\n")
    rows.append(f"| `magmesh/{{vehicle}}/raw/batch` | batch | `{streams.encoding_name('batch')}`, "
                f"`{streams.encoding_name('batch', 3)}` | vehicles' on-board agents | many samples of the vehicle's "
                "streams (contract v2; binary form v3) |\n")
    rows.append(f"| `magmesh/{{vehicle}}/clean/batch` | batch | `{streams.encoding_name('batch')}` | ingest "
                "(output = batches) | validated batches |\n")
    return "".join(rows)


def _limits() -> str:
    out = ["\n## Physical ranges (ingest)\n\nIngest refuses a sample outside these ranges (code `range`); the bound is "
           "the ingest setting named, whose default is shown. Every raw sample also needs `t_s` ≥ 0.\n\n"
           "| message | field | test | setting | default |\n|---|---|---|---|---|\n"]
    tests = {"norm": "norm ≤ bound", "abs": "every component within ± bound", "max": "≤ bound",
             "between": "within lo..hi"}
    for t, lims in streams.LIMITS.items():
        for lim in lims:
            d = streams.LIMIT_DEFAULTS[lim.setting]
            shown = f"{d[0]:g}..{d[1]:g}" if isinstance(d, tuple) else f"{d:g}"
            if lim.scale != 1.0:
                shown += f" × {lim.scale:g}"
            out.append(f"| {t} | `{lim.field}` | {tests[lim.how]} | `{lim.setting}` | {shown} {lim.unit} |\n")
    return "".join(out)


def render() -> str:
    out = [INTRO.replace("{STREAM_ROWS}", _stream_rows()).replace("{CONTRACT}", str(streams.CONTRACT_VERSION))]
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
    out.append(_limits())
    out.append("\n## Batches (contract version 2; binary form version 3)\n\n" + batch.__doc__.split("\n\n", 1)[1].rsplit("\n\n", 1)[0].replace("``", "`") + "\n")
    out.append("\n## Fleet frames (contract version 3)\n\n" + frame.__doc__.split("\n\n", 1)[1].rsplit("\n\n", 1)[0].replace("``", "`") + "\n")
    out.append("""
## Status replies

`magmesh/svc/{role}/{instance}/status` answers a msgpack map: `role`, `impl`, `instance`, `pid`, `host`,
`magmesh_version`, `uptime_s`, `rss_kb` (resident memory), `py_heap_blocks` (`sys.getallocatedblocks()`: grows
with a leak of Python objects), `vehicle_pattern`, `vehicles`, `consumes`, `produces`, `in` and `out`
(`{key: {n, rate_hz}}`; `out` counts every output numbered), `out_unwatched` (`{type: n}`: per-vehicle rows
numbered but not put while no subscriber matched their key — skipped by design), `rejects`, `drops`
(`{key: {reason: n}}`), `drops_total`, `queue_depth`, `last_error`, `settings`, `alarms_raised`, `mode`
(active, standby, retiring, retired), `holds_role`, `suppressed`, `cal_params_pending` (calibration parameter
sets waiting for a calibration instance to confirm them), plus service-specific entries.
""")
    return "".join(out)


if __name__ == "__main__":
    print(render(), end="")
