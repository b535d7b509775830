"""``magmesh record``: record mesh traffic to an MCAP file.

    magmesh record -o run.mcap                       # everything under magmesh/**
    magmesh record 'magmesh/car-1/**' -o car.mcap --duration 60

Every sample received is written (payload bytes unchanged, receive time and sample time) or counted
with the reason it was not (delete samples, duplicates from overlapping key expressions); the counts
are printed at the end and stored in the file. Service liveliness (``magmesh/svc/**``) is recorded as
appear/disappear events so a report can show when a service was swapped. Stops on Ctrl-C/SIGTERM or
after ``--duration``.
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
from collections.abc import Callable, Sequence
from pathlib import Path

from magmesh import zconf
from schemas import keys

from ..recording import RecordingWriter, keyexpr_matches

log = logging.getLogger("magmesh.record")

FIFO_CAPACITY = 16384
IDLE_SLEEP_S = 0.0005
MAX_IDLE_SLEEP_S = 0.002
SETTLE_MAX_S = 0.5  # after the stop: drain what is queued for at most this long


def register(subparsers) -> None:
    p = subparsers.add_parser("record", help="record mesh traffic to an MCAP file",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(p)
    p.set_defaults(func=run)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("key_exprs", nargs="*", metavar="KEYEXPR", help=f"key expressions (default {keys.everything()})")
    p.add_argument("-o", "--output", required=True, help="MCAP file to write")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: until Ctrl-C)")
    p.add_argument("--exclude", nargs="+", default=(), metavar="KEYEXPR", help="receive but do not write these keys")
    p.add_argument("--no-liveliness", action="store_true", help="do not record service liveliness events")
    p.add_argument("--compression", choices=["zstd", "lz4", "none"], default="zstd")
    p.add_argument("--encoding", choices=["msgpack", "json"], default="msgpack",
                   help="msgpack: the wire bytes unchanged, for replay (default); json: json messages with "
                        "jsonschema schemas and Foxglove types (foxglove.Log, LocationFix, PoseInFrame, "
                        "FrameTransform) that Foxglove opens as they are (also replayable)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress line")
    p.add_argument("--timeout", type=float, default=10.0, metavar="S",
                   help="seconds to wait for the connection to the mesh (default 10)")
    zconf.add_zenoh_args(p)


def record(
    conf,
    output: str | Path,
    key_exprs: Sequence[str] = (),
    duration_s: float = 0.0,
    liveliness: bool = True,
    compression: str = "zstd",
    stop: threading.Event | None = None,
    on_progress: Callable[[dict], None] | None = None,
    ready: threading.Event | None = None,
    exclude: Sequence[str] = (),
    encoding: str = "msgpack",
) -> dict:
    """Record until ``stop`` is set or ``duration_s`` passes; return the counts (also stored in the file).

    Samples on keys matching ``exclude`` are received but not written, and counted as such.
    """
    import zenoh

    exprs = list(key_exprs) or [keys.everything()]
    stop = stop or threading.Event()
    info = {"key_exprs": exprs, "exclude": list(exclude), "started_unix_s": time.time(), "tool": "magmesh record"}
    excluded: dict[str, bool] = {}
    if encoding == "json":
        from ..foxglove_mcap import FoxgloveMcapWriter as writer_cls
    else:
        writer_cls = RecordingWriter
    # ``conf`` is a Zenoh configuration, or an open session (kept open: the caller closes it)
    session_cm = contextlib.nullcontext(conf) if isinstance(conf, zenoh.Session) else zenoh.open(conf)
    with session_cm as session, writer_cls(output, info=info, compression=compression) as writer:
        subs = [(e, session.declare_subscriber(e, zenoh.handlers.FifoChannel(FIFO_CAPACITY))) for e in exprs]
        live = None
        if liveliness:
            live = session.liveliness().declare_subscriber(f"{keys.ROOT}/{keys.SVC}/**",
                                                           zenoh.handlers.FifoChannel(1024), history=True)
        if ready is not None:
            ready.set()
        t_end = time.monotonic() + duration_s if duration_s > 0 else None
        last_report = time.monotonic()

        earlier: dict[tuple[int, str], bool] = {}

        def _earlier(i: int, key: str) -> bool:
            """An earlier key expression also matches: that subscription keeps the sample."""
            hit = earlier.get((i, key))
            if hit is None:
                hit = earlier[(i, key)] = any(keyexpr_matches(prev, key) for prev, _ in subs[:i])
            return hit

        def _excluded(key: str) -> bool:
            hit = excluded.get(key)
            if hit is None:
                hit = excluded[key] = any(keyexpr_matches(e, key) for e in exclude)
            return hit

        def drain_once() -> int:
            n = 0
            for i, (_expr, sub) in enumerate(subs):
                while True:
                    sample = sub.try_recv()
                    if sample is None:
                        break
                    n += 1
                    now_ns = time.time_ns()
                    key = str(sample.key_expr)
                    if sample.kind != zenoh.SampleKind.PUT:
                        writer.skip(key, "delete sample")
                    elif i and _earlier(i, key):
                        writer.skip(key, "duplicate (overlapping key expressions)")
                    elif exclude and _excluded(key):
                        writer.skip(key, "excluded")
                    else:
                        writer.write(key, sample.payload.to_bytes(), now_ns)
            if live is not None:
                while True:
                    s = live.try_recv()
                    if s is None:
                        break
                    n += 1
                    writer.write_liveliness(str(s.key_expr), s.kind == zenoh.SampleKind.PUT, time.time_ns())
            return n

        idle_s = IDLE_SLEEP_S
        while not stop.is_set() and (t_end is None or time.monotonic() < t_end):
            if drain_once() == 0:
                # back off while nothing arrives (a first sample after a pause is stamped ≤ 2 ms late)
                time.sleep(idle_s)
                idle_s = min(idle_s * 1.5, MAX_IDLE_SLEEP_S)
            else:
                idle_s = IDLE_SLEEP_S
            if on_progress is not None and time.monotonic() - last_report >= 1.0:
                last_report = time.monotonic()
                on_progress(writer.counts.as_dict())
        # take what is already queued: nothing received is left uncounted. Bounded: on a live mesh new samples
        # keep arriving, and extending the settle window on each one would never end (a --duration that hangs)
        settle = time.monotonic() + 0.2
        settle_hard = time.monotonic() + SETTLE_MAX_S
        while time.monotonic() < min(settle, settle_hard):
            if drain_once():
                settle = time.monotonic() + 0.05
            else:
                time.sleep(0.01)
        drain_once()
        for _, sub in subs:
            sub.undeclare()
        if live is not None:
            live.undeclare()
        writer.info["stopped_unix_s"] = time.time()
        counts = writer.close()
    return counts


def format_counts(counts: dict, path: str | Path) -> str:
    lines = [f"recorded {counts['written']} messages on {counts['keys']} keys to {path}"]
    if counts.get("liveliness"):
        lines.append(f"  service liveliness events: {counts['liveliness']}")
    if counts["unvalidated"]:
        lines.append(f"  kept but not valid magmesh messages: {counts['unvalidated']}")
    for reason, n in counts.get("skipped_per_reason", {}).items():
        lines.append(f"  not written ({reason}): {n}")
    if counts.get("missed"):
        lines.append(f"  MISSED in transit (gaps in seq, never received): {counts['missed']} on "
                     + ", ".join(f"{k} {n}" for k, n in counts["missed_per_key"].items()))
    width = max((len(k) for k in counts["per_key"]), default=0)
    for k, n in counts["per_key"].items():
        lines.append(f"  {k:<{width}}  {n}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    session = zconf.open_client(args, args.timeout, "magmesh record")
    stop = threading.Event()

    def _on_signal(signum, frame):
        stop.set()

    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    tty = sys.stderr.isatty() and not args.quiet

    def progress(c: dict) -> None:
        if tty:
            print(f"\rrecording: {c['written']} messages, {c['keys']} keys, {c['skipped']} not written",
                  end="", file=sys.stderr, flush=True)

    with session:
        counts = record(session, args.output, args.key_exprs, args.duration, not args.no_liveliness,
                        args.compression, stop, progress, exclude=args.exclude, encoding=args.encoding)
    if tty:
        print(file=sys.stderr)
    print(format_counts(counts, args.output))
    if getattr(args, "json", False):
        print(json.dumps(counts))
    return 0
