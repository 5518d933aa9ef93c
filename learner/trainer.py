"""The learner's algorithm (TQC by default, :mod:`khgrl.learner.algorithm`) and its training schedule:
transitions into the replay buffer, due training iterations, and what the weights and ack messages say about
them.

Update-to-data ratio as SB3's ``learn()`` with ``train_freq`` F and ``gradient_steps`` G (the paper: 8 and 8):
one training iteration (G gradient steps) is due for every multiple of F in ``(learning_starts, ingested]``.
The learner never trains ahead of the data and never spins on stale data. After an iteration the weights
carry, per actor, its running transition index reached when the global count hit the multiple of F that
made the iteration due -- the data SB3's policy would have been trained on at that environment step. An
iteration samples only the first transitions up to the one that made it due (``sample_limit``), so what it
learns does not depend on how many more arrived meanwhile (the learner stores batches in another thread).

An iteration that leaves a training loss or a parameter NaN or infinite is rolled back: the algorithm is
restored from the in-memory snapshot taken before it (:meth:`~khgrl.learner.algorithm.LearnerAlgorithm.snapshot`),
so non-finite weights are never published or checkpointed (status ``rollbacks``). So is an iteration after which
the critic's Q goes beyond what the task's reward bound and gamma allow (:mod:`khgrl.learner.critic_watch`; the
summary's ``q_rollbacks``).

In ``robot`` mode (actors never wait) there is no schedule: :meth:`Trainer.train_now` trains on everything
stored so far whenever the learner is free, and the status reports the update-to-data ratio achieved.

One module of ~310 lines on purpose: the algorithm's construction and its training schedule, which share the replay
buffer and the version counter.
"""

from __future__ import annotations

import ctypes
import logging
import secrets
from collections import deque
from pathlib import Path
from typing import Any, Callable

import numpy as np
from khgrl.common.config.settings import TQCSettings
from khgrl.common.delivery.ingest import ActorStream
from khgrl.common.wire.protocol import Ack, Transitions, Weights
from khgrl.learner.algorithm import DEFAULT, LearnerAlgorithm, algorithm_class
from khgrl.learner.critic_watch import CriticWatch
from khgrl.learner.replay import StreamReplayBuffer

__all__ = ["Trainer", "build_algorithm", "build_model", "torch_device", "keep_freed_memory"]

log = logging.getLogger("khgrl.learner")

# glibc malloc parameters (malloc.h): the learner keeps the memory a training iteration frees (keep_freed_memory)
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD = 32 * 2**20  # the highest value glibc's own dynamic threshold reaches (64-bit)
TRIM_THRESHOLD = 2 * MMAP_THRESHOLD  # glibc's dynamic rule: twice the mmap threshold


def keep_freed_memory() -> bool:
    """Make this process's malloc keep the memory a training iteration frees for the next one, rather than hand it
    back to the kernel and fault it in again. Returns whether it was set (False where the C library is not glibc).

    torch's CPU tensors come from malloc. A TQC iteration (8 gradient steps, minibatch 256, 2 x 256 networks)
    allocates and frees tens of MB in tensors of 0.1-2 MB. glibc starts with a 128 kB mmap threshold and trims
    the heap whenever 256 kB lie free at its top; it raises both only after it happens to free a large mmapped
    block. A learner process stayed at the low values: every iteration mapped, faulted in (13,000-17,000 minor
    page faults) and returned its tensors' memory again -- about 15 % of the time inside ``train()``, which
    made the learner slower than standalone SB3 in a process that had freed a large block before. The two
    thresholds are set to what glibc's own adaptation reaches at most (mmap 32 MB, trim twice that): memory
    the learner frees stays in the process up to that much.
    """
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))


def torch_device(name: str) -> str:
    """The torch device ``name`` (``TQCSettings.device``) means on this machine: 'auto' is cuda where torch sees a
    GPU, else cpu.

    :param name: 'auto', 'cpu' or 'cuda'
    :raises ValueError: 'cuda' where torch sees no GPU (SB3 would quietly fall back to the CPU)
    """
    import torch

    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device cuda: torch {torch.__version__} sees no CUDA device on this machine (built for "
                         f"CUDA {torch.version.cuda}); use --device cpu or auto")
    return "cuda" if name == "cuda" or (name == "auto" and torch.cuda.is_available()) else "cpu"


