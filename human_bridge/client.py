"""What every human-input client shares (docs/protocol.md): its Zenoh side.

* :class:`CorrectionPublisher` -- the client's correction stream: typed :class:`~khgrl.common.wire.protocol.Correction`
  messages, sequence-numbered, express and high priority. A stream is ``active`` messages with P_h while the
  person (or script) holds the robot, sent for every frame, then one ``active=False`` release.
* :class:`HumanClient` -- one client's subscriptions (frames and whatever else it shows) into an
  :class:`~khgrl.common.delivery.transport.Inbox` that keeps the newest, decoded into typed messages; stop commands on
  ``control/human`` and ``control/all``; its liveliness token; its ``status/human/<id>`` (:class:`HumanInfo`),
  and ``pause`` / ``resume`` for the actors.
* :func:`connected` -- a :class:`HumanClient` on a session to the run's router, closed (holds released) on exit.
"""

from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from typing import Iterator

import numpy as np
from khgrl.common.config.process import ProcessConfig
from khgrl.common.delivery.control_auth import ControlGate, ControlSigner
from khgrl.common.delivery.declare import publisher, put, subscribe, token
from khgrl.common.delivery.senders import HUMAN_COMMANDS
from khgrl.common.delivery.task_link import fetch_task
from khgrl.common.delivery.transport import Inbox, open_client, undeclare_all
from khgrl.common.delivery.vouching import sign_correction
from khgrl.common.process import StopFlag
from khgrl.common.wire.messages import Control, Correction, EpisodeReport, Frame, HumanInfo, Message, Scale, Status
from khgrl.common.wire.protocol import Keys, ProtocolError, RejectCounter, attribute_control, decode, encode
from khgrl.human_bridge.estop import EStopPress

__all__ = ["CorrectionPublisher", "HumanClient", "connected", "read", "KINDS", "fetch_task"]

log = logging.getLogger("khgrl.human")

KINDS: dict[str, type[Message]] = {"frame": Frame, "scale": Scale, "episode": EpisodeReport, "status": Status,
                                   "control": Control}
STATUS_EVERY_S = 1.0


def read(kind: str, key: str, payload: bytes, rejects: RejectCounter) -> Message | None:
    """The typed message of ``kind`` in ``payload``, or None (counted in ``rejects``) if it breaks the protocol."""
    try:
        return decode(KINDS[kind], payload)
    except ProtocolError as exc:
        rejects.reject(kind, key, exc)
        return None


class CorrectionPublisher:
    """Publishes one client's correction stream.

    :param session: the process's Zenoh session.
    :param keys: the run's key expressions.
    :param client: the client id (a key chunk).
    :param private: the client's role key (``human:<client>``): each correction is signed with it, so the learner
        takes the steps it drives as human data (None: unsigned, they become ordinary data where the run has role
        keys; khgrl.common.delivery.vouching).
    """

    def __init__(self, session, keys: Keys, client: str, private=None) -> None:
        self.client, self.private = client, private
        self.seq = 0
        self.sent = 0
        self.active: dict[str, bool] = {}  # actor -> whether our last word to it was a hold
        self._pub = publisher(session, keys.correction(client), congestion="block", priority="interactive_high",
                              express=True)

    def send(self, actor: str, p_h: np.ndarray | None, episode: int = 0, t: int = 0, step: int | None = None) -> None:
        """Hold ``actor``'s desired position at ``p_h`` (2,), or release it (``p_h`` None).

        :param actor: the actor id.
        :param p_h: the desired position in workspace units, or None to release.
        :param episode: the episode of the frame this answers (1-based).
        :param t: the step of that frame.
        :param step: step-addressed (lock-step): P_h (or the release) is for this step of ``episode``; sent even
            when there is nothing to release, since the actor waits for this client's word on every step.
        """
        active = p_h is not None
        if not active and step is None and not self.active.get(actor, False):
            return  # nothing to release
        msg = Correction(client=self.client, actor=actor, active=active,
                         p_h=np.asarray(p_h, dtype=np.float64) if active else None,
                         episode=int(episode), t=int(t), step=None if step is None else int(step))
        self._pub.put(encode(sign_correction(msg, self.private, self.seq), self.client, self.seq))
        self.seq += 1
        self.sent += 1
        self.active[actor] = active

    def release_all(self) -> None:
        """Release every actor still held (on the way out)."""
        for actor, active in list(self.active.items()):
            if active:
                self.send(actor, None)

    def close(self) -> None:
        self._pub.undeclare()


