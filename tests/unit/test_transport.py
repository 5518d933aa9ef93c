"""common/delivery/transport.py: the bounded inbox and its overflow policies, reaching (or not) a router, and a session
open that gives up on time or on a stop request instead of hanging."""

from __future__ import annotations

import socket
import threading
import time

import pytest
from khgrl.common.delivery.transport import Inbox, endpoint_host_port, free_port, open_client, wait_reachable


def _fill(inbox: Inbox, n: int) -> list[int]:
    for i in range(n):
        inbox.put(("frame", "k", i, 0.0))
    out = []
    while (item := inbox.get()) is not None:
        out.append(item[2])
    return out


def test_drop_oldest_keeps_the_newest_and_counts_what_it_dropped():
    inbox = Inbox(maxsize=3, overflow="drop_oldest")
    assert _fill(inbox, 5) == [2, 3, 4]
    assert inbox.dropped == {"frame": 2}


def test_drop_newest_keeps_what_came_first():
    inbox = Inbox(maxsize=3, overflow="drop_newest")
    assert _fill(inbox, 5) == [0, 1, 2]
    assert inbox.dropped == {"frame": 2}


def test_an_unknown_overflow_policy_is_refused():
    with pytest.raises(ValueError, match="overflow policy"):
        Inbox(overflow="block")


def test_get_waits_at_most_its_timeout():
    inbox = Inbox()
    t0 = time.monotonic()
    assert inbox.get(0.2) is None
    assert 0.15 < time.monotonic() - t0 < 2.0


def test_endpoints_are_parsed():
    assert endpoint_host_port("tcp/127.0.0.1:7447") == ("127.0.0.1", 7447)
    assert endpoint_host_port("tls/[::1]:7448") == ("::1", 7448)
    assert endpoint_host_port("udp/127.0.0.1:7447") is None
    assert endpoint_host_port("tcp/host-without-port") is None


def test_wait_reachable_names_the_endpoint_after_its_timeout():
    ep = f"tcp/127.0.0.1:{free_port()}"  # nothing listens there
    t0 = time.monotonic()
    with pytest.raises(ConnectionError, match=ep.replace(".", r"\.")):
        wait_reachable(ep, 1.0)
    assert time.monotonic() - t0 < 5.0


def test_wait_reachable_returns_once_something_listens_and_stops_on_request():
    with socket.socket() as srv:
        srv.bind(("127.0.0.1", 0))
        srv.listen()
        wait_reachable(f"tcp/127.0.0.1:{srv.getsockname()[1]}", 5.0)
    stop = threading.Event()
    threading.Timer(0.3, stop.set).start()
    t0 = time.monotonic()
    with pytest.raises(ConnectionError, match="stopped"):
        wait_reachable(f"tcp/127.0.0.1:{free_port()}", 60.0, stop=stop.is_set)
    assert time.monotonic() - t0 < 5.0


def test_opening_a_session_to_no_router_gives_up_on_time_and_on_stop():
    ep = f"tcp/127.0.0.1:{free_port()}"
    t0 = time.monotonic()
    with pytest.raises(ConnectionError, match=f"no connection to the Zenoh router at {ep} within 1 s"):
        open_client(ep, timeout=1.0)
    assert time.monotonic() - t0 < 5.0
    stop = threading.Event()
    threading.Timer(0.3, stop.set).start()
    with pytest.raises(ConnectionError, match="stopped"):
        open_client(ep, stop=stop.is_set)


@pytest.mark.parametrize("policy", ["drop_oldest", "drop_newest"])
def test_a_byte_bound_keeps_the_waiting_payload_bytes_under_it(policy):
    inbox = Inbox(maxsize=1000, overflow=policy, max_bytes=10_000)
    for i in range(50):
        inbox.put(("transitions", "k", bytes([i]) * 1000, 0.0))
        assert inbox.bytes <= 10_000
    inbox.put(("alive", "k", True, 0.0))  # not a payload: not counted
    got = [item[2][0] for item in iter(inbox.get, None) if item[0] == "transitions"]
    assert got == (list(range(40, 50)) if policy == "drop_oldest" else list(range(10)))
    assert inbox.dropped["transitions"] == 40 and inbox.bytes == 0