def build_algorithm(tqc: TQCSettings, seed: int, task=None, algo: str = DEFAULT) -> LearnerAlgorithm:
    """A fresh learner algorithm (``--algo``) with the run's settings on the task's spaces, on the device
    ``tqc.device`` means here.

    :param tqc: the learner settings (``khgrl.common.config.settings.TQCSettings``)
    :param seed: the model's seed
    :param task: the run's :class:`~khgrl.common.wire.descriptor.TaskDescriptor` (None: the passage world's spaces)
    :param algo: the registered algorithm's name (:data:`khgrl.learner.algorithm.REGISTRY`)
    """
    return algorithm_class(algo).build(task, tqc, seed, torch_device(tqc.device))


def build_model(tqc: TQCSettings, seed: int, task=None):
    """The SB3 model of a fresh ``tqc`` algorithm (:func:`build_algorithm`): sb3-contrib TQC whose replay buffer is
    a :class:`StreamReplayBuffer` (which draws no random numbers: the seeded model is SB3's own).

    :param tqc: the TQC settings
    :param seed: the model's seed
    :param task: the run's task descriptor (None: the passage world's spaces)
    """
    return build_algorithm(tqc, seed, task).model


def _frames(msg: Transitions) -> dict[str, Any]:
    """A camera batch's ``frames``, ``obs_frame`` and ``next_frame`` for the algorithm's ``store`` (none: a vector
    batch's, stored as before)."""
    if msg.frames is None:
        return {}
    return {"frames": msg.frames, "obs_frame": msg.obs_frame, "next_frame": msg.next_frame}


