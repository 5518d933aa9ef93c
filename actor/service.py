"""``khgrl actor``: the actor process. Steps the passage world (KGRL mapping, GPR exploration scale) with
a local copy of the TQC policy, applies human corrections that arrive over Zenoh, and streams its
transitions to the learner without losing or duplicating any.

Per control step:

1. service the inbox (acks, corrections, learner liveliness, control) and swap in new policy weights if the
   background thread has a validated state dict ready (no stall: the swap is a ``load_state_dict``);
2. rate limit: while the learner is alive, wait while ``sent - ack.trained >= --max-lead`` or the loaded
   weights are older than ``ack.version``. The transition about to be collected would otherwise make the
   actor more than ``max_lead`` transitions ahead of what the learner has trained on. With the default
   ``--max-lead 8 --batch 8`` (= the train frequency) each step is taken with exactly the weights
   single-process SB3 would use: the weights trained at the last multiple of 8 (after learning_starts).
   If the learner is not alive, the actor keeps acting with its last weights (a robot does not stop);
3. pace to ``--rate`` (perf_counter deadlines), choose the action (uniform random, seeded, for the first
   ``--learning-starts`` transitions, as SB3 does; then ``policy.predict(obs, deterministic=False)``),
   apply the arbitrated correction (``env.set_correction``), step;
4. record the transition (the stored action is ``info["action"]``: the human's a_h when intervened), publish a
   frame, and every ``--batch`` transitions of the actor's running index (and at episode end) publish a batch.

Delivery: batches are numbered ``seq`` 0, 1, 2, ... and kept in an outbox (memory, spilled to
``RUN_DIR/actor-ID/outbox/`` beyond ``--outbox-memory``) until an ack says ``durable >= seq``. Everything after
``ack.received`` is re-sent when the ack's epoch changes (learner restarted), when the learner's liveliness
token re-appears, or when un-acked data has waited more than 2 s without progress. Re-sent batches carry the
current ``base_seq`` (the oldest batch still held) so a learner that never saw this actor starts there.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import queue
import secrets
import sys
import threading
import time
from collections import OrderedDict, deque
from dataclasses import asdict
from pathlib import Path

import msgpack
import numpy as np

from common.protocol import Keys, ProtocolError, RejectCounter, decode, encode
from common.session import StopFlag, install_stop_handlers, open_client, setup_process_logging

__all__ = ["main", "build_parser", "Outbox", "CorrectionArbiter", "CorrectionRecord"]

log = logging.getLogger("khgrl.actor")

RESEND_AFTER_S = 2.0


# ----------------------------------------------------------------------------------------- outbox
class Outbox:
    """Encoded batches by seq until the learner says they are durable. The newest ``memory`` batches stay in
    memory; older ones are spilled to ``spill_dir`` (one file per batch)."""

    def __init__(self, memory: int, spill_dir: Path) -> None:
        self.memory = max(1, int(memory))
        self.spill_dir = Path(spill_dir)
        self.mem: OrderedDict[int, bytes] = OrderedDict()
        self.disk: deque[int] = deque()
        self.spilled_total = 0

    def _path(self, seq: int) -> Path:
        return self.spill_dir / f"{seq:012d}.msgpack"

    def add(self, seq: int, payload: bytes) -> None:
        self.mem[seq] = payload
        while len(self.mem) > self.memory:
            old, data = self.mem.popitem(last=False)
            self.spill_dir.mkdir(parents=True, exist_ok=True)
            tmp = self._path(old).with_suffix(".tmp")
            tmp.write_bytes(data)
            os.replace(tmp, self._path(old))
            self.disk.append(old)
            self.spilled_total += 1

    def get(self, seq: int) -> bytes:
        if seq in self.mem:
            return self.mem[seq]
        return self._path(seq).read_bytes()

    def drop_through(self, durable: int) -> int:
        n = 0
        while self.disk and self.disk[0] <= durable:
            self._path(self.disk.popleft()).unlink(missing_ok=True)
            n += 1
        while self.mem and next(iter(self.mem)) <= durable:
            self.mem.popitem(last=False)
            n += 1
        return n

    def seqs_after(self, seq: int) -> list[int]:
        return [s for s in self.disk if s > seq] + [s for s in self.mem if s > seq]

    def oldest(self) -> int | None:
        if self.disk:
            return self.disk[0]
        return next(iter(self.mem)) if self.mem else None

    def newest(self) -> int | None:
        return next(reversed(self.mem)) if self.mem else (self.disk[-1] if self.disk else None)

    def __len__(self) -> int:
        return len(self.mem) + len(self.disk)


# ------------------------------------------------------------------------------------ corrections
class CorrectionArbiter:
    """One human-input client drives the actor at a time: the first client that sends an active correction
    holds the intervention until it sends ``active=False`` or is silent longer than ``timeout`` (of the
    actor's running time: pauses of the actor, e.g. waiting for the learner, extend the deadline, since the
    client gets no frames then).

    Corrections come in two kinds (docs/protocol.md). A live client (a person at the GUI) sends plain ones:
    the latest wins and applies to the actor's next step. A step-addressed one names the step it is for
    (``step``, with ``episode``): a client that sends one is *in lock-step* for the rest of that episode --
    the actor does not take a step before it has that client's word (P_h or release) for it (:meth:`ready`),
    so a scripted or replayed correction applies exactly at the step it was computed for, whatever the
    latency. A word for step 0 of the *next* episode, sent while this one runs, announces lock-step from that
    episode's first step. A lock-step client that stays silent for ``timeout`` at a step is dropped back to
    plain mode (:meth:`give_up`).
    """

    MAX_AHEAD = 64  # step-addressed messages kept ahead of the current step

    def __init__(self, actor: str, timeout: float, enabled: bool) -> None:
        self.actor = actor
        self.timeout = float(timeout)
        self.enabled = enabled
        self.holder: str | None = None
        self.p_h: np.ndarray | None = None
        self.deadline = 0.0
        self.lockstep: str | None = None  # client whose step-addressed word each step of this episode waits for
        self._addressed: dict[int, dict] = {}  # step -> that client's message for it
        self._announced: tuple[int, dict] | None = None  # (next episode, a client's word for its step 0)
        self.counts = {"applied": 0, "ignored_other_client": 0, "ignored_other_actor": 0, "ignored_method": 0,
                       "stale_episode": 0, "timeouts": 0, "releases": 0, "holds": 0, "projected_steps": 0,
                       "addressed": 0, "late_step": 0, "lockstep_waits": 0, "lockstep_timeouts": 0}

    def new_episode(self, episode: int) -> None:
        """Lock-step lasts one episode: a client re-enters it with a word for the new episode (announced during
        the last one, or its first step-addressed message), and a lock-step client's hold ends with the episode
        (its words were for that episode's steps)."""
        if self.lockstep is not None and self.holder == self.lockstep:
            self._release()
        self.lockstep = None
        self._addressed.clear()
        if self._announced is not None and self._announced[0] == episode:
            msg = self._announced[1]
            self.lockstep, self._addressed[0] = msg["client"], msg
        self._announced = None

    def offer(self, msg: dict, arrival: float, episode: int, step: int = 0) -> None:
        """A validated correction message that arrived at ``arrival`` while the actor is before ``step`` of ``episode``."""
        if msg["actor"] != self.actor:
            self.counts["ignored_other_actor"] += 1
            return
        if not self.enabled:
            self.counts["ignored_method"] += 1
            return
        client = msg["client"]
        if self.holder is not None and client != self.holder:
            self.counts["ignored_other_client"] += 1
            return
        if "step" in msg:
            self._offer_addressed(msg, episode, step)
            return
        if not msg["active"]:
            if self.holder == client:
                self._release()
            return
        if "episode" in msg and msg["episode"] != episode:
            self.counts["stale_episode"] += 1
            return
        self._hold(client, msg["p_h"], arrival)

    def _offer_addressed(self, msg: dict, episode: int, step: int) -> None:
        client = msg["client"]
        if msg["episode"] == episode + 1 and msg["step"] == 0:  # announces lock-step for the next episode
            self._announced = (episode + 1, msg)
            self.counts["addressed"] += 1
            return
        if msg["episode"] != episode:
            self.counts["stale_episode"] += 1
            return
        if self.lockstep is not None and client != self.lockstep:
            self.counts["ignored_other_client"] += 1
            return
        if msg["step"] < step:
            self.counts["late_step"] += 1  # the step it was meant for is already taken
            return
        self.lockstep = client
        self.counts["addressed"] += 1
        if len(self._addressed) < self.MAX_AHEAD or msg["step"] in self._addressed:
            self._addressed[msg["step"]] = msg

    def ready(self, step: int) -> bool:
        """Whether the actor may take ``step``: True unless a lock-step client has not yet sent its word for it."""
        return self.lockstep is None or step in self._addressed

    def give_up(self, step: int) -> None:
        """The lock-step client said nothing for ``step`` in time: carry on in plain mode (latest wins)."""
        log.warning("lock-step correction client %s sent nothing for step %d: no longer waiting for it this episode",
                    self.lockstep, step)
        self.counts["lockstep_timeouts"] += 1
        self.lockstep = None
        self._addressed.clear()

    def _hold(self, client: str, p_h, arrival: float) -> None:
        if self.holder is None:
            self.holder = client
            self.counts["holds"] += 1
        self.p_h = np.asarray(p_h, dtype=np.float64)
        self.deadline = arrival + self.timeout
        self.counts["applied"] += 1

    def _release(self) -> None:
        self.holder, self.p_h = None, None
        self.counts["releases"] += 1

    def extend(self, seconds: float) -> None:
        if self.holder is not None:
            self.deadline += seconds

    def current(self, now: float, step: int | None = None) -> np.ndarray | None:
        """P_h to apply at ``step`` (None: no intervention). In lock-step, the client's word for that step."""
        if self.lockstep is not None and step is not None:
            msg = self._addressed.pop(step, None)
            for s in [s for s in self._addressed if s < step]:
                del self._addressed[s]
            if msg is not None:
                if msg["active"]:
                    self._hold(msg["client"], msg["p_h"], now)
                elif self.holder == msg["client"]:
                    self._release()
                return self.p_h
        if self.holder is not None and now > self.deadline:
            log.info("correction client %s silent for > %.2f s: intervention ended", self.holder, self.timeout)
            self.holder, self.p_h = None, None
            self.counts["timeouts"] += 1
        return self.p_h


class CorrectionRecord:
    """``RUN_DIR/actor-ID/corrections.csv``: one row per step at which the actor applied a human correction
    (run, actor, episode, step t, wall time, client, P_h as received, and whether it was projected onto the
    workspace / its action clipped). ``khgrl human replay`` feeds such a file into a new run."""

    FIELDS = ("run", "actor", "episode", "step", "time", "client", "p_h_x", "p_h_y", "projected", "clipped")

    def __init__(self, path: Path, run: str, actor: str) -> None:
        import csv

        self.path = Path(path)
        self.run, self.actor = run, actor
        self._fh = open(self.path, "w", newline="")
        self._w = csv.writer(self._fh)
        self._w.writerow(self.FIELDS)
        self.rows = 0

    def write(self, episode: int, t: int, client: str | None, p_h, info: dict) -> None:
        if self._fh.closed:
            return
        self._w.writerow((self.run, self.actor, int(episode), int(t), f"{time.time():.6f}", client or "",
                          repr(float(p_h[0])), repr(float(p_h[1])), int(bool(info.get("projected"))),
                          int(bool(info.get("clipped")))))
        self.rows += 1

    def flush(self) -> None:
        if not self._fh.closed:
            self._fh.flush()

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()


# ---------------------------------------------------------------------------------------- weights
class WeightsReceiver:
    """Drains a RingChannel(1) weights subscriber in a background thread: decodes, validates names and shapes
    against the local actor network, converts to tensors and leaves the newest ready for the control loop."""

    def __init__(self, subscriber, template: dict, rejects: RejectCounter, key: str) -> None:
        self.sub = subscriber
        self.template = {k: tuple(v.shape) for k, v in template.items()}
        self.rejects = rejects
        self.key = key
        self.lock = threading.Lock()
        self.ready: tuple | None = None  # (epoch, version, trained, state_dict, publish ts)
        self.received = 0
        self.thread = threading.Thread(target=self._run, name="weights-rx", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def _run(self) -> None:
        handler = self.sub.handler
        while True:
            try:
                sample = handler.recv()
            except Exception:  # noqa: BLE001 - ZError "channel is empty and closed" after undeclare
                return
            self.offer(sample.payload.to_bytes())

    def parse(self, payload: bytes):
        import torch

        msg = decode("weights", payload)
        tensors = msg["tensors"]
        if set(tensors) != set(self.template):
            raise ProtocolError(f"tensors: names {sorted(tensors)} do not match the actor network")
        for k, shape in self.template.items():
            if tuple(tensors[k].shape) != shape:
                raise ProtocolError(f"tensors[{k}]: shape {tensors[k].shape}, the actor network has {shape}")
        sd = {k: torch.from_numpy(np.array(v, dtype=np.float32)) for k, v in tensors.items()}
        return (msg.get("epoch"), msg["version"], dict(msg["trained"]), sd, float(msg["ts"]))

    def offer(self, payload: bytes) -> None:
        try:
            item = self.parse(payload)
        except ProtocolError as exc:
            self.rejects.reject("weights", self.key, exc)
            return
        with self.lock:
            self.received += 1
            self.ready = item

    def take(self):
        with self.lock:
            item, self.ready = self.ready, None
        return item

    def stop(self) -> None:
        try:
            self.sub.undeclare()
        except Exception:  # noqa: BLE001
            pass
        self.thread.join(timeout=2.0)


# ------------------------------------------------------------------------------------------ actor
class ActorService:
    def __init__(self, args: argparse.Namespace, session, env, policy, flag: StopFlag, out_dir: Path) -> None:
        import zenoh

        self.args = args
        self.session = session
        self.env = env
        self.policy = policy
        self.flag = flag
        self.dir = out_dir
        self.id = args.id
        self.keys = Keys(args.run)
        self.stream = secrets.token_hex(6)
        self.rejects = RejectCounter(f"actor/{self.id}")
        self.inbox: queue.Queue = queue.Queue()
        self.khgrl = args.method == "khgrl"
        self.arbiter = CorrectionArbiter(self.id, args.correction_timeout, enabled=self.khgrl)
        self.outbox = Outbox(args.outbox_memory, out_dir / "outbox")
        self.record = CorrectionRecord(out_dir / "corrections.csv", args.run, self.id)
        self.tb = None  # a torch SummaryWriter, set by run() unless --no-tensorboard
        # stream state
        self.count = 0  # transitions collected (the next transition's per-actor index)
        self.sent = 0  # transitions published (first time)
        self.next_seq = 0
        self.buf: list[tuple] = []
        self.buf_first = 0
        # what the learner told us
        self.ack_epoch: str | None = None
        self.received = -1
        self.durable = -1
        self.trained = 0
        self.ack_version = 0
        self.last_progress = time.monotonic()
        self.learners: set[str] = set()
        # weights
        self.loaded_epoch: str | None = None
        self.loaded_version = -1
        self.loaded_trained = 0
        self.initial_weights_version: int | None = None
        self.weights_swaps = 0
        self.weights_latency: list[float] = []  # s from the learner's publish (msg ts) to applied in the loop
        self.max_weight_lag = 0
        self.lag_hist: dict[str, int] = {}  # steps by (transitions - those the loaded weights were trained on)
        # counters
        self.counters = {"frame": 0, "episode": 0, "scale": 0, "status": 0, "control": 0}
        self.resends = 0
        self.resent_batches = 0
        self.wait_time = 0.0
        self.waits = 0
        self.periods: list[float] = []
        self.paused = False
        self.episodes = []
        self.episode = 0
        self.scale_updates = 0
        self.scale_history: list[tuple[int, np.ndarray]] = []  # (episode, L table over the grid) after each refit
        self.realtime = False  # control loop under SCHED_FIFO (set_realtime)
        self._t_status = time.monotonic()
        self._ckpt_request_t = -1e9
        self._last_weights_get = -1e9
        self._resend_at: float | None = None

        cb = self._callback
        self.decls = [
            session.declare_subscriber(self.keys.ack(self.id), cb("ack")),
            session.declare_subscriber(self.keys.correction("*"), cb("correction")),
            session.declare_subscriber(self.keys.control("actor"), cb("control")),
            session.declare_subscriber(self.keys.control(self.id), cb("control")),
            session.declare_subscriber(self.keys.control("all"), cb("control")),
            session.liveliness().declare_subscriber(self.keys.alive("learner", "*"), self._alive_cb, history=True),
        ]
        BLOCK, DROP = zenoh.CongestionControl.BLOCK, zenoh.CongestionControl.DROP
        self.pubs = {
            "transitions": session.declare_publisher(self.keys.transitions(self.id), congestion_control=BLOCK,
                                                     priority=zenoh.Priority.DATA),
            "frame": session.declare_publisher(self.keys.frame(self.id), congestion_control=DROP,
                                               priority=zenoh.Priority.DATA),
            "episode": session.declare_publisher(self.keys.episode(self.id), congestion_control=BLOCK),
            "scale": session.declare_publisher(self.keys.scale(self.id), congestion_control=BLOCK),
            "status": session.declare_publisher(self.keys.status("actor", self.id), congestion_control=DROP,
                                                priority=zenoh.Priority.DATA_LOW),
        }
        template = policy.actor.state_dict()
        self.weights = WeightsReceiver(session.declare_subscriber(self.keys.weights, zenoh.handlers.RingChannel(1)),
                                       template, self.rejects, self.keys.weights)
        self.weights.start()
        self.token = session.liveliness().declare_token(self.keys.alive("actor", self.id))
        # who is alive right now, and the current weights (late joiner), before the first step
        try:
            for r in session.liveliness().get(self.keys.alive("learner", "*"), timeout=1.0):
                if r.ok:
                    self.learners.add(str(r.ok.key_expr))
        except Exception as exc:  # noqa: BLE001
            log.warning("liveliness query failed: %s", exc)
        self._get_weights(timeout=2.0)
        self.initial_weights_version = self.loaded_version if self.loaded_version >= 0 else None
        log.info("actor %s: learner %s, initial weights version %s", self.id,
                 "alive" if self.learners else "not seen", self.initial_weights_version)

    # ---------------------------------------------------------------- zenoh callbacks (enqueue only)
    def _callback(self, kind: str):
        def cb(sample) -> None:
            self.inbox.put((kind, str(sample.key_expr), sample.payload.to_bytes(), time.monotonic()))

        return cb

    def _alive_cb(self, sample) -> None:
        import zenoh

        self.inbox.put(("alive", str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT, time.monotonic()))

    # ---------------------------------------------------------------- inbox
    @property
    def learner_alive(self) -> bool:
        return bool(self.learners)

    def service(self, block: float = 0.0) -> None:
        """Handle everything that arrived; swap weights; resend if stalled; status."""
        timeout = block
        while True:
            try:
                kind, key, payload, arrival = self.inbox.get(timeout=timeout) if timeout > 0 else self.inbox.get_nowait()
            except queue.Empty:
                break
            timeout = 0.0
            if kind == "alive":
                self._on_alive(key, payload)
                continue
            try:
                msg = decode(kind, payload)
            except ProtocolError as exc:
                self.rejects.reject(kind, key, exc)
                continue
            if kind == "ack":
                self._on_ack(msg)
            elif kind == "correction":
                if msg["client"] != Keys.last_chunk(key, 3):
                    self.rejects.reject("correction", key, ProtocolError(f"client {msg['client']!r} published on {key}"))
                    continue
                self.arbiter.offer(msg, arrival, self.episode, self.env.t)
            elif kind == "control":
                self._on_control(msg["command"])
        self._swap_weights()
        now = time.monotonic()
        if self._resend_at is not None and now >= self._resend_at:
            self._resend_at = None
            self._resend(-1, "learner appeared")
        if self.learner_alive and self.outbox.newest() is not None and self.outbox.newest() > self.received \
                and now - self.last_progress > RESEND_AFTER_S:
            self._resend(self.received, "no ack progress for %.1f s" % (now - self.last_progress))
        if now - self._t_status >= 1.0:
            self._t_status = now
            self._publish_status()

    def _on_alive(self, key: str, put: bool) -> None:
        if put:
            if key not in self.learners:
                self.learners.add(key)
                log.info("learner %s appeared (outbox: %d batches)", key, len(self.outbox))
                # a resumed learner acks at once with its new epoch (which re-sends); a fresh one only acks
                # what it receives: re-send the whole outbox shortly unless that ack came first
                self._resend_at = time.monotonic() + 0.3
                self.last_progress = time.monotonic()  # (that re-send replaces the stall timer's)
        else:
            self.learners.discard(key)
            log.warning("learner %s gone: acting on with weights version %d", key, self.loaded_version)

    def _on_ack(self, msg: dict) -> None:
        # the learner echoes the stream id of the transitions it acks; an ack without it is not for us
        if msg["actor"] != self.id or msg.get("stream") != self.stream:
            return
        new_epoch = msg["epoch"] != self.ack_epoch
        restarted = new_epoch and self.ack_epoch is not None
        if restarted:
            log.info("learner epoch changed (%s -> %s): received %d, durable %d", self.ack_epoch, msg["epoch"],
                     msg["received"], msg["durable"])
            self._ckpt_request_t = -1e9
        if msg["received"] > self.received or new_epoch:
            self.last_progress = time.monotonic()
        self.ack_epoch = msg["epoch"]
        self.received = msg["received"]
        self.trained = msg["trained"]
        self.ack_version = msg["version"]
        if msg["durable"] > self.durable or new_epoch:
            self.durable = max(self.durable, msg["durable"])
            self.outbox.drop_through(self.durable)
        if restarted:
            self._resend_at = None
            self._resend(self.received, "new learner epoch")

    def _on_control(self, command: str) -> None:
        log.info("control: %s", command)
        if command == "stop":
            self.flag.set("stop command")
        elif command == "pause":
            self.paused = True
        elif command == "resume":
            self.paused = False

    # ---------------------------------------------------------------- weights
    def _load(self, item) -> None:
        epoch, version, trained, sd, _ts = item
        if epoch == self.loaded_epoch and version <= self.loaded_version:
            return
        self.policy.actor.load_state_dict(sd)
        self.loaded_epoch, self.loaded_version = epoch, version
        self.loaded_trained = int(trained.get(self.id, 0))
        self.weights_swaps += 1

    def _swap_weights(self) -> None:
        item = self.weights.take()
        if item is not None:
            swaps = self.weights_swaps
            self._load(item)
            if self.weights_swaps > swaps:  # applied: latency from the learner's publish (same-machine clock)
                self.weights_latency.append(time.time() - item[4])

    def _get_weights(self, timeout: float) -> None:
        """Pull the current weights from the learner's queryable (late joiner / missed update)."""
        self._last_weights_get = time.monotonic()
        try:
            replies = list(self.session.get(self.keys.weights, timeout=timeout))
        except Exception as exc:  # noqa: BLE001
            log.warning("weights query failed: %s", exc)
            return
        for r in replies:
            if r.ok:
                try:
                    self._load(self.weights.parse(r.ok.payload.to_bytes()))
                except ProtocolError as exc:
                    self.rejects.reject("weights", self.keys.weights, exc)

    def _weights_behind(self) -> bool:
        if self.ack_epoch is None:
            return False
        if self.loaded_epoch is not None and self.loaded_epoch != self.ack_epoch:
            return True
        return self.loaded_version < self.ack_version

    # ---------------------------------------------------------------- rate limit
    def _must_wait(self) -> bool:
        if self.paused:
            return True
        if not self.learner_alive:
            return False
        trained = self.trained if self.ack_epoch is not None else 0
        return self.sent - trained >= self.args.max_lead or self._weights_behind()

    def rate_limit(self) -> None:
        if not self._must_wait():
            return
        t0 = time.monotonic()
        self.waits += 1
        while not self.flag and self._must_wait():
            self.service(block=0.02)
            now = time.monotonic()
            if self._weights_behind() and now - t0 > 1.0 and now - self._last_weights_get > 1.0:
                self._get_weights(timeout=1.0)
        dt = time.monotonic() - t0
        self.wait_time += dt
        self.arbiter.extend(dt)

    def _await_correction(self, step: int) -> None:
        """A lock-step correction client has not yet sent its word for ``step``: wait for it (servicing the
        inbox) at most the correction timeout, then carry on without it."""
        t0 = time.monotonic()
        self.arbiter.counts["lockstep_waits"] += 1
        while not self.flag and not self.arbiter.ready(step):
            if time.monotonic() - t0 > self.arbiter.timeout:
                self.arbiter.give_up(step)
                break
            self.service(block=0.002)

    # ---------------------------------------------------------------- transitions
    def publish_batch(self) -> None:
        if not self.buf:
            return
        cols = list(zip(*self.buf))
        fields = {
            "actor": self.id,
            "first_step": self.buf_first,
            "obs": np.asarray(cols[0], dtype=np.float32),
            "next_obs": np.asarray(cols[1], dtype=np.float32),
            "action": np.asarray(cols[2], dtype=np.float32),
            "reward": np.asarray(cols[3], dtype=np.float32),
            "terminated": np.asarray(cols[4], dtype=np.uint8),
            "truncated": np.asarray(cols[5], dtype=np.uint8),
            "intervened": np.asarray(cols[6], dtype=np.uint8),
            "clipped": np.asarray(cols[7], dtype=np.uint8),
            "stream": self.stream,
        }
        seq = self.next_seq
        oldest = self.outbox.oldest()
        fields["base_seq"] = seq if oldest is None else oldest
        payload = encode("transitions", self.id, seq, **fields)
        if self.outbox.newest() is None or self.outbox.newest() <= self.received:
            self.last_progress = time.monotonic()  # nothing was waiting: the resend timer starts now
        self.outbox.add(seq, payload)
        self.pubs["transitions"].put(payload)
        self.next_seq += 1
        self.sent += len(self.buf)
        self.buf = []
        self.buf_first = self.count

    def _resend(self, after: int, why: str) -> None:
        seqs = self.outbox.seqs_after(after)
        self.last_progress = time.monotonic()
        if not seqs:
            return
        base = self.outbox.oldest()
        for s in seqs:
            m = msgpack.unpackb(self.outbox.get(s), raw=False)
            m["base_seq"] = base
            self.pubs["transitions"].put(msgpack.packb(m, use_bin_type=True))
        self.resends += 1
        self.resent_batches += len(seqs)
        log.info("re-sent batches %d..%d (%d) after %d: %s", seqs[0], seqs[-1], len(seqs), after, why)

    # ---------------------------------------------------------------- messages
    def _put(self, kind: str, **fields) -> None:
        self.pubs[kind].put(encode(kind, self.id, self.counters[kind], **fields))
        self.counters[kind] += 1

    def _publish_status(self) -> None:
        p = np.asarray(self.periods[-2000:]) if self.periods else None
        info = {
            "id": self.id, "episode": self.episode, "t": int(self.env.t), "transitions": self.count,
            "sent": self.sent, "next_seq": self.next_seq, "outbox": len(self.outbox), "received": self.received,
            "durable": self.durable, "trained": self.trained, "weights_version": self.loaded_version,
            "ack_version": self.ack_version, "learner_alive": self.learner_alive, "waits": self.waits,
            "wait_s": round(self.wait_time, 3), "resends": self.resends, "corrections": dict(self.arbiter.counts),
            "intervening": self.arbiter.holder is not None, "rejects": self.rejects.by_kind(), "paused": self.paused,
            "period_ms_p50": float(np.percentile(p, 50) * 1e3) if p is not None and p.size else None,
        }
        self._put("status", role="actor", info=info)

    def _publish_scale(self) -> None:
        m = self.env.mapping
        fields = {"actor": self.id, "model": m.scale_model.to_dict()}
        if m._table is not None:
            fields["table"] = np.asarray(m._table, dtype=np.float64)
        self._put("scale", **fields)

    def _refit_scale(self, segment: list[tuple]) -> None:
        if not segment or not (self.khgrl and self.env.scenario.learn_scale):
            return
        xi = np.array([s[0] for s in segment])
        ph = np.array([s[1] for s in segment])
        self.env.mapping.update_scale(xi, ph)
        self.scale_updates += 1
        if self.env.mapping.scale_table is not None:
            self.scale_history.append((self.episode, np.array(self.env.mapping.scale_table, dtype=np.float64)))
        self._publish_scale()

    def save_scale(self) -> None:
        """``scale.npz``: the exploration scale L over the grid's phases, as it ended (``table``, (N, O); KGRL and
        scenarios without a learned scale keep the constant default) and after each refit (``history``, with the
        ``episodes`` whose intervention produced it) -- the data of the paper's Fig. 6."""
        m = self.env.mapping
        if m.scale_table is None:  # a position-input scale model has no table over phase
            return
        table = np.asarray(m.scale_table, dtype=np.float64)
        hist = np.array([h for _, h in self.scale_history]) if self.scale_history else np.zeros((0, *table.shape))
        np.savez(self.dir / "scale.npz", table=table, phases=np.asarray(m.phases),
                 history=hist, episodes=np.array([e for e, _ in self.scale_history], dtype=np.int64))

    # ---------------------------------------------------------------- main loop
    def run(self) -> int:
        from common.metrics import EpisodeAccumulator

        args, env = self.args, self.env
        acc = EpisodeAccumulator()
        period = 1.0 / args.rate if args.rate > 0 else 0.0
        deadline = time.perf_counter()
        last_start = None
        first_due = (args.learning_starts // 8 + 1) * 8
        if self.khgrl:
            self._publish_scale()
        while len(self.episodes) < args.episodes and not self.flag:
            obs, _ = env.reset()
            acc.start()
            self.episode = acc.episode
            self.arbiter.new_episode(self.episode)
            t_ep = time.perf_counter()
            segment: list[tuple] = []
            ep_ret = 0.0
            done = False
            while not done and not self.flag:
                self.service()
                self.rate_limit()
                if self.flag:
                    break
                if period > 0:
                    deadline += period
                    now = time.perf_counter()
                    if deadline < now - period:  # fell behind by more than a period: don't try to catch up
                        deadline = now
                    elif deadline > now:
                        time.sleep(deadline - now)
                        # what arrived while pacing (a correction for the frame just published) applies to this step
                        self.service()
                        self.rate_limit()
                        if self.flag:
                            break
                start = time.perf_counter()
                if last_start is not None:
                    self.periods.append(start - last_start)
                last_start = start
                if self.count < args.learning_starts:
                    action = env.action_space.sample()
                else:
                    action, _ = self.policy.predict(obs, deterministic=False)
                    if self.count >= first_due:
                        lag = self.count - self.loaded_trained
                        self.max_weight_lag = max(self.max_weight_lag, lag)
                        b = str(lag) if lag < 2 * args.max_lead else f">={2 * args.max_lead}"
                        self.lag_hist[b] = self.lag_hist.get(b, 0) + 1
                if not self.arbiter.ready(env.t):
                    self._await_correction(env.t)
                p_h = self.arbiter.current(time.monotonic(), env.t)
                env.set_correction(p_h)
                next_obs, reward, terminated, truncated, info = env.step(action)
                acc.add(reward, info)
                ep_ret += float(reward)
                iv = bool(info["intervened"])
                if iv:
                    segment.append((info["xi_h"], info["phase"]))
                elif segment:
                    self._refit_scale(segment)
                    segment = []
                self.buf.append((obs, next_obs, info["action"], reward, terminated, truncated, iv, bool(info["clipped"])))
                self.count += 1
                t = int(info["t"])
                if iv and p_h is not None:
                    self.record.write(self.episode, t, self.arbiter.holder, p_h, info)
                    self.arbiter.counts["projected_steps"] += int(bool(info.get("projected")))
                self._put("frame", actor=self.id, episode=self.episode, t=t, phase=float(info["phase"]),
                          robot=[float(v) for v in env.robot], desired=[float(v) for v in info["desired"]],
                          mean=[float(v) for v in env.mapping.mean(t)], scale=[float(v) for v in info["scale"]],
                          intervening=iv, scenario=args.scenario, ret=float(ep_ret),
                          **({"next_mean": [float(v) for v in env.mapping.mean(t + 1)]} if t + 1 < env.horizon else {}))
                done = terminated or truncated
                if done or self.count % args.batch == 0:
                    self.publish_batch()
                obs = next_obs
            if not done:
                break  # stopped mid-episode: no statistics for a partial episode
            env.set_correction(None)
            self._refit_scale(segment)
            st = acc.finish(time.perf_counter() - t_ep)
            self.record.flush()
            self._tb_episode(st)
            self.episodes.append(st)
            self._put("episode", actor=self.id, stats=asdict(st))
            log.info("episode %d: %d steps, return %.1f, success %s, interventions %d (%d steps), weights v%d",
                     st.episode, st.steps, st.ret, st.success, st.interventions, st.intervention_steps,
                     self.loaded_version)
        self.publish_batch()  # a partial batch after a stop
        if self.flag:
            return self._finish_on_signal()
        return self._flush()

    def _tb_episode(self, st) -> None:
        """Per-episode scalars (return, success, intervention statistics) to TensorBoard (RUN_DIR/actor-ID/tb)."""
        if self.tb is None:
            return
        n = st.episode
        iv = st.intervention_steps
        scalars = {
            "episode/return": st.ret, "episode/success": float(st.success), "episode/steps": st.steps,
            "episode/obstacle_steps": st.obstacle_steps,
            "interventions/count": st.interventions, "interventions/steps": iv,
            "interventions/fraction_of_steps": iv / st.steps if st.steps else 0.0,
            "interventions/clipped_fraction": st.clipped_steps / iv if iv else 0.0,
            "interventions/projected_steps": st.projected_steps, "interventions/mean_abs_xi_h": st.mean_abs_xi_h,
        }
        for d, v in enumerate(st.scale_max or []):
            scalars[f"scale/max_L{'xy'[d] if d < 2 else d}"] = v
        try:
            for k, v in scalars.items():
                self.tb.add_scalar(k, float(v), n)
            self.tb.flush()
        except Exception as exc:  # noqa: BLE001 - metrics must never stop the robot
            log.warning("tensorboard write failed (%s): disabled", exc)
            self.tb = None

    def _flush(self) -> int:
        """Wait until the learner holds every batch in a checkpoint (or --flush-timeout)."""
        last = self.next_seq - 1
        t0 = time.monotonic()
        log.info("all %d episodes done: flushing %d batches (last seq %d)", len(self.episodes), len(self.outbox), last)
        while last >= 0 and self.durable < last and time.monotonic() - t0 < self.args.flush_timeout and not self.flag:
            self.service(block=0.05)
            now = time.monotonic()
            if self.learner_alive and self.received >= last and now - self._ckpt_request_t > 5.0:
                self._ckpt_request_t = now
                self.session.put(self.keys.control("learner"),
                                 encode("control", self.id, self.counters["control"], command="checkpoint"))
                self.counters["control"] += 1
        self._publish_status()
        if self.durable < last:
            n = self.unconfirmed()
            log.error("flush timed out: %d transitions in %d batches not confirmed durable by the learner", n, len(self.outbox))
            print(f"khgrl actor {self.id}: flush timed out: {n} transitions not confirmed", file=sys.stderr, flush=True)
            return 3
        log.info("flushed: every batch up to seq %d is in a learner checkpoint", last)
        return 0

    def _finish_on_signal(self) -> int:
        last = self.next_seq - 1
        t0 = time.monotonic()
        while last >= 0 and self.received < last and self.learner_alive and time.monotonic() - t0 < 2.0:
            self.service(block=0.05)
        log.info("stopped (%s): %d transitions not yet durable", self.flag.reason, self.unconfirmed())
        return 0

    def unconfirmed(self) -> int:
        n = 0
        for s in self.outbox.seqs_after(self.durable):
            n += len(msgpack.unpackb(self.outbox.get(s), raw=False)["reward"]["data"]) // 4
        return n

    def close(self) -> None:
        self.record.close()
        self.weights.stop()
        for d in self.decls:
            try:
                d.undeclare()
            except Exception:  # noqa: BLE001
                pass
        for p in self.pubs.values():
            try:
                p.undeclare()
            except Exception:  # noqa: BLE001
                pass
        self.token.undeclare()

    def summary(self, rc: int, wall: float) -> dict:
        p = np.asarray(self.periods)
        wl = np.asarray(self.weights_latency)

        def pct(q):
            return float(np.percentile(p, q) * 1e3) if p.size else None

        return {
            "id": self.id, "exit_code": rc, "stopped_by": self.flag.reason or None, "wall_time_s": wall,
            "episodes": len(self.episodes), "transitions": self.count, "sent": self.sent, "batches": self.next_seq,
            "last_seq": self.next_seq - 1, "received": self.received, "durable": self.durable,
            "unconfirmed_transitions": self.unconfirmed(), "outbox_spilled": self.outbox.spilled_total,
            "resends": self.resends, "resent_batches": self.resent_batches,
            "loop_period_ms": {"p50": pct(50), "p99": pct(99), "max": float(p.max() * 1e3) if p.size else None,
                               "n": int(p.size), "target": 1e3 / self.args.rate if self.args.rate > 0 else None},
            "rate_limit": {"waits": self.waits, "wait_s": self.wait_time, "max_lead": self.args.max_lead},
            "weights": {"initial_version": self.initial_weights_version, "final_version": self.loaded_version,
                        "swaps": self.weights_swaps, "received": self.weights.received,
                        "max_lag": self.max_weight_lag,
                        "lag_histogram": dict(sorted(self.lag_hist.items(), key=lambda kv: (len(kv[0]), kv[0])))},
            "weights_latency_ms": {"p50": float(np.percentile(wl, 50) * 1e3) if wl.size else None,
                                   "p99": float(np.percentile(wl, 99) * 1e3) if wl.size else None,
                                   "max": float(wl.max() * 1e3) if wl.size else None, "n": int(wl.size)},
            "corrections": dict(self.arbiter.counts), "scale_updates": self.scale_updates,
            "successes": int(sum(e.success for e in self.episodes)), "realtime": self.realtime,
            "rejects": self.rejects.by_kind(), "stream": self.stream,
        }


def set_realtime(priority: int) -> bool:
    """Run the calling thread -- the control loop; Zenoh's, the weights receiver's and TensorBoard's threads are
    already started and keep the normal policy -- under SCHED_FIFO at ``priority`` (1-99), as robot control
    loops are run, so that CPU-bound neighbours (a learner on the same machine) do not delay its wake-ups.
    Linux only, needs CAP_SYS_NICE (root); without it, logs why and returns False (the loop runs as before).
    The loop sleeps every period (``--rate`` is required), so it cannot starve the machine."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (AttributeError, OSError) as exc:
        log.warning("could not run the control loop under SCHED_FIFO %d (%s): normal scheduling", priority, exc)
        return False
    log.info("control loop thread runs under SCHED_FIFO priority %d", priority)
    return True


def run(args: argparse.Namespace) -> int:
    import torch
    from sb3_contrib.tqc.policies import TQCPolicy

    from common.env import PassageEnv
    from common.metrics import write_episodes

    out_dir = Path(args.run_dir) / f"actor-{args.id}"
    out_dir.mkdir(parents=True, exist_ok=True)
    setup_process_logging(out_dir / "actor.log")
    torch.set_num_threads(1)
    flag = StopFlag()
    install_stop_handlers(flag)
    t0 = time.perf_counter()
    env = PassageEnv(args.scenario)
    env.action_space.seed(args.seed)  # SB3 seeds the action space it samples warm-up actions from
    torch.manual_seed(args.seed)
    policy = TQCPolicy(env.observation_space, env.action_space, lr_schedule=lambda _: 1e-3, net_arch=[256, 256])
    policy.set_training_mode(False)
    log.info("actor %s: %s/%s, world ready in %.1f s", args.id, args.scenario, args.method, time.perf_counter() - t0)
    rc = 1
    t_run = time.perf_counter()
    tb = None
    if args.tensorboard:
        try:
            from torch.utils.tensorboard import SummaryWriter

            tb = SummaryWriter(log_dir=str(out_dir / "tb"))
        except Exception as exc:  # noqa: BLE001
            log.warning("no TensorBoard scalars: %s", exc)
    with open_client(args.connect, args.lease_ms) as session:
        svc = ActorService(args, session, env, policy, flag, out_dir)
        svc.tb = tb
        svc.realtime = set_realtime(args.rt_priority) if args.rt_priority > 0 else False
        try:
            rc = svc.run()
        finally:
            summary = svc.summary(rc, time.perf_counter() - t_run)
            svc.close()
            if svc.tb is not None:
                svc.tb.close()
    config = {"actor": vars(args), "tqc_policy": {"net_arch": [256, 256]}, "stream": svc.stream}
    write_episodes(out_dir, svc.episodes, config)
    svc.save_scale()
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    log.info("actor %s done (exit %d): %d episodes, %d transitions, loop period p50 %.2f ms p99 %.2f ms",
             args.id, rc, len(svc.episodes), svc.count, summary["loop_period_ms"]["p50"] or 0,
             summary["loop_period_ms"]["p99"] or 0)
    return rc


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="khgrl actor",
                                description="Actor: steps the passage world with the current policy, applies human "
                                            "corrections, streams transitions to the learner.")
    p.add_argument("--run", required=True, help="run id (key prefix khgrl/<run>/)")
    p.add_argument("--connect", required=True, help="router endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--run-dir", required=True, help="run directory; the actor writes RUN_DIR/actor-ID/")
    p.add_argument("--scenario", default="high_cov", choices=["high_cov", "low_cov"])
    p.add_argument("--method", default="khgrl", choices=["khgrl", "kgrl"],
                   help="khgrl: apply human corrections and learn the exploration scale; kgrl: ignore them")
    p.add_argument("--episodes", type=int, default=60)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--id", default="a0", help="actor id (default %(default)s)")
    p.add_argument("--max-lead", type=int, default=8,
                   help="transitions the actor may be ahead of what the learner trained on (8 = single-process SB3)")
    p.add_argument("--rate", type=float, default=0.0, help="control rate in Hz (0: as fast as allowed)")
    p.add_argument("--rt-priority", type=int, default=0,
                   help="run the control loop under SCHED_FIFO at this priority (1-99; Linux, root/CAP_SYS_NICE; "
                        "needs --rate). 0 (default): normal scheduling")
    p.add_argument("--batch", type=int, default=8, help="transitions per batch (cut at multiples of the running index)")
    p.add_argument("--learning-starts", type=int, default=100, help="uniform random actions for the first N transitions")
    p.add_argument("--correction-timeout", type=float, default=0.5, help="a silent correction client loses the robot after this (s)")
    p.add_argument("--outbox-memory", type=int, default=1000, help="batches kept in memory before spilling to disk")
    p.add_argument("--flush-timeout", type=float, default=120.0, help="at the end, wait this long for the learner to confirm (s)")
    p.add_argument("--lease-ms", type=int, default=3000, help="Zenoh link lease (liveliness timeout of this process)")
    p.add_argument("--tensorboard", action=argparse.BooleanOptionalAction, default=True,
                   help="write per-episode scalars (return, interventions) to RUN_DIR/actor-ID/tb")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        Keys(args.run)
        if not args.id or any(c in args.id for c in "/*$?# "):
            raise ValueError(f"bad actor id {args.id!r}")
        if args.episodes < 1 or args.batch < 1:
            raise ValueError("--episodes and --batch must be >= 1")
        if args.max_lead < 8:
            # the learner trains at multiples of 8 (train_freq): a smaller lead could wait forever after a
            # short end-of-episode batch
            raise ValueError("--max-lead must be >= 8 (the learner's train frequency)")
        if args.rt_priority and not (1 <= args.rt_priority <= 99 and args.rate > 0):
            raise ValueError("--rt-priority must be in 1..99 and needs --rate > 0 (a real-time loop must sleep)")
    except ValueError as exc:
        print(f"khgrl actor: error: {exc}", file=sys.stderr)
        return 2
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
