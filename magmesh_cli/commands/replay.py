"""``magmesh replay``: publish a recording back into the mesh.

    magmesh replay run.mcap                                  # original timing
    magmesh replay run.mcap --rate max                       # as fast as the mesh takes it
    magmesh replay run.mcap --keys 'magmesh/*/clean/**' --remap car-1=car-1r

Re-running a detector on yesterday's drive: replay only its inputs (``--keys``), under another vehicle id
(``--remap``) if the live mesh still carries the original, and let the new detector publish its outputs.
Publishers are reliable with blocking congestion control: the replay slows down rather than lose data.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from magmesh import zconf

from ..recording import (
    Remap,
    ReplayStats,
    keyexpr_matches,
    parse_rate,
    read_records,
    remap_sample,
    replay,
    summarize,
    time_window,
)

log = logging.getLogger("magmesh.replay")


def register(subparsers) -> None:
    p = subparsers.add_parser("replay", help="publish an MCAP recording back into the mesh",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(p)
    p.set_defaults(func=run)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", help="MCAP file written by magmesh record")
    p.add_argument("--rate", default="1.0", help="speed factor (1.0 = original timing) or 'max'")
    p.add_argument("--keys", nargs="+", default=None, metavar="KEYEXPR", help="replay only these keys")
    p.add_argument("--start", type=float, default=0.0, metavar="S",
                   help="begin S seconds into the recording (receive time)")
    p.add_argument("--end", type=float, default=0.0, metavar="S", help="stop S seconds into the recording (0: end)")
    p.add_argument("--remap", action="append", default=[], metavar="OLD=NEW",
                   help="rename a vehicle id (car-1=car-1r) or a key prefix (repeatable)")
    p.add_argument("--wait-subscribers", type=float, default=2.0, metavar="S",
                   help="wait up to S seconds for a subscriber to match before publishing (default 2)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print the statistics as JSON")
    zconf.add_zenoh_args(p)


def replay_to_mesh(
    conf,
    path: str | Path,
    rate: float = 1.0,
    key_exprs: Sequence[str] | None = None,
    remaps: Sequence[Remap] = (),
    wait_subscribers_s: float = 2.0,
    stop: threading.Event | None = None,
    progress: bool = False,
    start_s: float = 0.0,
    end_s: float = 0.0,
) -> ReplayStats:
    """Publish a recording on a Zenoh session built from ``conf``; return what was published."""
    import zenoh

    stop = stop or threading.Event()
    summ = summarize(path)
    recorded_keys = [k for k in summ["keys"] if not k.startswith("magmesh/svc/")]
    total = sum(n for k, n in summ["keys"].items() if k in recorded_keys)
    # ``conf`` is a Zenoh configuration, or an open session (kept open: the caller closes it)
    with (contextlib.nullcontext(conf) if isinstance(conf, zenoh.Session) else zenoh.open(conf)) as session:
        pubs: dict[str, object] = {}

        def publisher(key: str):
            pub = pubs.get(key)
            if pub is None:
                pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                                reliability=zenoh.Reliability.RELIABLE)
                pubs[key] = pub
            return pub

        # declare every output key first, then give subscribers a moment to match
        for k in recorded_keys:
            if key_exprs is None or any(keyexpr_matches(e, k) for e in key_exprs):
                publisher(remap_sample(k, b"", remaps)[0])
        deadline = time.monotonic() + wait_subscribers_s
        while pubs and time.monotonic() < deadline and not stop.is_set():
            if any(p.matching_status.matching for p in pubs.values()):
                time.sleep(0.2)  # let the remaining routes settle
                break
            time.sleep(0.02)
        if pubs and not any(p.matching_status.matching for p in pubs.values()):
            log.warning("no subscriber matches the replayed keys yet; publishing anyway")

        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=total, unit="msg", desc="replay", file=sys.stderr)
        try:
            records = time_window(read_records(path, key_exprs), summ["start_ns"] or 0, start_s, end_s)
            stats = replay(records, lambda k, p: publisher(k).put(p), rate=rate,
                           remaps=remaps, should_stop=stop.is_set, on_progress=bar.update if bar else None)
        finally:
            if bar is not None:
                bar.close()
        time.sleep(0.1)  # let the last samples leave before the session closes
    return stats


def format_stats(stats: ReplayStats) -> str:
    d = stats.as_dict()
    lines = [f"replayed {d['published']} messages on {d['keys']} keys in {d['wall_s']:.2f} s "
             f"(recording span {d['recorded_span_s']:.2f} s, largest lag behind schedule {d['max_late_s']:.3f} s)"]
    width = max((len(k) for k in d["per_key"]), default=0)
    lines += [f"  {k:<{width}}  {n}" for k, n in d["per_key"].items()]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        rate = parse_rate(args.rate)
        remaps = [Remap.parse(r) for r in args.remap]
    except ValueError as e:
        raise SystemExit(f"magmesh replay: {e}") from None
    if not Path(args.input).exists():
        raise SystemExit(f"magmesh replay: {args.input} does not exist")
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda s, f: stop.set())
    signal.signal(signal.SIGTERM, lambda s, f: stop.set())
    session = zconf.open_client(args, 10.0, "magmesh replay")  # bounded: nothing answering is an error
    with session:
        stats = replay_to_mesh(session, args.input, rate, args.keys, remaps,
                               args.wait_subscribers, stop, progress=not args.no_progress and sys.stderr.isatty(),
                               start_s=args.start, end_s=args.end)
    print(json.dumps(stats.as_dict()) if args.json else format_stats(stats))
    return 0
