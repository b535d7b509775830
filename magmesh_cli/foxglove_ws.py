"""A Foxglove WebSocket server (subprotocol ``foxglove.websocket.v1``) for live data, on ``websockets``.

The protocol (https://github.com/foxglove/ws-protocol): the server sends ``serverInfo`` and ``advertise``
(JSON text frames) listing its channels with their schemas; a client sends ``subscribe`` /
``unsubscribe``; the server sends each message of a subscribed channel as a binary frame
``0x01 | uint32 subscription id | uint64 log time ns | payload`` (little endian). New channels are
advertised to every connected client as they appear.

Why not foxglove-sdk's server: its WebSocket server (0.30) only accepts the ``foxglove.sdk.v1``
subprotocol and refuses ``foxglove.websocket.v1`` clients with HTTP 400; this one speaks
``foxglove.websocket.v1``, which Foxglove, Lichtblick and the ws-protocol client libraries all use.

Thread model: the server runs its own asyncio loop on a thread; :meth:`FoxgloveServer.add_channel` and
:meth:`FoxgloveServer.send` are called from any thread. A viewer must never slow the mesh down: each
client has a bounded queue (``backlog`` messages); when a slow client's queue is full its oldest message
is dropped and counted (``stats()["dropped_slow_client"]``) and the client is told once per second with a
``status`` warning; if the server's own loop falls behind the mesh, the oldest undispatched messages are
dropped and counted too (``stats()["dropped_server_behind"]``). A new subscription gets the channel's latest message at once (as a latched topic):
the first message of a channel that appears while a client is connected is sent before the client can
subscribe to it, and an alarm must not be missed that way.
"""

from __future__ import annotations

import asyncio
import json
import logging
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass, field

SUBPROTOCOL = "foxglove.websocket.v1"
OP_MESSAGE_DATA = 0x01
STATUS_INFO, STATUS_WARNING, STATUS_ERROR = 0, 1, 2

log = logging.getLogger("magmesh.foxglove")


@dataclass(frozen=True)
class ChannelInfo:
    id: int
    topic: str
    encoding: str
    schema_name: str
    schema: str
    schema_encoding: str = "jsonschema"

    def advert(self) -> dict:
        return {"id": self.id, "topic": self.topic, "encoding": self.encoding, "schemaName": self.schema_name,
                "schema": self.schema, "schemaEncoding": self.schema_encoding}


@dataclass(eq=False)
class _Client:
    ws: object
    subs: dict[int, int] = field(default_factory=dict)  # channel id → subscription id
    queue: deque = field(default_factory=deque)
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    dropped: int = 0
    last_warned: float = 0.0


