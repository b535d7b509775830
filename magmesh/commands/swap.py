"""``magmesh swap ROLE IMPL``: hand a role over to another implementation while the mesh runs."""

from __future__ import annotations

import argparse
import json
import sys

import msgpack

from schemas import keys

from .. import zconf


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("swap", help="swap the implementation serving a role, live, without losing an output",
                       description="Ask the supervisor to start IMPL for ROLE in standby, warm it on live input, "
                       "and hand the role over at an agreed cut-over time (see magmesh/swap.py).")
    p.add_argument("role", help="role, e.g. dmc_detector")
    p.add_argument("impl", help="implementation, e.g. fcm, threshold, single, quasistatic")
    p.add_argument("--supervisor", default="main", help="supervisor instance (default main)")
    p.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for the new instance to be ready")
    p.add_argument("--json", action="store_true")
    zconf.add_zenoh_args(p)
    p.set_defaults(func=run)


def request_swap(session, role: str, impl: str, supervisor: str = "main", timeout: float = 30.0) -> dict:
    payload = msgpack.packb({"op": "swap", "role": role, "impl": impl, "timeout_s": timeout}, use_bin_type=True)
    for rep in session.get(keys.svc_control("supervisor", supervisor), payload=payload, timeout=timeout + 15):
        if rep.ok is not None:
            return msgpack.unpackb(rep.ok.payload.to_bytes())
        return {"ok": False, "error": f"supervisor error: {rep.err.payload.to_bytes()!r}"}
    return {"ok": False, "error": f"no supervisor {supervisor!r} answered"}


def run(args: argparse.Namespace) -> int:
    import zenoh

    keys.check_id(args.role, "role")
    keys.check_id(args.impl, "implementation")
    with zenoh.open(zconf.config_from_args(args)) as session:
        res = request_swap(session, args.role, args.impl, args.supervisor, args.timeout)
    if args.json:
        json.dump(res, sys.stdout)
        print()
    elif res.get("ok"):
        print(f"{args.role}: {res['new']} ({res['impl']}) took over from {res['old']} in {res['took_s']} s; "
              f"sequence numbers continue from {res['seqs']}")
    else:
        print(f"swap failed: {res.get('error')}", file=sys.stderr)
    return 0 if res.get("ok") else 1
