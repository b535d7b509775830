"""``magmesh swap ROLE IMPL``: hand a role over to another implementation while the mesh runs."""

from __future__ import annotations

import argparse
import json
import re
import sys

import msgpack

from magmesh import zconf
from magmesh.errors import UserError
from schemas import keys


def check_wildcards(pattern: str, flag: str) -> None:
    """A vehicle pattern as Zenoh reads it: ``*`` alone, or ``$*`` inside a name (``car-$*``, not ``car-*``)."""
    if pattern not in ("*", "**") and re.search(r"(?<!\$)\*", pattern):
        fixed = re.sub(r"(?<!\$)\*", "$*", pattern)
        raise UserError(f"{flag} pattern {pattern!r} is not valid: inside a name a wildcard is written $* "
                        f"(e.g. {fixed!r}); * alone means every vehicle", 2)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("swap", help="swap the implementation serving a role, live, without losing an output",
                       description="Ask the supervisor to start IMPL for ROLE in standby beside the instance it "
                       "replaces, warm it on live input, and hand the role over at an agreed cut-over time (README, "
                       "Live swap). With one candidate instance no option is needed; with several, name "
                       "one with --instance or --vehicles. An instance whose manifest settings IMPL does not know "
                       "(for example the quasi-static detector's level) is not a candidate unless named, and "
                       "then the swap is refused with the settings listed.")
    p.add_argument("role", help="role, e.g. dmc_detector")
    p.add_argument("impl", help="implementation, e.g. fcm, threshold, single, quasistatic")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--instance", default=None, metavar="NAME", help="the instance to replace, e.g. dmc-1")
    g.add_argument("--vehicles", default=None, metavar="PATTERN",
                   help="the instance serving these vehicles, e.g. car-1 or 'car-$*'")
    p.add_argument("--supervisor", default="main", help="supervisor instance (default main)")
    p.add_argument("--timeout", type=float, default=30.0, metavar="S",
                   help="seconds to wait for the new instance to be ready (the connection: at most 10 s)")
    p.add_argument("--json", action="store_true")
    zconf.add_zenoh_args(p)
    p.set_defaults(func=run)


def request_swap(session, role: str, impl: str, supervisor: str = "main", timeout: float = 30.0,
                 instance: str | None = None, vehicles: str | None = None) -> dict:
    req = {"op": "swap", "role": role, "impl": impl, "timeout_s": timeout}
    if instance:
        req["instance"] = instance
    if vehicles:
        req["vehicles"] = vehicles
    payload = msgpack.packb(req, use_bin_type=True)
    for rep in session.get(keys.svc_control("supervisor", supervisor), payload=payload, timeout=timeout + 45,
                           priority=zconf.control_priority()):
        if rep.ok is None:
            return {"ok": False, "error": f"supervisor error: {_text(rep.err.payload.to_bytes())}"}
        try:
            res = msgpack.unpackb(rep.ok.payload.to_bytes(), raw=False, strict_map_key=False)
        except Exception as e:  # noqa: BLE001 - a bad reply is reported, not a crash
            return {"ok": False, "error": f"the reply of supervisor {supervisor!r} is not msgpack "
                    f"({type(e).__name__})"}
        if not isinstance(res, dict):
            return {"ok": False, "error": f"the reply of supervisor {supervisor!r} is not a map"}
        return res
    return {"ok": False, "error": f"no supervisor {supervisor!r} answered (is the mesh running under magmesh up? "
            f"see magmesh status)", "no_answer": True}


def _text(b: bytes) -> str:
    return b.decode("utf-8", "replace")[:500]


def run(args: argparse.Namespace) -> int:
    for value, what in ((args.role, "role"), (args.impl, "implementation"), (args.supervisor, "supervisor"),
                        (args.instance, "instance")):
        if value is not None:
            try:
                keys.check_id(value, what)
            except keys.KeyError_ as e:
                raise UserError(f"{e}. Roles and names are as magmesh status lists them, e.g. "
                                f"magmesh swap dmc_detector fcm --instance dmc-1") from None
    if args.vehicles is not None:
        try:
            keys.check_pattern(args.vehicles, "--vehicles pattern")
        except keys.KeyError_ as e:
            raise UserError(str(e)) from None
        check_wildcards(args.vehicles, "--vehicles")
    session = zconf.open_client(args, min(args.timeout, 10.0), "magmesh swap")
    with session:
        res = request_swap(session, args.role, args.impl, args.supervisor, args.timeout, args.instance,
                           args.vehicles)
    if args.json:
        json.dump(res, sys.stdout, default=str)
        print()
    elif res.get("ok"):
        print(f"{args.role}: {res.get('new')} ({res.get('impl')}) took over from {res.get('old')} in "
              f"{res.get('took_s')} s; sequence numbers continue from {res.get('seqs')}")
    else:
        print(f"magmesh swap: {args.role} to {args.impl} failed: {res.get('error')}", file=sys.stderr)
    return 0 if res.get("ok") else 1
