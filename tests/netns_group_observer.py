"""What an outside subscriber sees of a DMC detector group on the multi-host test, run inside a network namespace.

It collects every ``dmc`` output, ``alarm/dmc`` transition and clean magnetometer sample (bench/elastic_run.py's
Collector), writes the group's assignment as its members report it every 0.3 s to ``views.jsonl``, and when the
stop file appears (or the duration ends) the members' final statuses to ``final.json`` and everything seen to
``seen.msgpack`` (key, message per item).

    python tests/netns_group_observer.py --connect tcp/10.231.0.1:7447 --out DIR --stop-file DIR/stop
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import msgpack  # noqa: E402

from bench.elastic_run import Collector, group_view, statuses  # noqa: E402
from magmesh import zconf  # noqa: E402
from schemas import keys  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser()
    zconf.add_zenoh_args(p)
    p.add_argument("--out", required=True)
    p.add_argument("--duration", type=float, default=120.0)
    p.add_argument("--stop-file", required=True)
    args = p.parse_args()

    import zenoh

    out = Path(args.out)
    session = zenoh.open(zconf.config_from_args(args))
    data = [Collector(session, keys.dmc("*")), Collector(session, keys.alarm("*", "dmc")),
            Collector(session, "magmesh/*/clean/mag/*")]
    views = open(out / "views.jsonl", "a", buffering=1)
    views.write(json.dumps({"t": time.time(), "ready": True}) + "\n")
    t_end = time.monotonic() + args.duration
    while time.monotonic() < t_end and not Path(args.stop_file).exists():
        try:
            view, sts = group_view(session)
            views.write(json.dumps({"t": time.time(), "view": view,
                                    "busy": any(st["group"]["warming"] or st["group"]["taking"] or
                                                st["group"]["releasing"] for st in sts.values() if "group" in st)})
                        + "\n")
        except Exception as e:  # noqa: BLE001 - a status round that failed is retried
            views.write(json.dumps({"t": time.time(), "error": str(e)}) + "\n")
        time.sleep(0.3)
    (out / "final.json").write_text(json.dumps(statuses(session)))
    with open(out / "seen.msgpack", "wb") as f:
        for c in data:
            for k, m, _t in list(c.items):
                f.write(msgpack.packb((k, m), use_bin_type=True))
    (out / "done").write_text("")
    session.close()


if __name__ == "__main__":
    main()
