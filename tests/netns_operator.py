"""An operator's alarm watcher for the multi-host test, run inside the operators' network namespace.

It subscribes to ``magmesh/*/alarm/**`` with an AdvancedSubscriber (history for a late joiner, heartbeat miss
detection), recovers any transition missed in transit from the publishers' caches (a query of
``.../@adv/pub/**``) as soon as a miss is reported and once a second, counts clean samples arriving from the
vehicles' host, and at the end asks the services how many transitions they published and which alarms they
hold raised. Everything goes to ``--out`` as JSON lines.

    python tests/netns_operator.py --connect tcp/10.231.0.3:7447 --out events.jsonl --duration 40
"""

from __future__ import annotations

import argparse
import json
import queue
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import msgpack  # noqa: E402

from magmesh import zconf  # noqa: E402
from schemas import keys  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser()
    zconf.add_zenoh_args(p)
    p.add_argument("--out", required=True)
    p.add_argument("--duration", type=float, default=40.0)
    p.add_argument("--stop-file", default=None, help="stop early when this file appears")
    args = p.parse_args()

    import zenoh
    from zenoh import ext

    out = open(args.out, "a", buffering=1)

    def emit(**kw) -> None:
        out.write(json.dumps({"t": round(time.time(), 3), **kw}) + "\n")

    q: queue.Queue = queue.Queue()
    seen: dict[str, set[int]] = {}
    with zenoh.open(zconf.config_from_args(args)) as session:
        sub = ext.declare_advanced_subscriber(
            session, keys.alarms_all(), lambda s: q.put(("s", str(s.key_expr), s.payload.to_bytes())),
            history=ext.HistoryConfig(detect_late_publishers=True),
            recovery=ext.RecoveryConfig(heartbeat=True), subscriber_detection=True)
        sub.sample_miss_listener(lambda m: q.put(("miss", str(m.source), m.nb)))
        n_clean = [0]
        clean = session.declare_subscriber(keys.clean_all(), lambda s: n_clean.__setitem__(0, n_clean[0] + 1))
        emit(kind="ready")

        def take(key: str, payload: bytes, how: str) -> None:
            m = msgpack.unpackb(payload)
            s = seen.setdefault(key, set())
            if m["seq"] not in s:
                s.add(m["seq"])
                emit(kind="alarm", how=how, key=key, seq=m["seq"], state=m["state"], t_s=m["t_s"])

        def recover() -> None:
            for rep in session.get(f"{keys.alarms_all()}/@adv/pub/**", timeout=2.0,
                                   consolidation=zenoh.ConsolidationMode.NONE, accept_replies=zenoh.ReplyKeyExpr.ANY):
                if rep.ok is not None:
                    take(str(rep.ok.key_expr), rep.ok.payload.to_bytes(), "recovered")

        deadline = time.monotonic() + args.duration
        next_recover = time.monotonic() + 1.0
        last_clean = 0
        while time.monotonic() < deadline:
            if args.stop_file and Path(args.stop_file).exists():
                break
            try:
                ev = q.get(timeout=0.2)
            except queue.Empty:
                ev = None
            if ev is not None and ev[0] == "s":
                take(ev[1], ev[2], "live")
            elif ev is not None and ev[0] == "miss":
                emit(kind="miss", source=ev[1], nb=ev[2])
                recover()
            if time.monotonic() >= next_recover:
                next_recover = time.monotonic() + 1.0
                recover()
                if n_clean[0] != last_clean:
                    emit(kind="clean", n=n_clean[0])
                    last_clean = n_clean[0]
        recover()
        for rep in session.get(keys.svc_status_all(), timeout=3.0):
            if rep.ok is not None:
                st = msgpack.unpackb(rep.ok.payload.to_bytes())
                emit(kind="status", role=st.get("role"), instance=st.get("instance"),
                     transitions=st.get("transitions"), seqs={k: v for k, v in st.get("out", {}).items()})
        for rep in session.get(keys.alarms_all(), timeout=3.0):
            if rep.ok is not None:
                m = msgpack.unpackb(rep.ok.payload.to_bytes())
                emit(kind="current", key=str(rep.ok.key_expr), seq=m["seq"], state=m["state"])
        emit(kind="done", clean=n_clean[0])
        clean.undeclare()
        sub.undeclare()


if __name__ == "__main__":
    main()
