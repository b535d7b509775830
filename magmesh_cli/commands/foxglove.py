"""``magmesh foxglove``: serve the live mesh to Foxglove (WebSocket, ``foxglove.websocket.v1``).

    magmesh foxglove                           # ws://127.0.0.1:8765, every magmesh key
    magmesh foxglove --port 9000 'magmesh/car-1/**' --connect tcp/10.0.0.2:7447

Open Foxglove, "Open connection" → "Foxglove WebSocket" → ws://127.0.0.1:8765 (and import the layout
deploy/foxglove/magmesh-layout.json for a one-vehicle view). Every magmesh key becomes a channel as it
first appears (json messages, a JSON Schema per message type); alarms also appear as foxglove.Log on
/<vehicle>/log, GNSS and accepted geomagnetic fixes as foxglove.LocationFix on /<vehicle>/gnss/fix and
/<vehicle>/geomag/fix, the fused attitude as foxglove.PoseInFrame on /<vehicle>/pose and
foxglove.FrameTransform on /tf. Alarms that are already raised when it starts are fetched first.

A slow viewer never slows the mesh: each client has a bounded backlog and drops its oldest messages
when full (counted, and the client is warned). Counts are printed every 10 s and at the end.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
import time
import tomllib
from collections import Counter
from pathlib import Path

import msgpack

from magmesh import zconf
from magmesh.paths import DEPLOY_DIR
from schemas import keys, messages

from ..foxglove_types import FOXGLOVE_SCHEMAS, FoxgloveConverter, magmesh_channel, to_json_bytes
from ..foxglove_ws import FoxgloveServer
from ..recording import matches_any
from ..tap import decode_samples, run_tap

log = logging.getLogger("magmesh.foxglove")


def register(subparsers) -> None:
    p = subparsers.add_parser("foxglove", help="serve the live mesh to Foxglove (WebSocket)", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("key_exprs", nargs="*", metavar="KEYEXPR",
                   help=f"key expressions to serve (default {keys.everything()}; give disjoint ones)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8765, help="WebSocket port (default 8765; 0: any free port)")
    p.add_argument("--manifest", default=None, metavar="FILE",
                   help="mesh manifest whose vehicles' lat_deg/lon_deg/alt_m place their local frames on the map "
                        "(default deploy/mesh.toml when it exists); GNSS-equipped vehicles need none")
    p.add_argument("--origin", action="append", default=[], metavar="VEHICLE=LAT,LON[,ALT]",
                   help="origin of a vehicle's local ENU frame (repeatable; overrides the manifest)")
    p.add_argument("--stamp", choices=["receive", "sample"], default="receive",
                   help="timestamps of the Foxglove-typed messages: receive time (default) or the sample time t_s")
    p.add_argument("--backlog", type=int, default=4096, help="messages buffered per client before dropping")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: until Ctrl-C)")
    p.add_argument("--quiet", "-q", action="store_true", help="no periodic count lines")
    zconf.add_zenoh_args(p)
    p.set_defaults(func=run)


class UsageError(Exception):
    """A person's mistake in the flags or files: one clear paragraph, exit 2."""


def parse_origins(manifest: str | None, origin_flags: list[str]) -> dict[str, tuple[float, float, float]]:
    out: dict[str, tuple[float, float, float]] = {}
    path = Path(manifest) if manifest else DEPLOY_DIR / "mesh.toml"
    if manifest or path.exists():
        try:
            doc = tomllib.loads(path.read_text())
        except FileNotFoundError:
            raise UsageError(f"manifest {path} does not exist") from None
        except tomllib.TOMLDecodeError as e:
            raise UsageError(f"manifest {path} is not valid TOML: {e}") from None
        for vid, v in (doc.get("vehicles") or {}).items():
            if isinstance(v, dict) and "lat_deg" in v and "lon_deg" in v:
                out[vid] = (float(v["lat_deg"]), float(v["lon_deg"]), float(v.get("alt_m", 0.0)))
    for item in origin_flags:
        vid, sep, rest = item.partition("=")
        try:
            nums = [float(x) for x in rest.split(",")]
            if not sep or len(nums) not in (2, 3):
                raise ValueError
            keys.check_id(vid)
        except (ValueError, keys.KeyError_):
            raise UsageError(f"--origin {item!r} must be VEHICLE=LAT,LON or VEHICLE=LAT,LON,ALT "
                             "(degrees, metres), e.g. --origin survey-1=45.4,-75.7,300") from None
        if not (-90 <= nums[0] <= 90 and -180 <= nums[1] <= 180):
            raise UsageError(f"--origin {item!r}: latitude must be in [-90, 90] and longitude in [-180, 180]")
        out[vid] = (nums[0], nums[1], nums[2] if len(nums) == 3 else 0.0)
    return out


