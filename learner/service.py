"""``khgrl learner``: the learner process. sb3-contrib TQC (the paper's settings) trained ONLY from the
transition stream that actors publish over Zenoh; publishes the actor network by version; checkpoints and
resumes.

Data path (see docs/protocol.md and ../shared/design/zenoh-notes.md):

* Zenoh callbacks only put raw bytes on a :class:`queue.Queue`; the main loop decodes (every message goes
  through :func:`common.protocol.decode`; a bad one is counted and logged, never fatal), orders each actor's
  batches by ``seq`` (accept ``seq == next``; older: duplicate, re-acked; newer: held in a bounded pending
  dict until the actor re-sends the gap), and adds transitions to the SB3 replay buffer exactly as SB3's
  ``_store_transition`` does for one environment.
* Update-to-data ratio as SB3's ``learn()`` with ``train_freq=8, gradient_steps=8``: one training
  iteration (8 gradient steps) is due for every multiple of 8 in ``(learning_starts, total_ingested]``.
  The learner never trains ahead of the data and never spins on stale data.
* After each iteration the actor network is published on ``learner/weights`` (``version`` + 1, ``trained`` =
  per actor, its running transition index reached when the global count hit the multiple of 8 that made
  the iteration due -- the data SB3's policy would have been trained on at that env step); a queryable on
  the same key answers the latest weights at once (late or restarted actors).
* Acks per actor (``learner/ack/<actor>``): ``received`` (highest contiguous seq), ``durable`` (highest seq in
  a checkpoint), ``trained`` (this actor's transitions covered by the latest weights; all ingested ones
  while the run is still inside ``learning_starts``), ``version``, ``epoch`` (random per incarnation).
  Together with the actor's rate limit (``--max-lead``) this makes the distributed run step-for-step the
  schedule of single-process SB3 (see ``actor/service.py``).
* Checkpoints (``RUN_DIR/learner/checkpoint/``, written to a temporary directory and renamed into place):
  ``model.zip`` (policy, optimisers, entropy coefficient), ``replay_buffer.pkl``, per-buffer-slot arrays
  (intervention / clipped flags and provenance: actor code + the transition's per-actor index) and
  ``state.json`` (stream positions, counters, pending training iterations, weights version). ``--resume``
  continues from it; the replay buffer pickle is our own file on local disk, never anything from the wire.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import queue
import secrets
import shutil
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from common.protocol import ACT_DIM, OBS_DIM, Keys, ProtocolError, RejectCounter, decode, encode
from common.session import StopFlag, install_stop_handlers, open_client, setup_process_logging

__all__ = ["main", "build_parser", "LearnerCore", "SpacesEnv", "passage_spaces", "load_checkpoint_arrays"]

log = logging.getLogger("khgrl.learner")

TRAIN_FREQ = 8  # the paper's train frequency (tqc_kwargs); one iteration = TRAIN_FREQ gradient steps
MAX_PENDING = 4096  # out-of-order batches held per actor
STATE_FILE = "state.json"


# ------------------------------------------------------------------------------------------ spaces
def passage_spaces() -> tuple[spaces.Box, spaces.Box]:
    """PassageEnv's observation and action spaces (common/env.py), without fitting a world (~10 s)."""
    obs = spaces.Box(
        low=np.array([0.0, 0.0, 0.0, -1.0, -1.0], dtype=np.float32),
        high=np.array([1.0, 1.0, 1.0, 1.0, 1.0], dtype=np.float32),
        dtype=np.float32,
    )
    act = spaces.Box(-1.0, 1.0, shape=(ACT_DIM,), dtype=np.float32)
    assert obs.shape == (OBS_DIM,)
    return obs, act


class SpacesEnv(gym.Env):
    """An environment that only has PassageEnv's spaces: the learner never steps an environment."""

    metadata = {"render_modes": []}

    def __init__(self) -> None:
        self.observation_space, self.action_space = passage_spaces()

    def reset(self, *, seed=None, options=None):  # noqa: ARG002
        raise RuntimeError("the learner's environment has spaces only: transitions come from actors")

    def step(self, action):  # noqa: ARG002
        raise RuntimeError("the learner's environment has spaces only: transitions come from actors")


