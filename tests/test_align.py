"""The time aligner: joins by sample time, bounded wall-clock wait, every give-up counted."""

import numpy as np
import pytest

from magmesh.align import CoverWait, TimeAligner
from services.dmc_detector.core import Pairer


class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_two_streams_join_within_tolerance_whatever_the_arrival_order():
    a = TimeAligner(("1", "2"), tolerance_s=0.005, clock=_Clock())
    assert a.push("2", 0.001, "b0") == ([], [])
    joined, gave = a.push("1", 0.0, "a0")
    assert gave == [] and len(joined) == 1
    assert joined[0].t_s == 0.0 and joined[0].values == {"1": "a0", "2": "b0"}  # reference stream's time
    joined, gave = a.push("1", 0.02, "a1")
    assert joined == [] and a.waiting == 1


def test_a_sample_whose_partner_stream_moved_past_is_given_up_and_counted():
    a = TimeAligner(("1", "2"), tolerance_s=0.005, clock=_Clock())
    a.push("1", 0.00, "a0")
    a.push("1", 0.02, "a1")
    joined, gave = a.push("2", 0.02, "b1")  # sensor 2 never sent t = 0
    assert [j.t_s for j in joined] == [0.02]
    assert [(g.stream, g.t_s, g.reason) for g in gave] == [("1", 0.0, "passed")]
    assert a.counts()["gave_up"] == {"passed": {"1": 1}} and a.counts()["joined"] == 1


def test_the_wait_is_wall_clock_time_not_sample_time():
    clk = _Clock()
    a = TimeAligner(("mag", "dmc"), tolerance_s=1e-6, max_wait_s=0.5, clock=clk)
    for i in range(100):  # 100 s of sample time arriving within 0.1 s of wall time: nothing expires
        clk.t = i * 0.001
        a.push("mag", float(i), i)
    assert a.waiting == 100 and a.counts()["gave_up_total"] == 0
    clk.t = 0.55
    gave = a.expire()
    assert [g.value for g in gave] == list(range(0, 51))  # those that arrived 0.5 s of wall time ago or more
    assert all(g.reason == "expired" for g in gave)
    clk.t = 10.0
    assert len(a.expire()) == 49 and a.waiting == 0
    assert a.counts()["gave_up"]["expired"] == {"mag": 100}


def test_overflow_is_bounded_and_counted():
    a = TimeAligner(("1", "2"), tolerance_s=0.005, max_pending=3, clock=_Clock())
    gave = [g for i in range(5) for g in a.push("1", i * 0.02, i)[1]]
    assert [(g.value, g.reason) for g in gave] == [(0, "overflow"), (1, "overflow")] and a.waiting == 3


def test_three_streams():
    a = TimeAligner(("a", "b", "c"), tolerance_s=0.01, clock=_Clock())
    a.push("a", 1.0, 1)
    a.push("c", 1.005, 3)
    joined, _ = a.push("b", 0.995, 2)
    assert len(joined) == 1 and joined[0].values == {"a": 1, "b": 2, "c": 3}


@pytest.mark.parametrize("seed", range(6))
def test_aligner_pairs_exactly_as_the_dmc_pairer(seed):
    rng = np.random.default_rng(seed)
    n = 400
    t = np.arange(n) * 0.02
    events = []
    for s in ("1", "2"):
        keep = rng.random(n) > 0.1  # each compass loses a tenth of its samples
        jitter = rng.uniform(-0.003, 0.003, n) if s == "2" else np.zeros(n)
        events += [(s, float(t[i] + jitter[i]), i) for i in range(n) if keep[i]]
    # two subscriptions: each stream in order, the streams interleaved at random with lags
    by = {s: [e for e in events if e[0] == s] for s in ("1", "2")}
    order = []
    while by["1"] or by["2"]:
        s = rng.choice([k for k in by if by[k]])
        order.append(by[s].pop(0))
    p = Pairer(("1", "2"), 0.005)
    al = TimeAligner(("1", "2"), 0.005, max_wait_s=1e9, clock=_Clock())
    want, got = [], []
    dropped_p = 0
    for s, ts, i in order:
        pairs, d = p.push(s, ts, [i, 0, 0])
        dropped_p += d
        want += [(tp, int(a[0]), int(b[0])) for tp, a, b in pairs]
        joined, gave = al.push(s, ts, i)
        got += [(j.t_s, j.values["1"], j.values["2"]) for j in joined]
    assert got == want and len(got) > 300
    # every sample not joined is either given up (counted) or still waiting, in both
    passed = sum(al.counts()["gave_up"]["passed"].values())
    assert passed > 0 and passed + al.waiting == dropped_p + sum(len(q) for q in p.pending.values())


def test_cover_wait_releases_when_the_other_stream_reaches_the_time():
    clk = _Clock()
    w = CoverWait(max_wait_s=2.0, stream="field", clock=clk)
    assert w.push(1.0, "f1") == ([], [])
    assert w.push(2.0, "f2") == ([], [])
    rel, gave = w.advance(1.5)
    assert rel == [(1.0, "f1")] and gave == []
    clk.t = 3.0  # the INS went silent: f2 waited 3 s of wall time
    rel, gave = w.advance(1.6)
    assert rel == [] and [(g.value, g.reason) for g in gave] == [("f2", "expired")]
    rel, _ = w.push(1.55, "f3")  # already covered: released at once
    assert rel == [(1.55, "f3")] and w.counts()["joined"] == 2
    assert w.counts()["gave_up"] == {"expired": {"field": 1}}
