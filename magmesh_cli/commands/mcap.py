"""``magmesh mcap``: look into recordings and convert them.

    magmesh mcap info run.mcap                      # keys, counts, time span, how it was recorded
    magmesh mcap to-json run.mcap -o run.json.mcap  # JSON-encoded copy for viewers such as Foxglove
    magmesh mcap to-json --foxglove run.mcap -o fox.mcap  # + foxglove.Log / LocationFix / PoseInFrame / tf
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
from pathlib import Path

from ..recording import load_liveliness, summarize, to_json_mcap


def register(subparsers) -> None:
    p = subparsers.add_parser("mcap", help="inspect or convert MCAP recordings", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="mcap_command", metavar="ACTION")
    i = sub.add_parser("info", help="keys, counts, time span and metadata of a recording")
    i.add_argument("input")
    i.add_argument("--json", action="store_true")
    i.set_defaults(func=run_info)
    j = sub.add_parser("to-json", help="copy with JSON-encoded messages (Foxglove and other viewers)")
    j.add_argument("input")
    j.add_argument("-o", "--output", required=True)
    j.add_argument("--keys", nargs="+", default=None, metavar="KEYEXPR")
    j.add_argument("--foxglove", action="store_true",
                   help="also write Foxglove's well-known types (alarms as foxglove.Log, fixes as "
                        "foxglove.LocationFix, attitude as PoseInFrame and /tf), as `magmesh record --encoding json`")
    j.set_defaults(func=run_to_json)
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])


def _check(path: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise SystemExit(f"magmesh mcap: {p} does not exist")
    return p


def run_info(args: argparse.Namespace) -> int:
    s = summarize(_check(args.input))
    s["liveliness"] = [{"t_unix_s": t, "token": k, "alive": a} for t, k, a in load_liveliness(args.input)]
    if args.json:
        print(json.dumps(s))
        return 0
    start = (_dt.datetime.fromtimestamp(s["start_ns"] / 1e9, _dt.UTC).isoformat(timespec="seconds")
             if s["start_ns"] else "-")
    print(f"{s['path']}: {s['messages']} samples on {len(s['keys'])} keys, {s['duration_s']:.1f} s from {start}")
    meta = s["metadata"]
    if meta.get("key_exprs"):
        print(f"  recorded: {meta['key_exprs']}")
    if meta.get("counts"):
        c = json.loads(meta["counts"])
        print(f"  recorder counts: {c['written']} valid, {c['unvalidated']} not valid, {c['skipped']} not written")
    width = max((len(k) for k in s["keys"]), default=0)
    for k, n in s["keys"].items():
        print(f"  {k:<{width}}  {n}")
    for ev in s["liveliness"]:
        print(f"  service {'up  ' if ev['alive'] else 'gone'} {ev['token']}")
    return 0


def run_to_json(args: argparse.Namespace) -> int:
    if args.foxglove:
        from ..foxglove_mcap import export

        c = export(_check(args.input), args.output, args.keys)
        print(f"wrote {c['written']} JSON messages and {c['foxglove_messages']} Foxglove-typed messages to "
              f"{args.output}" + (f" ({c['unvalidated']} undecodable kept as bytes)" if c["unvalidated"] else ""))
        return 0
    r = to_json_mcap(_check(args.input), args.output, args.keys)
    print(f"wrote {r['written']} JSON messages to {args.output}" +
          (f" ({r['left_out']} undecodable left out)" if r["left_out"] else ""))
    return 0