class FoxgloveServer:
    """Serve channels to Foxglove clients; start with :meth:`start`, stop with :meth:`stop`."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, name: str = "magmesh", backlog: int = 4096):
        self.host, self.port, self.name, self.backlog = host, port, name, int(backlog)
        self._channels: dict[int, ChannelInfo] = {}
        self._lock = threading.Lock()
        self._next_id = 1
        self._clients: set[_Client] = set()
        self._last: dict[int, tuple[int, bytes]] = {}  # channel → its latest message, for new subscribers
        # messages handed over by send() and not yet dispatched by the loop (bounded: the loop may fall behind)
        self._inbox: deque = deque()
        self._inbox_lock = threading.Lock()
        self._drain_scheduled = False
        self.inbox_max = 16 * int(backlog)
        self.dropped_server = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._started = threading.Event()
        self._stop: asyncio.Event | None = None
        self._error: BaseException | None = None
        self.sent = 0
        self.dropped = 0
        self.clients_seen = 0
        self._session_id = str(time.time_ns())

    # ---- control -------------------------------------------------------------------------------

    def start(self, timeout_s: float = 10.0) -> FoxgloveServer:
        self._thread = threading.Thread(target=self._run, name="foxglove-ws", daemon=True)
        self._thread.start()
        if not self._started.wait(timeout_s):
            raise RuntimeError(f"the Foxglove server did not start on {self.host}:{self.port} in {timeout_s:g} s")
        if self._error is not None:
            raise self._error
        return self

    def stop(self) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        if self._thread is not None:
            self._thread.join(timeout=10)

    def stats(self) -> dict:
        return {"channels": len(self._channels), "clients": len(self._clients), "clients_seen": self.clients_seen,
                "sent": self.sent, "dropped_slow_client": self.dropped, "dropped_server_behind": self.dropped_server}

    # ---- channels and data (any thread) --------------------------------------------------------

    def add_channel(self, topic: str, schema_name: str, schema: str, encoding: str = "json",
                    schema_encoding: str = "jsonschema") -> int:
        with self._lock:
            cid = self._next_id
            self._next_id += 1
            ch = ChannelInfo(cid, topic, encoding, schema_name, schema, schema_encoding)
            self._channels[cid] = ch
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._advertise, [ch])
        return cid

    def send(self, channel_id: int, log_time_ns: int, payload: bytes) -> None:
        if self._loop is None:
            return
        with self._inbox_lock:
            if len(self._inbox) >= self.inbox_max:
                self._inbox.popleft()
                self.dropped_server += 1
            self._inbox.append((channel_id, int(log_time_ns), payload))
            if self._drain_scheduled:
                return
            self._drain_scheduled = True
        self._loop.call_soon_threadsafe(self._drain)

    def _drain(self) -> None:
        with self._inbox_lock:
            items = list(self._inbox)
            self._inbox.clear()
            self._drain_scheduled = False
        for item in items:
            self._dispatch(*item)

    # ---- loop side -----------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as e:  # reported to start() or logged
            self._error = e
            self._started.set()

    async def _main(self) -> None:
        from websockets.asyncio.server import serve

        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        async with serve(self._handler, self.host, self.port, subprotocols=[SUBPROTOCOL],
                         max_size=1 << 20, compression=None) as server:
            if self.port == 0:
                self.port = next(iter(server.sockets)).getsockname()[1]
            self._started.set()
            await self._stop.wait()

    def _advertise(self, chans: list[ChannelInfo]) -> None:
        text = json.dumps({"op": "advertise", "channels": [c.advert() for c in chans]})
        for c in list(self._clients):
            self._enqueue(c, text)

    def _enqueue(self, c: _Client, frame: str | bytes, droppable: bool = False) -> None:
        if droppable and len(c.queue) >= self.backlog:
            # drop the oldest data frame (control frames are kept)
            for i, f in enumerate(c.queue):
                if isinstance(f, bytes):
                    del c.queue[i]
                    break
            c.dropped += 1
            self.dropped += 1
            now = time.monotonic()
            if now - c.last_warned >= 1.0:
                c.last_warned = now
                c.queue.append(json.dumps({"op": "status", "level": STATUS_WARNING,
                                           "message": f"client too slow: {c.dropped} messages dropped so far"}))
        c.queue.append(frame)
        c.wake.set()

    def _dispatch(self, channel_id: int, log_time_ns: int, payload: bytes) -> None:
        self._last[channel_id] = (log_time_ns, payload)
        for c in self._clients:
            sub = c.subs.get(channel_id)
            if sub is None:
                continue
            header = struct.pack("<BIQ", OP_MESSAGE_DATA, sub, log_time_ns)
            self._enqueue(c, header + payload, droppable=True)

    async def _writer(self, c: _Client) -> None:
        while True:
            await c.wake.wait()
            c.wake.clear()
            while c.queue:
                frame = c.queue.popleft()
                await c.ws.send(frame)
                if isinstance(frame, bytes):
                    self.sent += 1

    async def _handler(self, ws) -> None:
        if ws.subprotocol != SUBPROTOCOL:
            await ws.close(1002, f"subprotocol {SUBPROTOCOL} required")
            return
        c = _Client(ws)
        self.clients_seen += 1
        self._clients.add(c)
        with self._lock:
            chans = list(self._channels.values())
        self._enqueue(c, json.dumps({"op": "serverInfo", "name": self.name, "capabilities": [],
                                     "supportedEncodings": [], "metadata": {"library": "magmesh"},
                                     "sessionId": self._session_id}))
        if chans:
            self._enqueue(c, json.dumps({"op": "advertise", "channels": [ch.advert() for ch in chans]}))
        writer = asyncio.create_task(self._writer(c))
        try:
            async for raw in ws:
                self._on_client_message(c, raw)
        except Exception as e:  # a client that goes away mid-frame is normal
            log.debug("client %s: %s", ws.remote_address, e)
        finally:
            self._clients.discard(c)
            writer.cancel()

    def _on_client_message(self, c: _Client, raw) -> None:
        def status(level: int, text: str) -> None:
            self._enqueue(c, json.dumps({"op": "status", "level": level, "message": text}))

        if isinstance(raw, bytes):
            status(STATUS_WARNING, "binary client messages are not supported (no clientPublish capability)")
            return
        try:
            m = json.loads(raw)
            op = m["op"]
        except (ValueError, KeyError, TypeError):
            status(STATUS_ERROR, f"not a foxglove.websocket.v1 message: {str(raw)[:80]!r}")
            return
        if op == "subscribe":
            for s in m.get("subscriptions", []):
                try:
                    sid, cid = int(s["id"]), int(s["channelId"])
                except (KeyError, TypeError, ValueError):
                    status(STATUS_ERROR, f"bad subscription {s!r}")
                    continue
                if cid not in self._channels:
                    status(STATUS_WARNING, f"no channel {cid}")
                    continue
                c.subs[cid] = sid
                last = self._last.get(cid)
                if last is not None:  # the latest state at once (a new channel's first message comes before
                    # any client could subscribe to it: an alarm must not be missed that way)
                    self._enqueue(c, struct.pack("<BIQ", OP_MESSAGE_DATA, sid, last[0]) + last[1], droppable=True)
        elif op == "unsubscribe":
            gone = {int(x) for x in m.get("subscriptionIds", []) if isinstance(x, int)}
            c.subs = {cid: sid for cid, sid in c.subs.items() if sid not in gone}
        else:
            status(STATUS_WARNING, f"operation {op!r} is not supported by this server")
