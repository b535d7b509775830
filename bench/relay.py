"""A no-processing hop for the mesh benchmark's limit: receive on one stream, republish the same bytes on another.

``python -m bench.relay --from raw --to clean`` re-publishes ``magmesh/*/raw/**`` on ``magmesh/*/clean/**``
through the same FIFO-channel → queue → main-loop path as a service, minus decoding and processing.
"""

from __future__ import annotations

import argparse
import queue
import signal
import sys
import threading


def main(argv: list[str] | None = None) -> int:
    import zenoh

    from magmesh import zconf
    from schemas import keys

    p = argparse.ArgumentParser(description=__doc__)
    zconf.add_zenoh_args(p)
    p.add_argument("--from", dest="src", default="raw")
    p.add_argument("--to", dest="dst", default="clean")
    p.add_argument("--instance", default="relay")
    args = p.parse_args(argv)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    signal.signal(signal.SIGINT, lambda *a: stop.set())
    q: queue.Queue = queue.Queue(maxsize=65536)
    with zenoh.open(zconf.config_from_args(args)) as s:
        sub = s.declare_subscriber(f"{keys.ROOT}/*/{args.src}/**", zenoh.handlers.FifoChannel(4096))
        token = s.liveliness().declare_token(keys.svc_token("relay", args.instance))

        def reader() -> None:
            while True:
                try:
                    smp = sub.recv()
                except Exception:
                    return
                q.put((str(smp.key_expr), smp.payload.to_bytes()))

        threading.Thread(target=reader, daemon=True).start()
        pubs: dict = {}
        opts = dict(congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)
        src, dst = f"/{args.src}/", f"/{args.dst}/"
        while not stop.is_set():
            try:
                key, payload = q.get(timeout=0.2)
            except queue.Empty:
                continue
            out = pubs.get(key)
            if out is None:
                out = pubs[key] = s.declare_publisher(key.replace(src, dst, 1), **opts)
            out.put(payload)
        token.undeclare()
    return 0


if __name__ == "__main__":
    sys.exit(main())
