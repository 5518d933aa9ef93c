"""Human data vouched for by a human (issue 34, point 6; docs/protocol.md, "Trust model").

A transition flagged ``intervened`` is the learner's prior data (half of every minibatch under ``--sampling rlpd``)
and is exempt from the replay guard, so the flag must not be the sender's word alone: any process holding an actor
key could set it. Here it counts only with evidence that a human drove the row:

* a human-input client signs each correction it sends with its role key ``human:<client>``
  (:func:`sign_correction`: the correction's fields, the actor it is for and its envelope ``seq``);
* the actor keeps, per intervened row, the signed correction that drove it and ships it in the batch's ``vouch``
  (:func:`evidence`, about 110 bytes a row; covered by the batch's ``mac`` and the actor's signature);
* the learner (:class:`Vouching`) stores a row flagged intervened as prior data only when its evidence is a valid
  signature of a key ``human:*`` of the run over a correction *for this batch's actor*; any other such row is stored
  as ordinary data (``intervened`` cleared, counted ``unvouched``). A signed correction vouches for at most
  :data:`ROWS_PER_WORD` rows (a live hold spans a few steps); one already used by another actor makes the batch a
  replay: refused whole, like the replay guard's (a one-ulp change does not make it new evidence).

The run's own demonstrations (:mod:`khgrl.actor.demos`: actor ``a0`` replays them first on its stream) carry the
evidence ``(row,)``: taken only from ``a0`` and only for its first ``demos x horizon`` running indices.

Limit: a physical push (robot mode, a hand on the arm: :mod:`khgrl.actor.physical`) carries no human signature, so
its steps become ordinary data. A learner without the run's role keys checks nothing (the flag counts, as before).
"""

from __future__ import annotations

import json
from collections import Counter, OrderedDict
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from khgrl.common.delivery.role_keys import PublicKeys, key_id, role_of
from khgrl.common.wire.batch import DEMO_ENTRY, Evidence

__all__ = ["correction_bytes", "sign_correction", "evidence", "DEMO", "Verdict", "Vouching", "ROWS_PER_WORD",
           "FIRST_ACTOR", "demo_rows"]

ROWS_PER_WORD = 64  # rows one signed correction may vouch for (a live hold: until the next word or the 0.5 s timeout)
USED_TABLE = 65_536  # signed corrections remembered (which actor used each, how many rows)
FIRST_ACTOR = "a0"  # the actor that replays the run's demonstrations (khgrl.actor.demos)
DEMO = object()  # the word that drives a demonstration row (its entry is (row,): see :func:`evidence`)


def correction_bytes(client: str, actor: str, active: bool, p_h: Any, episode: int | None, t: int | None,
                     step: int | None, seq: int) -> bytes:
    """What a correction's signature covers (canonical JSON; ``p_h`` as float64 reprs).

    :param client: the human-input client's id (its key is ``human:<client>``).
    :param actor: the actor the correction is for.
    :param active: a hold (True) or a release.
    :param p_h: the held position (None for a release).
    :param episode: the frame's episode it answers.
    :param t: that frame's step.
    :param step: the step it is addressed to (lock-step), or None.
    :param seq: its envelope's seq (each word of a client signed apart).
    """
    ph = None if p_h is None else [float(v) for v in np.asarray(p_h, dtype=np.float64).reshape(-1)]
    return json.dumps(["khgrl-correction", key_id("human", client), actor, bool(active), ph, episode, t, step,
                       int(seq)], separators=(",", ":"), ensure_ascii=True).encode()


def sign_correction(msg: Any, private: Any, seq: int) -> Any:
    """``msg`` (a :class:`~khgrl.common.wire.messages.Correction` to be sent with envelope ``seq``) with its ``sig``
    (unchanged without a key).

    :param msg: the correction.
    :param private: the client's Ed25519 private key (None: unsigned).
    :param seq: the envelope's seq.
    """
    if private is None:
        return msg
    data = correction_bytes(msg.client, msg.actor, msg.active, msg.p_h, msg.episode, msg.t, msg.step, seq)
    return msg.replace(sig=private.sign(data))


def evidence(row: int, word: Any | None) -> Evidence | None:
    """The ``vouch`` entry of a batch row: the signed correction ``word`` that drove it (an active, signed
    :class:`~khgrl.common.wire.messages.Correction` as received, with its envelope), ``(row,)`` for a demonstration
    (``word`` :data:`DEMO`), None without evidence (unsigned, a physical push).

    :param row: the row's index in its batch.
    :param word: the correction, or :data:`DEMO`.
    """
    if word is DEMO:
        return (row,)
    if word is None or getattr(word, "sig", None) is None or not word.active or word.envelope is None:
        return None
    p_h = tuple(float(v) for v in np.asarray(word.p_h, dtype=np.float64).reshape(-1))
    return (row, word.client, int(word.envelope.seq), word.episode, word.t, word.step, p_h, word.sig)


