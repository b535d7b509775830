"""``magmesh status``: the live services (from liveliness) and their status."""

from __future__ import annotations

import argparse
import json
import sys

import msgpack

from magmesh import zconf
from schemas import keys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("status", help="list live services and their status",
                       description="List the live services (liveliness tokens) and their status replies. Exits 1 "
                       "when nothing answers within --timeout.")
    zconf.add_zenoh_args(p)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--timeout", type=float, default=3.0, metavar="S",
                   help="seconds to wait for the connection and for each query (default 3)")
    p.set_defaults(func=run)


def decode_status(payload: bytes) -> tuple[dict | None, str | None]:
    """A status reply as a dict, or ``(None, why)`` for a reply that is not one (never raises)."""
    try:
        st = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception as e:  # noqa: BLE001 - any garbage is a warning, not a crash
        return None, f"not msgpack ({type(e).__name__}: {str(e)[:60] or 'malformed bytes'})"
    if not isinstance(st, dict):
        return None, f"a msgpack {type(st).__name__}, not a status map"
    if not isinstance(st.get("role"), str) or not isinstance(st.get("instance"), str):
        return None, "a map without string fields role and instance"
    return st, None


def collect(session, timeout: float = 2.0) -> dict:
    """Live tokens and status replies. Replies that are not valid status maps are counted in ``bad_replies``
    with the reason (never a crash): any process on the mesh can answer a status query."""
    live = []
    for rep in session.liveliness().get(keys.svc_all(), timeout=timeout):
        if rep.ok is not None:
            live.append(str(rep.ok.key_expr))
    statuses = {}
    bad: list[str] = []
    for rep in session.get(keys.svc_status_all(), timeout=timeout, priority=zconf.control_priority()):
        if rep.ok is None:
            continue
        st, why = decode_status(rep.ok.payload.to_bytes())
        if st is None:
            bad.append(f"{str(rep.ok.key_expr)[:120]}: {why}")
            continue
        statuses[f"{st.get('role')}/{st.get('instance')}"] = st
    services = []
    for token in sorted(live):
        try:
            info = keys.parse(token)
            role, inst = info.rest[0], info.rest[1]
        except (keys.KeyError_, IndexError, AttributeError):
            bad.append(f"{token[:120]}: not a service token")
            continue
        st = statuses.get(f"{role}/{inst}", {})
        services.append({"role": role, "instance": inst, "status": st, "answered": bool(st)})
    return {"services": services, "bad_replies": bad, "groups": group_assignment(services)}


def group_assignment(services: list[dict]) -> dict:
    """Role groups (instances = N): per ``role/group``, each member's vehicles and every vehicle seen by a member
    that no member holds (``unowned``) or that two hold (``duplicates``)."""
    from magmesh.groups import summarize

    by: dict[str, dict] = {}
    for s in services:
        g = s["status"].get("group") if isinstance(s.get("status"), dict) else None
        if isinstance(g, dict) and isinstance(g.get("name"), str):
            by.setdefault(f"{s['role']}/{g['name']}", {})[s["instance"]] = g
    return {name: summarize(members) for name, members in sorted(by.items())}


def _num(v, default=0.0) -> float:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else default


def _fmt_rate(d) -> str:
    if not isinstance(d, dict):
        return "?"
    return f"{sum(_num(v.get('rate_hz')) for v in d.values() if isinstance(v, dict)):.0f}"


def render(result: dict) -> str:
    rows = [("ROLE", "INSTANCE", "IMPL", "HOLDS", "UP s", "IN/s", "OUT/s", "LOST", "REJECTED/SKIPPED", "VEHICLES", "NOTE")]
    for s in result["services"]:
        st = s["status"]
        try:
            rows.append(_row(s, st))
        except Exception as e:  # noqa: BLE001 - a malformed field in one reply must not hide the others
            rows.append((s["role"], s["instance"], "?", "?", "?", "?", "?", "?", "?", "?",
                         f"malformed status reply ({type(e).__name__})"))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    out = "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=False)).rstrip() for r in rows)
    for name, g in (result.get("groups") or {}).items():
        vs = g.get("vehicles", {})
        n = sum(len(x) for x in vs.values() if x)
        out += (f"\ngroup {name}: {len(vs)} members, {n} vehicles held; "
                + "; ".join(f"{m}: {', '.join(x) if x else ('-' if x is not None else 'no answer')}"
                            for m, x in vs.items())
                + f"\n  without an owner: {', '.join(g.get('unowned', [])) or 'none'}"
                + (f"; held twice: {', '.join(g['duplicates'])}" if g.get("duplicates") else ""))
    return out


def _row(s: dict, st: dict) -> tuple:
    if s["role"] == "supervisor":
        procs = st.get("processes", {})
        procs = procs if isinstance(procs, dict) else {}
        note = (f"{sum(bool(p.get('alive')) for p in procs.values())}/{len(procs)} processes alive, "
                f"{sum(int(_num(p.get('restarts'))) for p in procs.values())} restarts; alarms raised: "
                f"{', '.join(map(str, st.get('alarms_raised', []))) or 'none'}")
        given_up = [n for n, p in procs.items() if p.get("given_up")]
        if given_up:
            note += f"; given up: {', '.join(given_up)}"
        return ("supervisor", s["instance"], "-", "-", f"{_num(st.get('uptime_s')):.0f}", "-", "-", "-", "-", "-",
                note)
    note = str(st.get("last_error") or "")
    if st.get("calibration"):
        note = (note + " " + str(st["calibration"]))[:80]
    vehicles = st.get("vehicles", [])
    if isinstance(st.get("group"), dict):  # a group member: the vehicles it holds (not those it warms on)
        vehicles = st["group"].get("vehicles", [])
    return (s["role"], s["instance"], str(st.get("impl", "?")), "yes" if st.get("holds_role", True) else "no",
            f"{_num(st.get('uptime_s')):.0f}", _fmt_rate(st.get("in", {})), _fmt_rate(st.get("out", {})),
            str(st.get("lost_total", "?")), f"{st.get('rejects', '?')}/{st.get('skipped_total', '?')}",
            ",".join(map(str, vehicles if isinstance(vehicles, list) else []))[:30], note[:80])


def run(args: argparse.Namespace) -> int:
    session = zconf.open_client(args, args.timeout, "magmesh status")
    with session:
        result = collect(session, args.timeout)
    for why in result["bad_replies"]:
        print(f"warning: ignored a status reply that is not one: {why}", file=sys.stderr)
    if args.json:
        json.dump(result, sys.stdout, default=str)
        print()
        return 0 if result["services"] else 1
    if not result["services"]:
        print(f"magmesh status: no magmesh service answered at {zconf.where(args)} within {args.timeout:g} s "
              f"(the router is reachable, but no service token is live).", file=sys.stderr)
        return 1
    print(render(result))
    if result["bad_replies"]:
        print(f"({len(result['bad_replies'])} reply(ies) ignored: not valid status maps)")
    return 0
