"""``magmesh status``: the live services (from liveliness) and their status."""

from __future__ import annotations

import argparse
import json
import sys

import msgpack

from schemas import keys

from .. import zconf


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("status", help="list live services and their status")
    zconf.add_zenoh_args(p)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--timeout", type=float, default=2.0, help="query timeout, s")
    p.set_defaults(func=run)


def collect(session, timeout: float = 2.0) -> dict:
    live = []
    for rep in session.liveliness().get(keys.svc_all(), timeout=timeout):
        if rep.ok is not None:
            live.append(str(rep.ok.key_expr))
    statuses = {}
    for rep in session.get(keys.svc_status_all(), timeout=timeout):
        if rep.ok is not None:
            st = msgpack.unpackb(rep.ok.payload.to_bytes())
            statuses[f"{st.get('role')}/{st.get('instance')}"] = st
    services = []
    for token in sorted(live):
        info = keys.parse(token)
        role, inst = info.rest[0], info.rest[1]
        st = statuses.get(f"{role}/{inst}", {})
        services.append({"role": role, "instance": inst, "status": st, "answered": bool(st)})
    return {"services": services}


def _fmt_rate(d: dict) -> str:
    return f"{sum(v.get('rate_hz', 0) for v in d.values()):.0f}"


def render(result: dict) -> str:
    rows = [("ROLE", "INSTANCE", "IMPL", "HOLDS", "UP s", "IN/s", "OUT/s", "REJECTS", "DROPS", "VEHICLES", "NOTE")]
    for s in result["services"]:
        st = s["status"]
        if s["role"] == "supervisor":
            procs = st.get("processes", {})
            note = (f"{sum(p['alive'] for p in procs.values())}/{len(procs)} processes alive, "
                    f"{sum(p['restarts'] for p in procs.values())} restarts; alarms raised: "
                    f"{', '.join(st.get('alarms_raised', [])) or 'none'}")
            rows.append(("supervisor", s["instance"], "-", "-", f"{st.get('uptime_s', 0):.0f}", "-", "-", "-", "-", "-",
                         note))
            continue
        note = st.get("last_error") or ""
        if st.get("calibration"):
            note = (note + " " + str(st["calibration"]))[:80]
        rows.append((s["role"], s["instance"], st.get("impl", "?"), "yes" if st.get("holds_role", True) else "no",
                     f"{st.get('uptime_s', 0):.0f}", _fmt_rate(st.get("in", {})), _fmt_rate(st.get("out", {})),
                     str(st.get("rejects", "?")), str(st.get("drops_total", "?")),
                     ",".join(st.get("vehicles", []))[:30], note[:80]))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=False)).rstrip() for r in rows)


def run(args: argparse.Namespace) -> int:
    import zenoh

    with zenoh.open(zconf.config_from_args(args)) as session:
        result = collect(session, args.timeout)
    if args.json:
        json.dump(result, sys.stdout, default=str)
        print()
    else:
        if not result["services"]:
            print(f"no magmesh services answered at {', '.join(args.connect or [zconf.default_endpoint()])}")
            return 1
        print(render(result))
    return 0