class Trainer:
    """Owns the learner algorithm (:class:`~khgrl.learner.algorithm.LearnerAlgorithm`): stores transitions, keeps
    the schedule of due iterations, trains them, and reports what the latest weights cover. One per learner
    incarnation (``epoch``)."""

    def __init__(self, algo: LearnerAlgorithm, *, learning_starts: int, train_freq: int, log_dir: str | Path,
                 logger_formats: tuple[str, ...] = ("csv", "tensorboard"), reward_bound: float | None = None) -> None:
        """:param algo: the algorithm (:func:`build_algorithm`, or loaded from a checkpoint)
        :param learning_starts: transitions before the first training iteration
        :param train_freq: transitions per training iteration
        :param log_dir: where the algorithm's SB3 logger writes (csv, TensorBoard)
        :param logger_formats: SB3 logger output formats
        :param reward_bound: the task's reward bound: the critic is watched against it (None: not watched)
        """
        self.algo = algo
        self.learning_starts = int(learning_starts)
        self.train_freq = int(train_freq)
        self.epoch = secrets.token_hex(6)
        self.total = 0  # transitions ingested, all actors
        self.due: deque[tuple[int, dict[str, int]]] = deque()  # (multiple of train_freq, positions) not trained yet
        self.iterations = 0
        self.gradient_steps = 0
        self.version = 0
        self.weights_trained: dict[str, int] = {}
        self.rollbacks = 0  # iterations rolled back (a loss or parameter went non-finite)
        self.last_rollback = ""  # what was not finite the last time
        self.watch = CriticWatch(reward_bound) if reward_bound is not None else None
        self.schedule = True  # simulation mode: iterations come due with the data; robot mode: train_now
        algo.set_logger(Path(log_dir), logger_formats)

    @property
    def buffer(self) -> StreamReplayBuffer:
        """The algorithm's replay buffer."""
        return self.algo.buffer

    @property
    def training_started(self) -> bool:
        """More than ``learning_starts`` transitions are in: training iterations come due."""
        return self.total > self.learning_starts

    @property
    def first_due(self) -> int:
        """The transition count at which the first training iteration comes due: the first multiple of
        ``train_freq`` past ``learning_starts``."""
        return (self.learning_starts // self.train_freq + 1) * self.train_freq

    # ------------------------------------------------------------------------------------ data
    def add(self, msg: Transitions, stream: ActorStream, positions: Callable[[], dict[str, int]]) -> None:
        """Store one accepted batch as SB3's ``_store_transition`` would, transition by transition, for one
        environment (done = terminated or truncated, ``TimeLimit.truncated`` for the time limit; in one
        :meth:`~khgrl.learner.replay.StreamReplayBuffer.add_batch`), and note each iteration that becomes due.

        :param msg: the batch
        :param stream: its actor's stream (provenance code, running index)
        :param positions: every actor's running index now (the due iteration's ``trained`` snapshot)
        """
        first = msg.first_step
        if first != stream.index and (stream.ingested or first):
            log.warning("actor %s batch %d starts at its step %d, expected %d", stream.actor, msg.envelope.seq, first,
                        stream.index)
        term, trunc = msg.terminated.astype(bool), msg.truncated.astype(bool)
        rb = self.buffer
        with rb.lock:  # one batch at a time between the training thread's minibatches
            self._add(msg, stream, positions, term, trunc)

    def _add(self, msg: Transitions, stream: ActorStream, positions, term: np.ndarray, trunc: np.ndarray) -> None:
        n, first, base = msg.n, msg.first_step, self.total
        self.algo.store(msg.obs, msg.next_obs, msg.action, msg.reward, (term | trunc).astype(np.float32),
                        (trunc & ~term).astype(np.float32), intervened=msg.intervened, clipped=msg.clipped,
                        actor=stream.code, first_step=first, **_frames(msg))
        if self.schedule:  # an iteration comes due at every multiple of train_freq past learning_starts
            lo = max(base, self.learning_starts) + 1
            for at in range(-(-lo // self.train_freq) * self.train_freq, base + n + 1, self.train_freq):
                snapshot = positions()
                snapshot[stream.actor] = first + (at - base)  # this stream's index when the count reached ``at``
                self.due.append((at, snapshot))
        stream.stored(first + n - 1, n)
        self.total += n

    # ------------------------------------------------------------------------------------ training
    def train_one(self) -> bool:
        """Run one due training iteration (``gradient_steps`` steps on minibatches of ``batch_size``);
        False if none is due."""
        with self.buffer.lock:  # (the ingest thread appends under it)
            if not self.due:
                return False
            at, snapshot = self.due.popleft()
        self._train(at, snapshot, limit=at)
        return True

    def train_now(self, positions: dict[str, int]) -> bool:
        """Robot mode: one iteration on everything stored so far (False inside ``learning_starts``).

        :param positions: every actor's running index now (what these weights are trained on)
        """
        if not self.training_started:
            return False
        self._train(self.total, positions, limit=None)
        return True

    @property
    def utd(self) -> float:
        """Gradient steps per transition ingested after ``learning_starts`` (the paper's: G/F = 1)."""
        return self.gradient_steps / max(1, self.total - self.learning_starts)

    def _train(self, at: int, snapshot: dict[str, int], limit: int | None) -> None:
        """One iteration; rolled back if it left a loss or a parameter non-finite (:meth:`_iterate`). Either way
        it counts as done (the weights that follow are the last good ones), so that the schedule and the actors'
        flow control go on."""
        fault = self._iterate(at, limit)
        if fault is not None:
            self.rollbacks += 1
            self.last_rollback = fault
            if self.rollbacks <= 10 or self.rollbacks % 100 == 0:
                log.warning("training iteration %d (at transition %d) rolled back: %s is not finite; networks and "
                            "optimisers restored to before it, so no non-finite weights are published or "
                            "checkpointed (%d rollbacks in this learner)", self.iterations + 1, at, fault,
                            self.rollbacks)
        self.iterations += 1
        self.gradient_steps += self.algo.gradient_steps
        self.version += 1
        self.weights_trained = dict(snapshot)

    def _iterate(self, at: int, limit: int | None) -> str | None:
        """``gradient_steps`` gradient steps from a snapshot of the algorithm; if they leave a loss or a parameter
        non-finite, the snapshot is restored and that is returned (None: the iteration stands). A NaN parameter
        can also make the iteration raise (torch refuses a distribution of NaN): that is a fault too."""
        before = self.algo.snapshot()
        try:
            self.algo.train(self.algo.gradient_steps, timestep=at, sample_limit=limit)
            fault = self.algo.fault()
        except (ValueError, RuntimeError) as exc:
            fault = self.algo.fault()
            if fault is None:  # not a numerical fault: a bug, raised
                raise
            fault = f"{fault} ({type(exc).__name__} in the iteration)"
        if fault is not None:
            self.algo.restore(before)
        elif self.watch is not None and self.watch.check(self.algo, limit) is not None:
            self.algo.restore(before)  # (counted and logged by the watch; not a non-finite ``rollbacks``)
        return fault

    @property
    def q_rollbacks(self) -> int:
        """Iterations rolled back for a critic's Q beyond the task's bound (:mod:`khgrl.learner.critic_watch`)."""
        return 0 if self.watch is None else self.watch.rollbacks

    def record_iteration(self, seconds: float, queue_depth: int) -> None:
        """Training scalars after an iteration (SB3 logger: csv and TensorBoard).

        :param seconds: how long the iteration took
        :param queue_depth: messages waiting in the learner's inbox
        """
        lg = self.algo.logger
        lg.record("learner/ingested", self.total)
        lg.record("learner/version", self.version)
        lg.record("learner/iteration_s", seconds)
        lg.record("learner/queue_depth", queue_depth)
        lg.record("learner/pending_iterations", len(self.due))
        lg.record("learner/prior_share", self.buffer.prior_share)  # of the transitions sampled so far (RLPD: 0.5)
        lg.record("learner/prior_slots", self.buffer.prior_slots())  # stored transitions with intervened = 1
        lg.dump(step=self.total)

    # ------------------------------------------------------------------------------------ messages
    def weights(self) -> Weights:
        """The actor network of the latest version, and the transitions per actor it was trained on."""
        return Weights(version=self.version, trained=dict(self.weights_trained), tensors=self.algo.policy_weights(),
                       epoch=self.epoch)

    def ack(self, stream: ActorStream) -> Ack:
        """What the learner holds of one actor's stream, in the actor's own index space.

        ``trained`` before the first iteration comes due (:attr:`first_due` transitions: inside ``learning_starts``
        and up to the next multiple of ``train_freq``): what is ingested, rounded down to a multiple of
        ``train_freq`` -- as trained on, since the initial weights are what SB3 acts with there. Not rounded,
        an episode ending off the grid (Fetch: 100 steps, ``learning_starts`` 100) let the actor run ``max_lead``
        past its short last batch: past the first due iteration (104) with the initial weights whenever the ack
        of the batch that made it due came late -- a seeded run that depended on timing. On the grid, the actor
        waits at the first due step for that iteration as at every later one (``max_lead >= train_freq``: it
        never waits for an iteration that cannot come). Counted from ``learning_starts`` instead (0 as soon as
        more than ``learning_starts`` are in), an episode ending between the two (Panda: 43 + 60 = 103 steps)
        left the actor waiting for weights at 103 and the learner for its 104th transition: a deadlock.

        :param stream: the actor's stream
        """
        if self.total >= self.first_due:
            trained = min(self.weights_trained.get(stream.actor, 0), stream.index)
        else:  # before the first iteration is due: what is ingested, down to the training grid (the docstring)
            trained = stream.index - stream.index % self.train_freq
        return Ack(actor=stream.actor, received=stream.next_seq - 1, durable=stream.durable, trained=int(trained),
                   version=self.version, epoch=self.epoch, stream=stream.stream or None)

    # ------------------------------------------------------------------------------------ checkpoints
    def state(self) -> dict[str, Any]:
        """Counters and the schedule for a checkpoint."""
        rb = self.buffer
        return {"algo": self.algo.name, "epoch": self.epoch, "total_ingested": self.total,
                "learning_starts": self.learning_starts,
                "iterations": self.iterations, "gradient_steps": self.gradient_steps, "version": self.version,
                "weights_trained": dict(self.weights_trained), "due": [[at, snap] for at, snap in self.due],
                "replay": {"pos": int(rb.pos), "full": bool(rb.full), "size": int(rb.buffer_size)},
                "sampled": {"prior": int(rb.sampled_prior), "online": int(rb.sampled_online)}}

    def restore(self, state: dict[str, Any]) -> None:
        """Continue from a checkpoint's counters and schedule (the model and its buffer are loaded already; the
        buffer's sample counters as the state says, where it says: a model checkpoint's are newer than its buffer's).

        :param state: the checkpoint's state map
        """
        self.total = int(state["total_ingested"])
        self.iterations = int(state["iterations"])
        self.gradient_steps = int(state["gradient_steps"])
        self.version = int(state["version"])
        self.weights_trained = {k: int(v) for k, v in state["weights_trained"].items()}
        self.due = deque((int(at), {k: int(v) for k, v in snap.items()}) for at, snap in state["due"])
        sampled = state.get("sampled")  # (not in the state of an older learner: the buffer's own counters stand)
        if isinstance(sampled, dict):
            self.buffer.sampled_prior, self.buffer.sampled_online = int(sampled["prior"]), int(sampled["online"])
        saved = int(state.get("learning_starts", self.learning_starts))
        if saved != self.learning_starts:
            log.warning("resuming with learning_starts %d (checkpoint: %d)", self.learning_starts, saved)
