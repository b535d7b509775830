"""``magmesh alarms``: print alarm transitions as they arrive (currently raised ones first)."""

from __future__ import annotations

import argparse
import json
import sys
import time

from magmesh import zconf
from magmesh.errors import UserError
from schemas import keys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("alarms", help="print alarm events as they arrive",
                       description="Print the currently raised alarms (each once), then every alarm transition as "
                       "it arrives. A reply or sample that is not a valid alarm is counted and shown as a warning.")
    zconf.add_zenoh_args(p)
    p.add_argument("--vehicle", default="*", help="vehicle id or pattern (default all)")
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--timeout", type=float, default=5.0, metavar="S",
                   help="seconds to wait for the connection and for the currently raised alarms (default 5)")
    p.set_defaults(func=run)


def fmt(msg: dict) -> str:
    v = msg.get("value")
    th = msg.get("threshold")
    unit = msg.get("unit", "")
    vals = f" value {v:.3g}{unit} / threshold {th:.3g}{unit}" if isinstance(v, float) and isinstance(th, float) else ""
    return (f"t={msg.get('t_s', 0):9.2f}s {msg.get('vehicle')} {msg.get('source'):>18} {msg.get('state').upper():8} "
            f"{msg.get('severity')}: {msg.get('reason')}{vals} [{msg.get('service')} #{msg.get('seq')}]")


class AlarmPrinter:
    """Validates every alarm against the contract and prints each transition once.

    A transition is identified by its key and ``seq``: the query of the currently raised alarms, the
    publishers' history and miss recovery may all deliver the same one; it is printed the first time only.
    Anything that is not a valid alarm is counted by reason and reported as a warning line."""

    SEEN_PER_KEY = 256

    def __init__(self, out=sys.stdout, err=sys.stderr, as_json: bool = False):
        self.out, self.err, self.as_json = out, err, as_json
        self.seen: dict[str, dict[int, None]] = {}
        self.bad: dict[str, int] = {}
        self.printed = 0
        self.repeated = 0

    def feed(self, key: str, payload: bytes, prefix: str = "") -> bool:
        from schemas import messages
        from schemas.messages import SchemaError

        try:
            msg = messages.decode(payload, where=key, expected_type="alarm")
        except SchemaError as e:
            return self._bad(key, "decode" if e.field == "<payload>" else "schema", str(e))
        except Exception as e:  # noqa: BLE001 - a reply must never crash the tool
            return self._bad(key, "decode", f"{type(e).__name__}: {e}")
        seen = self.seen.setdefault(key, {})
        if msg["seq"] in seen:
            self.repeated += 1
            return False
        seen[msg["seq"]] = None
        if len(seen) > self.SEEN_PER_KEY:
            del seen[next(iter(seen))]
        print(json.dumps(msg) if self.as_json else prefix + fmt(msg), file=self.out, flush=True)
        self.printed += 1
        return True

    def _bad(self, key: str, code: str, why: str) -> bool:
        self.bad[code] = self.bad.get(code, 0) + 1
        print(f"warning: ignored an invalid alarm on {key[:200]} ({code}): {why[:300]}", file=self.err, flush=True)
        return False


def run(args: argparse.Namespace) -> int:
    """Currently raised alarms first (queried), then every transition as it arrives.

    The live part is an AdvancedSubscriber with miss detection: a transition lost on the way is reported,
    never silently skipped.
    """
    import queue

    from zenoh import ext

    try:
        keys.alarms_all(args.vehicle)
    except keys.KeyError_ as e:
        raise UserError(f"--vehicle: {e}; give a vehicle id such as car-1 or a pattern such as 'car-$*'") from None
    from .swap import check_wildcards

    check_wildcards(args.vehicle, "--vehicle")
    out = sys.stdout
    printer = AlarmPrinter(out, sys.stderr, args.json)
    q: queue.Queue = queue.Queue()
    deadline = time.monotonic() + args.duration if args.duration else None
    session = zconf.open_client(args, args.timeout, "magmesh alarms")
    with session:
        sub = ext.declare_advanced_subscriber(
            session, keys.alarms_all(args.vehicle), lambda s: q.put(("s", str(s.key_expr), s.payload.to_bytes())),
            recovery=ext.RecoveryConfig(heartbeat=True), subscriber_detection=True)
        sub.sample_miss_listener(lambda m: q.put(("miss", str(m.source), m.nb)))
        try:
            query_s = args.timeout if deadline is None else max(0.1, min(args.timeout, deadline - time.monotonic()))
            for rep in session.get(keys.alarms_all(args.vehicle), timeout=query_s,
                                   priority=zconf.control_priority()):
                if rep.ok is not None:
                    printer.feed(str(rep.ok.key_expr), rep.ok.payload.to_bytes(), "(currently raised) ")
            while deadline is None or time.monotonic() < deadline:
                # bounded waits so Ctrl-C and --duration are noticed promptly
                timeout = 0.5 if deadline is None else max(0.0, min(0.5, deadline - time.monotonic()))
                try:
                    ev = q.get(timeout=timeout)
                except queue.Empty:
                    continue
                if ev[0] == "miss":
                    print(f"WARNING: {ev[2]} alarm sample(s) from {ev[1]} were missed in transit", file=sys.stderr,
                          flush=True)
                    continue
                printer.feed(ev[1], ev[2])
        except KeyboardInterrupt:
            pass
        sub.undeclare()
    if printer.bad:
        print(f"magmesh alarms: ignored {sum(printer.bad.values())} invalid alarm(s) "
              f"({', '.join(f'{k} {n}' for k, n in sorted(printer.bad.items()))})", file=sys.stderr)
    return 0
