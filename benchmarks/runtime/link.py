"""This process as a stand-in actor: valid transition batches published to a learner as fast as its acks
allow, and the learner's status messages -- typed messages through :mod:`khgrl.common.wire.protocol`."""

from __future__ import annotations

import functools
import math
import secrets
import time
from typing import Callable

import numpy as np
from khgrl.benchmarks.runtime.procs import BENCH_ACTOR
from khgrl.common.delivery.declare import alive_now, publisher, put, subscribe
from khgrl.common.delivery.transport import Inbox, undeclare_all
from khgrl.common.tasks.spaces import ACT_DIM, OBS_DIM
from khgrl.common.wire.messages import Ack, Control, Status, Transitions
from khgrl.common.wire.protocol import Keys, ProtocolError, decode, encode
from khgrl.deploy.run.supervisor import Proc

__all__ = ["batches", "Link", "passage_digest"]


@functools.cache
def passage_digest() -> str:
    """The task digest of the benchmark learner's task (the passage world, as :func:`procs.passage_task_file`
    writes it): every batch must carry it."""
    from khgrl.common.config.settings import RunConfig
    from khgrl.deploy.run.preflight import check_task

    return check_task(RunConfig()).digest


def batches(n: int, batch: int, seed: int, keys=None) -> list[bytes]:
    """``n`` valid transitions as encoded batches seq 0, 1, ... (encoded and signed before any timing starts).

    :param n: transitions
    :param batch: transitions per batch
    :param seed: seed of the random contents
    :param keys: what :data:`BENCH_ACTOR` signs with (:class:`~khgrl.common.delivery.data_keys.DataKeys`; None:
        unsigned)
    """
    from khgrl.common.delivery.data_keys import sign_batch

    rng = np.random.default_rng(seed)
    stream = secrets.token_hex(6)
    out = []
    for seq in range(math.ceil(n / batch)):
        m = min(batch, n - seq * batch)
        trunc = np.zeros(m, dtype=np.uint8)
        trunc[-1] = 1 if seq % 8 == 7 else 0  # an episode end now and then
        zeros = np.zeros(m, dtype=np.uint8)
        msg = Transitions(actor=BENCH_ACTOR, first_step=seq * batch, obs=rng.random((m, OBS_DIM), dtype=np.float32),
                          next_obs=rng.random((m, OBS_DIM), dtype=np.float32),
                          action=rng.uniform(-1, 1, (m, ACT_DIM)).astype(np.float32),
                          reward=rng.standard_normal(m).astype(np.float32), terminated=zeros, truncated=trunc,
                          intervened=zeros, clipped=zeros, stream=stream, base_seq=0, task=passage_digest())
        out.append(encode(sign_batch(msg, keys, seq), BENCH_ACTOR, seq))
    return out


class Link:
    """This process's Zenoh declarations for one measurement: a transitions publisher, the acks of
    :data:`BENCH_ACTOR` and the learner's status.

    :param session: an open Zenoh client session
    :param run: the run id
    """

    def __init__(self, session, run: str) -> None:
        self.session = session
        self.keys = Keys(run)
        self.acks = Inbox(maxsize=100_000)
        self.status = Inbox(maxsize=100_000)
        self.decls = [subscribe(session, self.keys.ack(BENCH_ACTOR), self.acks.callback("ack")),
                      subscribe(session, self.keys.status("learner", "*"), self.status.callback("status"))]
        self.pub = publisher(session, self.keys.transitions(BENCH_ACTOR), congestion="block", priority="data")
        self.decls.append(self.pub)
        self._control_seq = 0

    def wait_learner(self, learner: Proc, timeout: float = 120.0) -> None:
        """Until the learner's liveliness token (declared after its subscribers) is visible here."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if learner.poll() is not None:
                raise RuntimeError(f"{learner.name} exited with {learner.poll()}:\n{learner.tail()}")
            if alive_now(self.session, self.keys.learners_alive, timeout=1.0):
                time.sleep(0.3)  # let the subscription reach this client through the router
                return
            time.sleep(0.2)
        raise RuntimeError(f"the learner's liveliness token never appeared:\n{learner.tail()}")

    def control(self, command: str) -> None:
        """Send ``control/learner COMMAND`` (pause, resume, ...)."""
        put(self.session, self.keys.control("learner"), encode(Control(command=command), "bench", self._control_seq))
        self._control_seq += 1

    def _drain_acks(self, seen: dict, wait: float) -> bool:
        """Read the acks that arrived (waiting up to ``wait`` s for the first) into ``seen``: the highest
        ``received`` and ``durable`` seqs and when the acks that raised them arrived. Returns whether either rose."""
        rose = False
        item = self.acks.get(timeout=wait)
        while item is not None:
            try:
                ack = decode(Ack, item[2])
            except ProtocolError:
                ack = None
            for field in ("received", "durable"):
                if ack is not None and getattr(ack, field) > seen[field]:
                    seen[field], seen[f"t_{field}"], rose = getattr(ack, field), item[3], True
            item = self.acks.get()
        return rose

    def stream(self, payloads: list[bytes], inflight: int, on_progress: Callable[[int], None] | None = None,
               timeout: float = 300.0, stall_s: float = 5.0, durable: bool = False) -> dict:
        """Publish ``payloads`` keeping at most ``inflight`` beyond the last ``received`` seq (as an actor's
        window), until the last seq is acked received (``durable``: and durable); batches not acknowledged after
        ``stall_s`` s without progress are sent again. ``elapsed_s``: first put to the last ack received,
        ``durable_s``: to the ack saying the last seq durable (None unless ``durable``)."""
        last = len(payloads) - 1
        nxt, resends = 0, 0
        t0 = time.monotonic()
        seen = {"received": -1, "durable": -1, "t_received": t0, "t_durable": None}
        last_progress = t0
        while seen["received"] < last or (durable and seen["durable"] < last):
            while nxt <= last and nxt - 1 - seen["received"] < inflight:
                self.pub.put(payloads[nxt])
                nxt += 1
            now = time.monotonic()
            if self._drain_acks(seen, 0.5):
                last_progress = now
            if on_progress is not None:
                on_progress(seen["received"] + 1)
            if now - t0 > timeout:
                raise RuntimeError(f"ingest: only seq {seen['received']} of {last} acknowledged (durable "
                                   f"{seen['durable']}) after {timeout:.0f} s")
            if now - last_progress > stall_s:  # a lost batch (e.g. before the subscription was matched): re-send
                for s in range(seen["received"] + 1, nxt):
                    self.pub.put(payloads[s])
                resends += 1
                last_progress = now
        return {"elapsed_s": seen["t_received"] - t0, "resends": resends, "batches": len(payloads),
                "durable_s": seen["t_durable"] - t0 if durable else None}

    def statuses(self) -> list[Status]:
        """The learner status messages that arrived since the last call (decoded; ``.envelope.ts`` is the
        learner's send time)."""
        out = []
        item = self.status.get()
        while item is not None:
            try:
                out.append(decode(Status, item[2]))
            except ProtocolError:
                pass
            item = self.status.get()
        return out

    def close(self) -> None:
        undeclare_all(*self.decls)