# ------------------------------------------------------------------------------------------ core
@dataclass
class ActorStream:
    """What the learner knows about one actor's transition stream."""

    actor: str
    code: int  # index into LearnerCore.codes (provenance)
    stream: str = ""  # the actor incarnation (transitions' optional "stream" field)
    next_seq: int = 0
    ingested: int = 0  # transitions ingested from this stream
    index: int = 0  # the actor's running index after the last ingested transition (== ingested unless the
    # stream was adopted mid-way by a learner without a checkpoint, see base_seq)
    durable: int = -1  # highest seq held in a checkpoint
    duplicates: int = 0
    held: int = 0
    dropped_pending: int = 0
    skipped: int = 0  # batches the actor no longer holds (see base_seq): lost, logged
    pending: dict = field(default_factory=dict)

    def state(self) -> dict:
        return {"actor": self.actor, "code": self.code, "stream": self.stream, "next_seq": self.next_seq,
                "ingested": self.ingested, "index": self.index, "durable": self.durable, "duplicates": self.duplicates,
                "skipped": self.skipped}


class LearnerCore:
    """Model, replay buffer, stream ordering, training schedule and checkpoints: everything but Zenoh."""

    def __init__(self, run_dir: str | Path, *, seed: int = 0, learning_starts: int = 100, buffer_size: int = 200_000,
                 resume: bool = False, logger_formats: tuple[str, ...] = ("csv", "tensorboard")) -> None:
        from sb3_contrib import TQC
        from stable_baselines3.common.logger import configure

        from learner.reference import tqc_kwargs

        self.dir = Path(run_dir) / "learner"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.ckpt_dir = self.dir / "checkpoint"
        self.learning_starts = int(learning_starts)
        self.epoch = secrets.token_hex(6)
        self.streams: dict[str, ActorStream] = {}
        self.codes: list[dict] = []  # provenance code -> {"actor", "stream"}
        self.total = 0  # transitions ingested, all actors
        self.due: deque = deque()  # (multiple of TRAIN_FREQ, {actor: ingested at that point}) not trained yet
        self.iterations = 0
        self.version = 0
        self.weights_trained: dict[str, int] = {}
        self.last_ckpt_total = 0
        self.checkpoints = 0
        self.resumed_from: str | None = None
        env = SpacesEnv()
        if resume and not self._has_checkpoint():
            log.warning("--resume: no checkpoint under %s yet: starting fresh (actors re-send what they hold)", self.dir)
            resume = False
        if resume:
            self._load(env)
        else:
            kw = tqc_kwargs(seed)
            kw.update(learning_starts=self.learning_starts, buffer_size=int(buffer_size))
            self.model = TQC("MlpPolicy", env, **kw)
            n = self.model.replay_buffer.buffer_size
            self.prov_actor = np.full(n, -1, dtype=np.int32)
            self.prov_step = np.full(n, -1, dtype=np.int64)
            self.flag_intervened = np.zeros(n, dtype=np.uint8)
            self.flag_clipped = np.zeros(n, dtype=np.uint8)
        self.model.set_logger(configure(str(self.dir / "tb"), list(logger_formats)))
        self.model._current_progress_remaining = 1.0  # constant learning rate (tqc_kwargs): value unused

    # ---------------------------------------------------------------- stream ordering
    def offer(self, msg: dict) -> str:
        """A decoded transitions message: 'accepted' (and maybe held ones after it), 'duplicate' or 'held'."""
        a, seq = msg["actor"], msg["seq"]
        stream = msg.get("stream", "")
        base = msg.get("base_seq", 0)
        st = self.streams.get(a)
        if st is None or (stream and st.stream and stream != st.stream):
            if st is not None:
                log.warning("actor %s restarted (stream %s -> %s): new stream from seq %d", a, st.stream, stream, base)
            st = ActorStream(actor=a, code=len(self.codes), stream=stream, next_seq=base)
            self.codes.append({"actor": a, "stream": stream})
            self.streams[a] = st
        elif stream and not st.stream:
            st.stream = stream
        if base > st.next_seq:
            log.error("actor %s no longer holds batches %d..%d (confirmed durable by an earlier learner): skipping them",
                      a, st.next_seq, base - 1)
            st.skipped += base - st.next_seq
            st.next_seq = base
            for s in [s for s in st.pending if s < base]:
                del st.pending[s]
        if seq < st.next_seq:
            st.duplicates += 1
            return "duplicate"
        if seq > st.next_seq:
            if seq not in st.pending:
                if len(st.pending) >= MAX_PENDING:
                    st.dropped_pending += 1  # the actor re-sends it
                    return "held"
                st.pending[seq] = msg
                st.held += 1
            return "held"
        self._ingest(st, msg)
        st.next_seq += 1
        while st.next_seq in st.pending:
            self._ingest(st, st.pending.pop(st.next_seq))
            st.next_seq += 1
        return "accepted"

    def _ingest(self, st: ActorStream, msg: dict) -> None:
        rb = self.model.replay_buffer
        obs, nobs, act, rew = msg["obs"], msg["next_obs"], msg["action"], msg["reward"]
        term, trunc = msg["terminated"].astype(bool), msg["truncated"].astype(bool)
        iv, cl = msg["intervened"], msg["clipped"]
        first = msg["first_step"]
        if first != st.index and (st.ingested or first):
            log.warning("actor %s batch %d starts at its step %d, expected %d", st.actor, msg["seq"], first, st.index)
        for i in range(obs.shape[0]):
            pos = rb.pos
            done = np.array([term[i] or trunc[i]], dtype=np.float32)
            # as SB3's DummyVecEnv + _store_transition: done = terminated or truncated, with the time-limit flag
            rb.add(obs[i][None], nobs[i][None], act[i][None], rew[i:i + 1], done,
                   [{"TimeLimit.truncated": bool(trunc[i] and not term[i])}])
            self.prov_actor[pos] = st.code
            self.prov_step[pos] = first + i
            self.flag_intervened[pos] = iv[i]
            self.flag_clipped[pos] = cl[i]
            st.ingested += 1
            st.index = first + i + 1
            self.total += 1
            if self.total > self.learning_starts and self.total % TRAIN_FREQ == 0:
                self.due.append((self.total, {k: s.index for k, s in self.streams.items()}))

    # ---------------------------------------------------------------- training
    @property
    def training_started(self) -> bool:
        return self.total > self.learning_starts

    def train_one(self) -> bool:
        """Run one due training iteration (8 gradient steps, batch 256); False if none is due."""
        if not self.due:
            return False
        at, snapshot = self.due.popleft()
        self.model.num_timesteps = at
        self.model.train(gradient_steps=self.model.gradient_steps, batch_size=self.model.batch_size)
        self.iterations += 1
        self.version += 1
        self.weights_trained = dict(snapshot)
        return True

    def weights_fields(self) -> dict:
        sd = self.model.policy.actor.state_dict()
        tensors = {k: v.detach().cpu().numpy().astype(np.float32, copy=True) for k, v in sd.items()}
        return {"version": self.version, "epoch": self.epoch, "trained": dict(self.weights_trained), "tensors": tensors}

    def ack_fields(self, actor: str) -> dict:
        st = self.streams[actor]
        # in the actor's own index space (what it compares with the transitions it sent)
        trained = st.index if not self.training_started else min(self.weights_trained.get(actor, 0), st.index)
        out = {"actor": actor, "received": st.next_seq - 1, "durable": st.durable, "trained": int(trained),
               "version": self.version, "epoch": self.epoch}
        if st.stream:
            out["stream"] = st.stream
        return out

    @property
    def gradient_steps(self) -> int:
        return int(self.model._n_updates)

    # ---------------------------------------------------------------- checkpoints
    def save_checkpoint(self) -> Path:
        """Write everything to a temporary directory, then rename it to checkpoint/ (old one kept until then)."""
        t0 = time.perf_counter()
        tmp = self.dir / f"checkpoint.tmp-{os.getpid()}"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
        self.model.save(tmp / "model.zip")
        self.model.save_replay_buffer(tmp / "replay_buffer.pkl")
        np.save(tmp / "provenance_actor.npy", self.prov_actor)
        np.save(tmp / "provenance_step.npy", self.prov_step)
        np.save(tmp / "intervened.npy", self.flag_intervened)
        np.save(tmp / "clipped.npy", self.flag_clipped)
        durable = {a: st.next_seq - 1 for a, st in self.streams.items()}
        rb = self.model.replay_buffer
        state = {
            "format": 1,
            "epoch": self.epoch,
            "time": time.time(),
            "total_ingested": self.total,
            "learning_starts": self.learning_starts,
            "iterations": self.iterations,
            "gradient_steps": self.gradient_steps,
            "version": self.version,
            "weights_trained": self.weights_trained,
            "due": [[at, snap] for at, snap in self.due],
            "codes": self.codes,
            "actors": {a: dict(st.state(), durable=durable[a]) for a, st in self.streams.items()},
            "replay": {"pos": int(rb.pos), "full": bool(rb.full), "size": int(rb.buffer_size)},
        }
        with open(tmp / STATE_FILE, "w") as fh:  # written last: a checkpoint without it is incomplete
            json.dump(state, fh, indent=1)
            fh.flush()
            os.fsync(fh.fileno())
        old = self.dir / "checkpoint.old"
        if old.exists():
            shutil.rmtree(old)
        if self.ckpt_dir.exists():
            os.rename(self.ckpt_dir, old)
        os.rename(tmp, self.ckpt_dir)
        if old.exists():
            shutil.rmtree(old)
        for a, st in self.streams.items():
            st.durable = durable[a]
        self.last_ckpt_total = self.total
        self.checkpoints += 1
        log.info("checkpoint %d: %d transitions, version %d, %d iterations (%.2f s)", self.checkpoints, self.total,
                 self.version, self.iterations, time.perf_counter() - t0)
        return self.ckpt_dir

    def _has_checkpoint(self) -> bool:
        return any((d / STATE_FILE).exists() for d in (self.ckpt_dir, self.dir / "checkpoint.old"))

    def _find_checkpoint(self) -> Path:
        for d in (self.ckpt_dir, self.dir / "checkpoint.old"):
            if (d / STATE_FILE).exists():
                return d
        raise FileNotFoundError(f"--resume: no complete checkpoint under {self.dir}")

    def _load(self, env: gym.Env) -> None:
        from sb3_contrib import TQC

        d = self._find_checkpoint()
        state = json.loads((d / STATE_FILE).read_text())
        self.model = TQC.load(d / "model.zip", env=env, device="cpu")
        self.model.load_replay_buffer(d / "replay_buffer.pkl")
        arrays = load_checkpoint_arrays(d)
        self.prov_actor, self.prov_step = arrays["provenance_actor"], arrays["provenance_step"]
        self.flag_intervened, self.flag_clipped = arrays["intervened"], arrays["clipped"]
        self.total = int(state["total_ingested"])
        self.iterations = int(state["iterations"])
        self.version = int(state["version"])
        self.weights_trained = {k: int(v) for k, v in state["weights_trained"].items()}
        self.due = deque((int(at), {k: int(v) for k, v in snap.items()}) for at, snap in state["due"])
        self.codes = list(state["codes"])
        for a, s in state["actors"].items():
            self.streams[a] = ActorStream(actor=a, code=int(s["code"]), stream=s.get("stream", ""),
                                          next_seq=int(s["next_seq"]), ingested=int(s["ingested"]),
                                          index=int(s.get("index", s["ingested"])),
                                          durable=int(s["durable"]), duplicates=int(s.get("duplicates", 0)),
                                          skipped=int(s.get("skipped", 0)))
        if int(state.get("learning_starts", self.learning_starts)) != self.learning_starts:
            log.warning("resuming with --learning-starts %d (checkpoint: %s)", self.learning_starts, state.get("learning_starts"))
        self.last_ckpt_total = self.total
        self.resumed_from = str(d)
        rb = self.model.replay_buffer
        log.info("resumed from %s: %d transitions (buffer pos %d), version %d, %d iterations, actors %s",
                 d, self.total, rb.pos, self.version, self.iterations,
                 {a: st.next_seq for a, st in self.streams.items()})