def demo_rows(task: Any, teacher_demos: int = 0) -> int:
    """How many running indices of ``a0``'s stream may be demonstrations: the task's demos and the teacher's
    (``--teacher-demos``: whole episodes) x the longest episode.

    :param task: the run's :class:`~khgrl.common.wire.descriptor.TaskDescriptor`.
    :param teacher_demos: demonstrations the scripted teacher records before the first episode
        (:mod:`khgrl.actor.teach`).
    """
    demos = np.asarray(task.demos)
    n, length = (int(demos.shape[0]), int(demos.shape[1])) if demos.ndim == 3 else (0, 0)
    return (n + max(0, int(teacher_demos))) * max(int(task.horizon), length)


@dataclass
class Verdict:
    """What :meth:`Vouching.judge` says of a batch: the batch to store (unvouched rows' ``intervened`` cleared), the
    counts, the actor whose evidence it replays (None: not a replay) and whether every row is vouched (then the
    replay guard lets an identical batch of another actor pass)."""

    batch: Any
    vouched: int = 0
    demo: int = 0
    unvouched: int = 0
    replay_of: str | None = None
    why: str = ""  # the first reason a row was not vouched
    all_vouched: bool = False
    words: list[bytes] = field(default_factory=list)  # signatures used, one per vouched row


class Vouching:
    """The learner's check of intervened rows (the module docstring).

    :param public: the run's public keys (None or empty: nothing is checked, the flag counts as before).
    :param demo_limit: running indices of ``a0`` that may be demonstrations (:func:`demo_rows`).
    :param size: signed corrections remembered.
    """

    def __init__(self, public: PublicKeys | None, demo_limit: int = 0, size: int = USED_TABLE) -> None:
        self.public = public if public is not None and public.present else None
        self.demo_limit, self.size = int(demo_limit), int(size)
        self.used: OrderedDict[bytes, list] = OrderedDict()  # signature -> [actor, rows vouched]
        self.counts: Counter = Counter()  # vouched, demo, unvouched rows; replays (batches)

    @property
    def enforced(self) -> bool:
        """Whether rows need evidence (the run has role keys)."""
        return self.public is not None

    def judge(self, msg: Any) -> Verdict:
        """Which intervened rows of ``msg`` are vouched for (nothing is remembered until :meth:`stored`).

        :param msg: a received, authentic ``transitions`` batch.
        """
        iv = np.asarray(msg.intervened, dtype=bool)
        if not self.enforced:
            return Verdict(msg, vouched=int(iv.sum()), all_vouched=bool(iv.all()))
        entries = list(msg.vouch or ())
        for e in entries:
            used = self.used.get(e[-1]) if len(e) != DEMO_ENTRY else None
            if used is not None and used[0] != msg.actor:
                return Verdict(msg, replay_of=used[0], why=f"a correction signed for actor {used[0]}")
        ok, v = np.zeros(iv.shape, dtype=bool), Verdict(msg)
        pending: Counter = Counter()
        for e in entries:
            row = e[0]
            if not iv[row]:
                continue
            why = self._demo(msg, row) if len(e) == DEMO_ENTRY else self._word(msg.actor, e, pending)
            if why:
                v.why = v.why or why
                continue
            ok[row] = True
            if len(e) == DEMO_ENTRY:
                v.demo += 1
            else:
                v.words.append(e[-1])
        v.vouched = int(ok.sum())
        v.unvouched = int(iv.sum()) - v.vouched
        if v.unvouched and not v.why:
            v.why = "no evidence"
        v.all_vouched = bool(ok.all())
        if v.unvouched:
            v.batch = msg.replace(intervened=(iv & ok).astype(np.uint8))
        return v

    def _demo(self, msg: Any, row: int) -> str:
        """Why a demonstration entry does not vouch for ``row`` ("" : it does)."""
        if msg.actor != FIRST_ACTOR:
            return f"a demonstration entry from actor {msg.actor} (only {FIRST_ACTOR} replays them)"
        if msg.first_step + row >= self.demo_limit:
            return f"a demonstration entry at running index {msg.first_step + row} (demonstrations end before " \
                   f"{self.demo_limit})"
        return ""

    def _word(self, actor: str, e: Evidence, pending: Counter) -> str:
        """Why the signed correction ``e`` does not vouch for a row of ``actor`` ("" : it does)."""
        row, client, seq, episode, t, step, p_h, sig = e
        used = self.used.get(sig)
        if (used[1] if used else 0) + pending[sig] >= ROWS_PER_WORD:
            return f"a correction used for more than {ROWS_PER_WORD} rows"
        if used is None and pending[sig] == 0:
            kid = key_id("human", client)
            if role_of(kid) != "human":
                return f"signed by {kid!r}, not a human client"
            why = self.public.verify(kid, sig, correction_bytes(client, actor, True, p_h, episode, t, step, seq))
            if why:
                return why
        pending[sig] += 1
        return ""

    def stored(self, verdict: Verdict, actor: str) -> None:
        """The batch of ``verdict`` went into the replay buffer: remember its signed corrections and count.

        :param verdict: :meth:`judge`'s.
        :param actor: the batch's actor id.
        """
        for sig in verdict.words:
            entry = self.used.setdefault(sig, [actor, 0])
            entry[1] += 1
            self.used.move_to_end(sig)
        while len(self.used) > self.size:
            self.used.popitem(last=False)
        self.counts.update(vouched=verdict.vouched, demo=verdict.demo, unvouched=verdict.unvouched)
