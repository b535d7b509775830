"""``magmesh scale PROCESS N``: run N instances of a group process (``instances = N`` in the manifest), live."""

from __future__ import annotations

import argparse
import json
import sys

import msgpack

from magmesh import zconf
from magmesh.errors import UserError
from schemas import keys

MAX_INSTANCES = 64  # as magmesh_cli.supervisor.MAX_INSTANCES (not imported: this command stays light)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scale", help="change the number of instances of a group process, live",
                       description="Ask the supervisor to run N instances PROCESS-1..N of a process that has "
                       "instances = N in the manifest. The instances share the vehicles (each vehicle served by one "
                       "of them); a new instance warms on the vehicles it will own and takes them over at an agreed "
                       "sample time; instances beyond N hand theirs over the same way and stop. Sequence numbers "
                       "continue and alarm states move with each vehicle (README, Elastic roles).")
    p.add_argument("process", help="the [[process]] name in the manifest, e.g. dmc")
    p.add_argument("n", help=f"the number of instances, 1 to {MAX_INSTANCES}")
    p.add_argument("--supervisor", default="main", help="supervisor instance (default main)")
    p.add_argument("--timeout", type=float, default=10.0, metavar="S", help="seconds to connect (default 10)")
    p.add_argument("--json", action="store_true")
    zconf.add_zenoh_args(p)
    p.set_defaults(func=run)


def request_scale(session, name: str, n: int, supervisor: str = "main", timeout: float = 120.0) -> dict:
    payload = msgpack.packb({"op": "scale", "name": name, "n": n}, use_bin_type=True)
    for rep in session.get(keys.svc_control("supervisor", supervisor), payload=payload, timeout=timeout,
                           priority=zconf.control_priority()):
        if rep.ok is None:
            return {"ok": False, "error": "supervisor error: "
                    f"{rep.err.payload.to_bytes().decode('utf-8', 'replace')[:500]}"}
        try:
            res = msgpack.unpackb(rep.ok.payload.to_bytes(), raw=False, strict_map_key=False)
        except Exception as e:  # noqa: BLE001 - a bad reply is reported, not a crash
            return {"ok": False, "error": f"the reply of supervisor {supervisor!r} is not msgpack ({type(e).__name__})"}
        return res if isinstance(res, dict) else {"ok": False, "error": "the supervisor's reply is not a map"}
    return {"ok": False, "error": f"no supervisor {supervisor!r} answered (is the mesh running under magmesh up? "
            f"see magmesh status)"}


def run(args: argparse.Namespace) -> int:
    for value, what in ((args.process, "process name"), (args.supervisor, "supervisor")):
        try:
            keys.check_id(value, what)
        except keys.KeyError_ as e:
            raise UserError(f"{e}. Name the [[process]] as in the manifest, e.g. magmesh scale dmc 3", 2) from None
    try:
        n = int(args.n)
    except ValueError:
        n = None
    if n is None or not 1 <= n <= MAX_INSTANCES:
        raise UserError(f"the number of instances must be a whole number from 1 to {MAX_INSTANCES}, not "
                        f"{args.n!r}; e.g. magmesh scale {args.process} 3", 2)
    session = zconf.open_client(args, args.timeout, "magmesh scale")
    with session:
        res = request_scale(session, args.process, n, args.supervisor)
    if args.json:
        json.dump(res, sys.stdout, default=str)
        print()
    elif res.get("ok"):
        parts = [f"{args.process}: {len(res.get('instances', []))} instances ({', '.join(res.get('instances', []))})"]
        if res.get("started"):
            parts.append(f"started {', '.join(res['started'])}")
        if res.get("stopped"):
            kept = [i for i, ok in (res.get("handed_over") or {}).items() if not ok]
            parts.append(f"stopped {', '.join(res['stopped'])}" + (
                f" ({', '.join(kept)} still held vehicles: taken over from its persisted state)" if kept else
                " after handing their vehicles over"))
        print("; ".join(parts) + f"; {res.get('took_s')} s")
    else:
        print(f"magmesh scale: {res.get('error')}", file=sys.stderr)
    return 0 if res.get("ok") else 1
