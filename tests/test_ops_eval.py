"""eval ops: the codec measurement in the default suite; the loopback round trip under -m slow."""

from __future__ import annotations

import argparse
import math

import pytest

from bench import eval_ops


def _args(**kw):
    p = argparse.ArgumentParser()
    eval_ops.add_arguments(p)
    a = p.parse_args([])
    for k, v in kw.items():
        setattr(a, k, v)
    return a


def test_codec_measurement_is_plain_and_sane():
    r = eval_ops.run(_args(no_mesh=True, codec_n=2000))
    c = r["codec"]
    assert set(r) == {"codec"}
    # every message written is read back and decodes (the rates are measurements for the bench, not checks)
    assert c["messages"] == c["read_back"] == c["decoded"] == 2000
    for k in ("write_msgs_per_s", "read_msgs_per_s", "read_decode_msgs_per_s"):
        assert math.isfinite(c[k]) and c[k] > 0, (k, c[k])
    # zstd chunks make the file smaller than the raw payloads
    assert c["bytes_per_message"] < c["payload_bytes_per_message"]
    assert "msg/s" in eval_ops.format_text(r)


@pytest.mark.slow
@pytest.mark.mesh
def test_round_trip_loses_nothing_and_keeps_timing():
    r = eval_ops.run(_args(seconds=5.0, burst=10000, codec_n=5000))
    t, b = r["timing"], r["burst"]
    assert t["lost"] == 0 and t["received"] == t["messages"]
    assert t["error_ms_p50"] < 5.0 and t["error_ms_p99"] < 30.0
    assert b["lost"] == 0 and b["msgs_per_s"] > 2000
