"""``magmesh alarms``: print alarm transitions as they arrive (currently raised ones first)."""

from __future__ import annotations

import argparse
import json
import sys
import time

import msgpack

from schemas import keys

from .. import zconf


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("alarms", help="print alarm events as they arrive")
    zconf.add_zenoh_args(p)
    p.add_argument("--vehicle", default="*", help="vehicle id or pattern (default all)")
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    p.set_defaults(func=run)


def fmt(msg: dict) -> str:
    v = msg.get("value")
    th = msg.get("threshold")
    unit = msg.get("unit", "")
    vals = f" value {v:.3g}{unit} / threshold {th:.3g}{unit}" if isinstance(v, float) and isinstance(th, float) else ""
    return (f"t={msg.get('t_s', 0):9.2f}s {msg.get('vehicle')} {msg.get('source'):>18} {msg.get('state').upper():8} "
            f"{msg.get('severity')}: {msg.get('reason')}{vals} [{msg.get('service')} #{msg.get('seq')}]")


def run(args: argparse.Namespace) -> int:
    """Currently raised alarms first (queried), then every transition as it arrives.

    The live part is an AdvancedSubscriber with miss detection: a transition lost on the way is reported,
    never silently skipped.
    """
    import queue

    import zenoh
    from zenoh import ext

    out = sys.stdout
    q: queue.Queue = queue.Queue()
    with zenoh.open(zconf.config_from_args(args)) as session:
        sub = ext.declare_advanced_subscriber(
            session, keys.alarms_all(args.vehicle), lambda s: q.put(("s", str(s.key_expr), s.payload.to_bytes())),
            recovery=ext.RecoveryConfig(heartbeat=True), subscriber_detection=True)
        sub.sample_miss_listener(lambda m: q.put(("miss", str(m.source), m.nb)))
        for rep in session.get(keys.alarms_all(args.vehicle), timeout=2.0):
            if rep.ok is not None:
                msg = msgpack.unpackb(rep.ok.payload.to_bytes())
                print(json.dumps(msg) if args.json else "(currently raised) " + fmt(msg), file=out, flush=True)
        deadline = time.monotonic() + args.duration if args.duration else None
        try:
            while deadline is None or time.monotonic() < deadline:
                timeout = None if deadline is None else max(0.0, deadline - time.monotonic())
                try:
                    ev = q.get(timeout=timeout)
                except queue.Empty:
                    break
                if ev[0] == "miss":
                    print(f"WARNING: {ev[2]} alarm sample(s) from {ev[1]} were missed in transit", file=sys.stderr,
                          flush=True)
                    continue
                try:
                    msg = msgpack.unpackb(ev[2])
                except Exception:
                    print(f"undecodable alarm payload on {ev[1]}", file=sys.stderr)
                    continue
                print(json.dumps(msg) if args.json else fmt(msg), file=out, flush=True)
        except KeyboardInterrupt:
            pass
        sub.undeclare()
    return 0
