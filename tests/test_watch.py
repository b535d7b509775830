"""Per-vehicle output rows are put only while a subscriber matches their key (magmesh/runtime.py ``_Watch``): the
rows of an unwatched key are still numbered and journaled, counted in ``out_unwatched``, and a subscriber that
comes receives the key's seq where it stands. With a test double (no matching support), with Zenoh's own
matching status through a router, and a publisher's first second (its status not known yet) put whatever."""

import time

import msgpack
from meshutil import free_port, open_client, open_router
from test_frames_runtime import _dmc_cols as _cols

from magmesh import runtime
from magmesh.runtime import Runner, Service, _Watch
from schemas import keys


class _Status:
    def __init__(self, matching):
        self.matching = matching


class _Pub:
    """A publisher with Zenoh's matching interface: ``matching`` set by the test, listeners called on change."""

    def __init__(self, sess, key):
        self.sess, self.key, self.listeners = sess, key, []

    def put(self, payload):
        self.sess.out.append((self.key, payload))

    @property
    def matching_status(self):
        return _Status(self.sess.watched)

    def declare_matching_listener(self, cb):
        self.listeners.append(cb)
        return self


class _Session:
    def __init__(self):
        self.out, self.pubs, self.watched = [], [], False

    def declare_publisher(self, key, **kw):
        p = _Pub(self, key)
        self.pubs.append(p)
        return p

    def watch(self, on):
        self.watched = on
        for p in self.pubs:
            for cb in p.listeners:
                cb(_Status(on))


class _Svc(Service):
    role = "watch_test"
    impl = "t"


def _rows(r, t0, n=2):
    veh = ["car-1", "car-2"][:n]
    return r.publish_rows("dmc", [keys.dmc(v) for v in veh], veh, [t0] * n, _cols(n))


def test_unwatched_rows_numbered_not_put_and_a_new_subscriber_continues_the_seq(tmp_path, monkeypatch):
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(tmp_path))
    sess = _Session()
    r = Runner(_Svc(instance="w-1"), sess)
    r.resume_journal()
    monkeypatch.setattr(runtime, "WATCH_SETTLE_S", 0.05)
    assert _rows(r, 1.0) == [0, 0]  # a new publisher's first rows go out whatever its status says
    assert [k for k, _ in sess.out] == [keys.dmc("car-1"), keys.dmc("car-2")]
    time.sleep(0.06)
    assert _rows(r, 1.02) == [1, 1]  # settled: nobody matches, numbered and journaled, not put
    assert _rows(r, 1.04) == [2, 2]
    assert len(sess.out) == 2
    assert r.journal.load()["o" + keys.dmc("car-2")] == 2
    st = r.status()
    assert st["out_unwatched"] == {"dmc": 4}
    assert st["out"][keys.dmc("car-1")]["n"] == 3  # out counts every numbered row
    assert st["lost_total"] == 0
    sess.watch(True)  # a subscriber came: from the next row on, put, the seq where it stands
    assert _rows(r, 1.06) == [3, 3]
    got = [(k, msgpack.unpackb(p)) for k, p in sess.out[2:]]
    assert [(k, m["seq"], m["t_s"], m["dh_rad"]) for k, m in got] == [
        (keys.dmc("car-1"), 3, 1.06, 0.01), (keys.dmc("car-2"), 3, 1.06, 0.01)]
    sess.watch(False)
    assert _rows(r, 1.08) == [4, 4]
    assert len(sess.out) == 4 and r.status()["out_unwatched"] == {"dmc": 6}


def test_a_publisher_without_matching_support_is_always_put():
    class Plain:
        def put(self, payload):
            pass

    w = _Watch(Plain())
    w.settle()
    assert w.on


def test_zenoh_matching_through_a_router_drives_the_watch():
    port = free_port()
    router = open_router(port)
    a, b = open_client(port), open_client(port)
    try:
        pub = a.declare_publisher(keys.dmc("car-7"))
        w = _Watch(pub)
        assert w.on  # not settled: put
        time.sleep(0.3)
        w.settle()
        assert not w.on  # nobody subscribes
        sub = b.declare_subscriber(keys.dmc("*"), lambda s: None)
        deadline = time.monotonic() + 3.0
        while not w.on and time.monotonic() < deadline:
            time.sleep(0.01)
        assert w.on  # the listener saw the subscriber
        sub.undeclare()
        deadline = time.monotonic() + 3.0
        while w.on and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not w.on
        w.close()
    finally:
        for s in (a, b, router):
            s.close()