class HumanClient:
    """One human-input client's Zenoh side.

    :param session: the process's Zenoh session.
    :param keys: the run's key expressions.
    :param client: the client id.
    :param flag: the process's stop flag (set by a ``stop`` command).
    :param actor: the actor whose messages to take (``*``: all).
    :param kinds: what to subscribe to of those actors: ``frame``, ``scale``, ``episode``, ``status``.
    """

    def __init__(self, session, keys: Keys, client: str, flag: StopFlag, actor: str = "*",
                 kinds: tuple[str, ...] = ("frame",), signer: ControlSigner | None = None,
                 gate: ControlGate | None = None) -> None:
        self.session, self.keys, self.client, self.flag = session, keys, client, flag
        self.signer = signer or ControlSigner(None, f"human:{client}")  # signs this client's requests
        self.gate = gate or ControlGate.of_run(None)  # checks the stop it gets (the operator's signature)
        self.rejects = RejectCounter(f"human/{client}")
        self.frames = 0
        self.inbox = Inbox(4096, "drop_oldest")  # a viewer needs the newest frames, not every old one
        self.controls = Inbox(64, "drop_newest")
        sel = actor or "*"
        topics = {"frame": keys.frame(sel), "scale": keys.scale(sel), "episode": keys.episode(sel),
                  "status": keys.status("actor", sel)}
        self._decls = [subscribe(session, topics[k], self.inbox.callback(k)) for k in kinds]
        self._decls += [subscribe(session, keys.control(t), self.controls.callback("control"))
                        for t in ("human", "all")]
        self.estop = EStopPress(lambda: self._request("estop"), f"human client {client}")  # repeated until confirmed
        self._decls.append(subscribe(session, keys.status("actor", "*"), self.estop.on_status))
        self._decls.append(token(session, keys.alive("human", client)))
        self._status = publisher(session, keys.status("human", client), congestion="drop")
        self._decls.append(self._status)
        self.pub = CorrectionPublisher(session, keys, client, self.signer.key)
        self._status_seq = 0
        self._control_seq = 0
        self._t_status = time.monotonic()

    def next(self, timeout: float = 0.0) -> tuple[str, Message] | None:
        """The next valid message as ``(key, message)``, waiting up to ``timeout`` s; None if there is none.
        Control messages are handled here (``stop`` sets the stop flag) and not returned."""
        self._handle_controls()
        item = self.inbox.get(timeout)
        if item is None:
            return None
        kind, key, payload, _ = item
        msg = read(kind, key, payload, self.rejects)
        if msg is None:
            return None
        self.frames += isinstance(msg, Frame)
        return key, msg

    def _handle_controls(self) -> None:
        while (item := self.controls.get()) is not None:
            msg = read("control", item[1], item[2], self.rejects)
            if msg is not None and (why := self.gate.check(msg, item[1])):
                self.rejects.reject("control", item[1], ProtocolError(why))
            elif msg is not None and msg.command == "stop":
                attribute_control(msg, item[1], log)
                self.flag.set("stop command")

    def publish_status(self, force: bool = False) -> None:
        """``status/human/<id>`` about once a second (:class:`HumanInfo`: frames, corrections, rejects); and the e-stop
        press again while the actors have not confirmed it (:class:`~khgrl.human_bridge.estop.EStopPress`)."""
        self.estop.tick()
        now = time.monotonic()
        if not force and now - self._t_status < STATUS_EVERY_S:
            return
        self._t_status = now
        info = HumanInfo(frames=self.frames, corrections=self.pub.sent, rejects=self.rejects.by_kind())
        self._status.put(encode(Status(role="human", info=info), self.client, self._status_seq))
        self._status_seq += 1

    def control_actors(self, command: str) -> None:
        """Ask the actors to ``pause`` or ``resume`` or say ``ready``, or press the e-stop (``estop``: every actor
        holds its robot until the operator releases it, ``khgrl stop --release``; repeated until confirmed), on this
        client's own ``human/<id>/request``."""
        if command not in HUMAN_COMMANDS:
            raise ValueError(f"a human-input client may only pause or resume the actors or press the e-stop, not "
                             f"{command!r}")
        if command == "estop":
            self.estop.press()
        else:
            self._request(command)

    def _request(self, command: str) -> None:
        key = self.keys.human_request(self.client)
        put(self.session, key, self.signer.payload(key, command, self.client, self._control_seq), congestion="block",
            priority="interactive_high", express=True)
        self._control_seq += 1

    def close(self) -> None:
        """Release every hold, then undeclare everything."""
        try:
            self.pub.release_all()
        finally:
            undeclare_all(*self._decls)
            self.pub.close()


@contextmanager
def connected(proc: ProcessConfig, client: str, flag: StopFlag, actor: str = "*",
              kinds: tuple[str, ...] = ("frame",)) -> Iterator[HumanClient]:
    """A :class:`HumanClient` on a session to the run's router; waits for the router until ``flag`` is set or for
    the connect timeout (``--connect-timeout``; :class:`ConnectionError` then, naming the endpoint).

    :param proc: the resolved process configuration (run id, endpoint, lease).
    :param client: the client id.
    :param flag: the process's stop flag.
    :param actor: the actor to follow (``*``: all).
    :param kinds: what to subscribe to (see :class:`HumanClient`).
    """
    run_dir = proc.cfg.run_dir  # this client's signing key and the run's public keys (RUN_DIR/keys)
    signer, gate = ControlSigner.load(run_dir, f"human:{client}"), ControlGate.of_run(run_dir)
    with open_client(proc.endpoint, proc.cfg.stream.lease_ms, stop=lambda: bool(flag),
                     timeout=proc.cfg.connect_timeout, zenoh_config=proc.zenoh_config) as session:
        link = HumanClient(session, Keys(proc.run), client, flag, actor, kinds, signer, gate)
        try:
            yield link
        finally:
            link.close()