class FoxgloveBridge:
    """Mesh samples → Foxglove channels (the glue between :mod:`magmesh_cli.tap` and the server)."""

    def __init__(self, server: FoxgloveServer, converter: FoxgloveConverter):
        self.server = server
        self.conv = converter
        self.channels: dict[str, int] = {}
        self.counts: Counter = Counter()

    def _channel(self, topic: str, schema_name: str, schema: dict) -> int:
        cid = self.channels.get(topic)
        if cid is None:
            cid = self.channels[topic] = self.server.add_channel(topic, schema_name, json.dumps(schema))
        return cid

    def on_sample(self, key: str, payload: bytes, receive_ns: int) -> None:
        try:
            info = keys.parse(key)
        except keys.KeyError_:
            self.counts["not a magmesh key"] += 1
            return
        if info.kind == "svc":
            try:
                msg = msgpack.unpackb(payload, raw=False)
            except Exception:
                msg = None
            if not isinstance(msg, dict):
                self.counts["undecodable"] += 1
                return
            name, schema = magmesh_channel(key)
            self.server.send(self._channel(key, name, schema), receive_ns, to_json_bytes(msg))
            self.counts["forwarded"] += 1
            return
        try:
            samples = decode_samples(key, payload)
        except (messages.SchemaError, keys.KeyError_, KeyError):
            # raw/ keys may carry anything a sensor sends; ingest reports the refusal on rejects
            self.counts["undecodable"] += 1
            return
        for skey, msg in samples:  # a batch is shown as its samples, each on its stream's key
            name, schema = magmesh_channel(skey)
            self.server.send(self._channel(skey, name, schema), receive_ns, to_json_bytes(msg))
            self.counts["forwarded"] += 1
            for out in self.conv.convert(skey, msg, receive_ns):
                cid = self._channel(out.topic, out.schema, FOXGLOVE_SCHEMAS[out.schema])
                self.server.send(cid, receive_ns, to_json_bytes(out.msg))
                self.counts[out.schema] += 1


def _raised_alarms(session, exprs: list[str]) -> list[tuple[str, bytes]]:
    """Alarms currently raised (services answer queries on their alarm keys), for a late joiner."""
    out = []
    try:
        for rep in session.get(keys.alarms_all(), timeout=2.0, priority=zconf.control_priority()):
            if rep.ok is not None:
                k = str(rep.ok.key_expr)
                if matches_any(exprs, k):
                    out.append((k, rep.ok.payload.to_bytes()))
    except Exception as e:  # no queryable or a timeout is not an error for a viewer
        log.debug("alarm query: %s", e)
    return out


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("websockets").setLevel(logging.WARNING)
    try:
        origins = parse_origins(args.manifest, args.origin)
        if not (0 <= args.port <= 65535):
            raise UsageError(f"--port {args.port} is not a TCP port (0-65535)")
        if args.backlog < 1:
            raise UsageError("--backlog must be at least 1")
        exprs = list(args.key_exprs) or [keys.everything()]
        for e in exprs:
            if not e.startswith(keys.ROOT + "/"):
                raise UsageError(f"key expression {e!r} is outside magmesh ({keys.ROOT}/...)")
        conf = zconf.config_from_args(args)
    except (UsageError, ValueError) as e:
        print(f"magmesh foxglove: {e}", file=sys.stderr)
        return 2
    import zenoh

    server = FoxgloveServer(args.host, args.port, name="magmesh", backlog=args.backlog)
    try:
        server.start()
    except OSError as e:
        print(f"magmesh foxglove: cannot listen on {args.host}:{args.port} ({e.strerror or e}); "
              "is another server using the port? Choose one with --port.", file=sys.stderr)
        return 2
    bridge = FoxgloveBridge(server, FoxgloveConverter(origins=origins, stamp=args.stamp))
    print(f"serving Foxglove on ws://{args.host}:{server.port} (subprotocol foxglove.websocket.v1)", flush=True)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    last = [time.monotonic()]

    def tick() -> None:
        if not args.quiet and time.monotonic() - last[0] >= 10.0:
            last[0] = time.monotonic()
            print(_summary(bridge, server), flush=True)

    where = ", ".join(args.connect or []) or (args.config or zconf.default_endpoint())
    print(f"connecting to the mesh at {where} (waiting for its router if it is not up yet)", flush=True)
    try:
        with zenoh.open(conf) as session:
            for k, payload in _raised_alarms(session, exprs):
                bridge.on_sample(k, payload, time.time_ns())
            counts = run_tap(session, exprs, bridge.on_sample, stop, args.duration, on_tick=tick)
    finally:
        server.stop()
    bridge.counts.update({f"mesh {k}": v for k, v in counts.items()})
    print(_summary(bridge, server), flush=True)
    return 0


def _summary(bridge: FoxgloveBridge, server: FoxgloveServer) -> str:
    s = server.stats()
    c = bridge.counts
    extra = "".join(f", {k}: {v}" for k, v in sorted(bridge.conv.skipped.items()))
    return (f"foxglove: {c['forwarded']} magmesh messages on {s['channels']} channels, "
            f"{s['sent']} frames sent to {s['clients']} client(s), {s['dropped_slow_client']} dropped for slow "
            f"clients, {s['dropped_server_behind']} dropped with the server behind, {c['undecodable']} undecodable, {c['not a magmesh key']} outside the key contract{extra}")