def load_checkpoint_arrays(ckpt: str | Path) -> dict[str, np.ndarray]:
    """The per-replay-slot arrays of a checkpoint (provenance_actor, provenance_step, intervened, clipped)."""
    ckpt = Path(ckpt)
    return {name: np.load(ckpt / f"{name}.npy", allow_pickle=False)
            for name in ("provenance_actor", "provenance_step", "intervened", "clipped")}


# ------------------------------------------------------------------------------------------ service
class _Inbox:
    """Zenoh callbacks put (kind, key, bytes) here and return at once; the main loop does the rest."""

    def __init__(self) -> None:
        self.q: queue.Queue = queue.Queue()

    def callback(self, kind: str):
        def cb(sample) -> None:
            self.q.put((kind, str(sample.key_expr), sample.payload.to_bytes()))

        return cb


def run(args: argparse.Namespace) -> int:
    import torch
    import zenoh

    run_dir = Path(args.run_dir)
    (run_dir / "learner").mkdir(parents=True, exist_ok=True)
    setup_process_logging(run_dir / "learner" / "learner.log")
    torch.set_num_threads(max(1, args.threads))
    if args.nice:
        # training yields the CPU to the actors' control loops when they share a machine
        os.nice(args.nice)
    flag = StopFlag()
    install_stop_handlers(flag)
    keys = Keys(args.run)
    core = LearnerCore(run_dir, seed=args.seed, learning_starts=args.learning_starts, buffer_size=args.buffer_size,
                       resume=args.resume)
    rejects = RejectCounter(f"learner/{args.id}")
    inbox = _Inbox()
    counters = {"weights": 0, "ack": 0, "status": 0}
    latest = {"weights": b""}
    latest_lock = threading.Lock()
    stats = {"accepted": 0, "duplicate": 0, "held": 0, "batches": 0, "queries": 0}
    paused = False

    def on_query(query) -> None:
        # answer with the latest weights message (bytes prepared by the main loop); always finalize
        with query:
            with latest_lock:
                blob = latest["weights"]
            if blob:
                query.reply(keys.weights, blob)
            stats["queries"] += 1

    log.info("khgrl learner %s: run %s, epoch %s, learning_starts %d, connecting to %s", args.id, args.run, core.epoch,
             core.learning_starts, args.connect)
    with open_client(args.connect, args.lease_ms) as session:
        decls: list = []
        weights_pub = session.declare_publisher(keys.weights, congestion_control=zenoh.CongestionControl.BLOCK,
                                                priority=zenoh.Priority.DATA)
        status_pub = session.declare_publisher(keys.status("learner", args.id),
                                               congestion_control=zenoh.CongestionControl.DROP,
                                               priority=zenoh.Priority.DATA_LOW)
        ack_pubs: dict[str, Any] = {}
        decls += [weights_pub, status_pub]
        decls.append(session.declare_subscriber(keys.transitions("*"), inbox.callback("transitions")))
        decls.append(session.declare_subscriber(keys.control("learner"), inbox.callback("control")))
        decls.append(session.declare_subscriber(keys.control("all"), inbox.callback("control")))
        decls.append(session.declare_queryable(keys.weights, on_query))

        def publish_weights() -> None:
            blob = encode("weights", args.id, counters["weights"], **core.weights_fields())
            counters["weights"] += 1
            with latest_lock:
                latest["weights"] = blob
            weights_pub.put(blob)

        def ack(actor: str) -> None:
            pub = ack_pubs.get(actor)
            if pub is None:
                pub = ack_pubs[actor] = session.declare_publisher(
                    keys.ack(actor), congestion_control=zenoh.CongestionControl.BLOCK,
                    priority=zenoh.Priority.INTERACTIVE_LOW)
            pub.put(encode("ack", args.id, counters["ack"], **core.ack_fields(actor)))
            counters["ack"] += 1

        def checkpoint() -> None:
            core.save_checkpoint()
            for a in core.streams:
                ack(a)

        publish_weights()  # version 0 (or the resumed version) at start
        for a in core.streams:  # after a resume: actors re-send everything after the checkpoint
            ack(a)
        token = session.liveliness().declare_token(keys.alive("learner", args.id))
        print(f"khgrl learner {args.id} ready (epoch {core.epoch}, version {core.version}, "
              f"{core.total} transitions)", flush=True)

        t_status = time.monotonic()
        last_status_steps, last_status_t = core.gradient_steps, time.monotonic()
        ckpt_requested = False
        train_time = 0.0
        try:
            while not flag:
                touched: set[str] = set()
                # drain what has arrived (bounded, so training and acks interleave with the stream)
                for n in range(512):
                    try:
                        item = inbox.q.get(timeout=0.05 if (n == 0 and (not core.due or paused)) else 0.0)
                    except queue.Empty:
                        break
                    kind, key, payload = item
                    if kind == "transitions":
                        try:
                            msg = decode("transitions", payload)
                            if msg["actor"] != Keys.last_chunk(key, 3):
                                raise ProtocolError(f"actor {msg['actor']!r} published on {key}")
                        except ProtocolError as exc:
                            rejects.reject("transitions", key, exc)
                            continue
                        res = core.offer(msg)
                        stats[res] += 1
                        stats["batches"] += 1
                        touched.add(msg["actor"])
                    else:
                        try:
                            cmd = decode("control", payload)["command"]
                        except ProtocolError as exc:
                            rejects.reject("control", key, exc)
                            continue
                        log.info("control: %s (%s)", cmd, key)
                        if cmd == "stop":
                            flag.set("stop command")
                        elif cmd == "checkpoint":
                            ckpt_requested = True
                        elif cmd in ("pause", "resume"):
                            paused = cmd == "pause"
                for a in sorted(touched):
                    ack(a)
                if flag:
                    break
                if not paused and core.due:
                    t0 = time.perf_counter()
                    core.train_one()
                    dt = time.perf_counter() - t0
                    train_time += dt
                    publish_weights()
                    for a in core.streams:
                        ack(a)
                    lg = core.model.logger
                    lg.record("learner/ingested", core.total)
                    lg.record("learner/version", core.version)
                    lg.record("learner/iteration_s", dt)
                    lg.record("learner/queue_depth", inbox.q.qsize())
                    lg.record("learner/pending_iterations", len(core.due))
                    lg.dump(step=core.total)
                if ckpt_requested or (args.checkpoint_every > 0
                                      and core.total - core.last_ckpt_total >= args.checkpoint_every):
                    ckpt_requested = False
                    checkpoint()
                now = time.monotonic()
                if now - t_status >= 1.0:
                    gs = core.gradient_steps
                    rate = (gs - last_status_steps) / max(now - last_status_t, 1e-9)
                    last_status_steps, last_status_t = gs, now
                    t_status = now
                    info = {
                        "id": args.id, "epoch": core.epoch, "ingested": core.total, "iterations": core.iterations,
                        "gradient_steps": gs, "grad_steps_per_s": round(rate, 2), "version": core.version,
                        "pending_iterations": len(core.due), "queue_depth": inbox.q.qsize(),
                        "rejects": rejects.by_kind(), "paused": paused, "checkpoints": core.checkpoints,
                        "next_seq": {a: st.next_seq for a, st in core.streams.items()},
                        "durable": {a: st.durable for a, st in core.streams.items()},
                        "duplicates": {a: st.duplicates for a, st in core.streams.items()},
                        "weights_queries": stats["queries"],
                    }
                    status_pub.put(encode("status", args.id, counters["status"], role="learner", info=info))
                    counters["status"] += 1
            log.info("stopping (%s): final checkpoint", flag.reason or "stop")
            checkpoint()
        finally:
            for d in decls:
                try:
                    d.undeclare()
                except Exception:  # noqa: BLE001 - best effort on the way out
                    pass
            for p in ack_pubs.values():
                try:
                    p.undeclare()
                except Exception:  # noqa: BLE001
                    pass
            token.undeclare()
    log.info("learner %s done: %d transitions, %d iterations, %d gradient steps (%.1f s training), version %d, "
             "rejected %s", args.id, core.total, core.iterations, core.gradient_steps, train_time, core.version,
             rejects.by_kind())
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="khgrl learner",
                                description="TQC learner: trains from the actors' transition stream, publishes weights.")
    p.add_argument("--run", required=True, help="run id (key prefix khgrl/<run>/)")
    p.add_argument("--connect", required=True, help="router endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--run-dir", required=True, help="run directory; the learner writes RUN_DIR/learner/")
    p.add_argument("--id", default="learner", help="learner id (default %(default)s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resume", action="store_true", help="continue from RUN_DIR/learner/checkpoint")
    p.add_argument("--checkpoint-every", type=int, default=2000, help="checkpoint every N ingested transitions (0: never)")
    p.add_argument("--learning-starts", type=int, default=100, help="transitions before the first training iteration")
    p.add_argument("--buffer-size", type=int, default=200_000, help="replay buffer capacity")
    p.add_argument("--lease-ms", type=int, default=3000, help="Zenoh link lease (liveliness timeout of this process)")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (default %(default)s)")
    p.add_argument("--nice", type=int, default=0, help="lower the learner's CPU priority by N (default %(default)s)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        Keys(args.run)
    except ValueError as exc:
        print(f"khgrl learner: error: {exc}", file=sys.stderr)
        return 2
    try:
        return run(args)
    except FileNotFoundError as exc:
        print(f"khgrl learner: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
