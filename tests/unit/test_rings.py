"""khgrl.common.delivery.transport.Rings with real Zenoh sessions on loopback: a flood leaves only the newest
``capacity`` samples
(nothing runs per sample in Python), polling takes keys in turn and is bounded, oversize payloads are skipped and
counted."""

from __future__ import annotations

import time

import pytest
from khgrl.common.delivery.transport import Rings, free_port, open_client, open_router


@pytest.fixture(scope="module")
def sessions():
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(ep)
    a, b = open_client(ep, timeout=10), open_client(ep, timeout=10)
    yield a, b
    for s in (a, b, router):
        s.close()


def _settle(rings: Rings, n: int, timeout: float = 5.0) -> None:
    """Wait until the rings' subscribers are known to the router (a first sample on each arrives)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        time.sleep(0.1)
        if len(rings.poll(1000)) >= n:
            return


def test_a_flood_keeps_the_newest_and_polling_is_bounded_and_fair(sessions):
    pub, sub = sessions
    rings = Rings(sub)
    rings.add("flood", "t/rings/flood", capacity=8)
    rings.add("quiet", "t/rings/quiet", capacity=8)
    time.sleep(0.5)
    pub.put("t/rings/flood", b"warm")
    pub.put("t/rings/quiet", b"warm")
    _settle(rings, 2)
    for i in range(5000):
        pub.put("t/rings/flood", str(i).encode())
    pub.put("t/rings/quiet", b"q0")
    pub.put("t/rings/quiet", b"q1")
    time.sleep(1.0)
    first = rings.poll(3)
    assert len(first) == 3
    assert [k for k, *_ in first[:2]] == ["flood", "quiet"]  # one from each key in turn
    rest = rings.poll(1000)
    flood = [p for k, _, p, _ in first + rest if k == "flood"]
    quiet = [p for k, _, p, _ in first + rest if k == "quiet"]
    assert quiet == [b"q0", b"q1"]
    assert len(flood) == 8 and flood[-1] == b"4999"  # only the newest 8 of 5,000 were kept
    assert rings.poll(10) == []
    rings.undeclare()


def test_oversize_payloads_are_skipped_and_counted(sessions):
    pub, sub = sessions
    rings = Rings(sub)
    rings.add("small", "t/rings/small", capacity=16, max_bytes=100)
    time.sleep(0.5)
    pub.put("t/rings/small", b"x")
    _settle(rings, 1)
    pub.put("t/rings/small", b"y" * 101)
    pub.put("t/rings/small", b"z" * 100)
    time.sleep(0.5)
    got = rings.poll(10)
    assert [p for _, _, p, _ in got] == [b"z" * 100]
    assert rings.oversize == {"small": 1}
    rings.undeclare()
