"""Oversize messages over a real router: Zenoh drops a message larger than ``MAX_MESSAGE_BYTES`` at the link
(it is never delivered), and an Inbox drops a payload over its kind's limit before copying it out of Zenoh; the
receiver keeps receiving."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time

import pytest
from khgrl.common.delivery.transport import MAX_MESSAGE_BYTES, Inbox, open_client

from helpers import REPO, ProcGroup, wait_for

pytestmark = pytest.mark.integration

PUBLISHER = textwrap.dedent("""
    import sys, time
    from khgrl.common.delivery.transport import open_client
    endpoint, key, sizes = sys.argv[1], sys.argv[2], [int(s) for s in sys.argv[3:]]
    with open_client(endpoint, timeout=20) as s:
        import zenoh
        pub = s.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        time.sleep(0.5)
        for n in sizes:
            pub.put(bytes([n % 251]) * n)
            time.sleep(0.2)
        time.sleep(1.0)
""")


def _publish(endpoint: str, key: str, *sizes: int) -> None:
    subprocess.run([sys.executable, "-c", PUBLISHER, endpoint, key, *map(str, sizes)], cwd=REPO, check=True,
                   timeout=120, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})


def test_a_message_over_the_limit_never_reaches_a_receiver_and_an_inbox_limit_drops_before_copying(tmp_path):
    with ProcGroup(tmp_path) as g:
        ep = g.router()
        inbox = Inbox()
        sizes: list[int] = []  # what Zenoh delivers at all (a plain callback, no Inbox limit)
        with open_client(ep, timeout=20) as s:
            subs = [s.declare_subscriber("t/big", lambda sample: sizes.append(len(sample.payload))),
                    s.declare_subscriber("t/limited", inbox.callback("limited", max_bytes=1000))]
            _publish(ep, "t/big", 100 * 1024 * 1024, 1000, MAX_MESSAGE_BYTES + 1, 2000)
            wait_for(lambda: len(sizes) >= 2, 30, "the small messages")
            time.sleep(1.0)
            assert sorted(sizes) == [1000, 2000]  # Zenoh dropped both messages over MAX_MESSAGE_BYTES
            _publish(ep, "t/limited", 500, 5000, 800)
            wait_for(lambda: inbox.oversize.get("limited") == 1 and inbox.qsize() == 2, 30, "the limited kind")
            assert sorted(len(inbox.get()[2]) for _ in range(2)) == [500, 800]
            for sub in subs:
                sub.undeclare()
