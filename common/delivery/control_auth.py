"""Signed control: who may press, release, stop and confirm ready (docs/protocol.md, "Who may press, release, stop
and confirm ready").

Every ``control`` message -- on ``control/<target>`` from the operator, on ``human/<id>/request`` from a human-input
client -- is made by :meth:`ControlSigner.payload` (the one place control is signed) and checked by
:meth:`ControlGate.check` (the one place it is verified). A signature (Ed25519, :mod:`~khgrl.common.delivery.role_keys`)
covers the key the message is published on (run and target), the command, the envelope's sender, seq and ts, and the
signer's key id. With the run's public keys (``RUN_DIR/keys/public.json``) a receiver takes only:

- on ``control/<target>``: any command signed by the operator's key (``operator:launcher``);
- on ``human/<id>/request``: a command of that client's own key (``human:<id>``) -- the e-stop from any admitted
  client; pause, resume and ready as before (the actor's assignment rules);

and only when its ``ts`` is within :data:`WINDOW_S` of the receiver's clock and its signature was not taken before: a
recorded message replayed later, or again, is refused. Without public keys (a
run without role keys: processes started by hand, no ``khgrl keys``) nothing is checked, as before.
"""

from __future__ import annotations

import time
from pathlib import Path

from khgrl.common.delivery.control_sign import OPERATOR, ControlSigner, signed_bytes
from khgrl.common.delivery.role_keys import PublicKeys, role_of
from khgrl.common.wire.messages import Control
from khgrl.common.wire.protocol import Keys, ProtocolError

WINDOW_S = 10.0  # a signed control message is taken this many seconds either side of the receiver's clock

__all__ = ["OPERATOR", "WINDOW_S", "signed_bytes", "ControlSigner", "ControlGate", "operator_side"]

class ControlGate:
    """Checks the signature, signer and freshness of received control (see the module's docstring).

    :param public: the run's public keys (none: nothing is checked).
    :param window_s: seconds a message's ``ts`` may differ from this clock.
    """

    def __init__(self, public: PublicKeys, window_s: float = WINDOW_S) -> None:
        self.public, self.window_s = public, float(window_s)
        # the signatures taken within the window, with their ts: a message seen before is a replay. (Not "newer than
        # the last one": the operator's processes -- the launcher's heartbeat, khgrl stop -- sign with one key, and
        # the router may deliver one's message before another's older one.)
        self.seen: dict[bytes, float] = {}

    @classmethod
    def of_run(cls, run_dir: str | Path | None) -> "ControlGate":
        """The gate of the run in ``run_dir`` (its ``keys/public.json``).

        :param run_dir: the run directory (None: a gate that checks nothing).
        """
        return cls(PublicKeys(run_dir))

    @property
    def active(self) -> bool:
        """Whether control is checked (the run has role keys)."""
        return self.public.present

    def check(self, msg: Control, key_expr: str) -> str | None:
        """Why ``msg``, received on ``key_expr``, is refused (None: it is taken, and its time remembered).

        :param msg: the decoded control message.
        :param key_expr: the key it came on.
        """
        if not self.public.present:
            return None
        env, signer = msg.envelope, msg.signer
        if msg.sig is None or not signer:
            return f"{msg.command} not signed (this run's control must carry the operator's or a client's signature)"
        why = self._may(signer, msg.command, key_expr)
        if why is None and abs(time.time() - env.ts) > self.window_s:
            why = f"{msg.command} signed {time.time() - env.ts:+.1f} s ago: outside the {self.window_s:g} s window"
        if why is None and bytes(msg.sig) in self.seen:
            why = f"{msg.command} by {signer} taken before (a replay)"
        why = why or self.public.verify(signer, msg.sig,
                                        signed_bytes(key_expr, msg.command, env.sender, env.seq, env.ts, signer))
        if why is None:
            self._remember(bytes(msg.sig), env.ts)
        return why

    def _remember(self, sig: bytes, ts: float) -> None:
        """Keep ``sig`` while its ``ts`` is within the window (older ones are refused by time anyway)."""
        self.seen[sig] = ts
        if len(self.seen) > 256:
            old = time.time() - self.window_s
            self.seen = {k: t for k, t in self.seen.items() if t >= old}

    def admit(self, msg: Control, key_expr: str) -> None:
        """:meth:`check`, raising :class:`ProtocolError` with the reason for a refused message (count it as one).

        :param msg: the decoded control message.
        :param key_expr: the key it came on.
        """
        if why := self.check(msg, key_expr):
            raise ProtocolError(why)

    @staticmethod
    def _may(signer: str, command: str, key_expr: str) -> str | None:
        """Why ``signer`` may not send ``command`` on ``key_expr`` (None: it may)."""
        parts = str(key_expr).split("/")
        if len(parts) == 4 and parts[2] == "control":
            return None if signer == OPERATOR else \
                f"{command} on {key_expr} signed by {signer}: only the operator's key may send control"
        if len(parts) == 5 and parts[2] == "human" and parts[4] == "request":
            client = Keys.chunk(key_expr, 3)
            return None if role_of(signer) == "human" and signer == f"human:{client}" else \
                f"{command} on {key_expr} signed by {signer}: only human client {client!r}'s own key may"
        return f"{command} on {key_expr}: not a control key"


def operator_side(run_dir: str | Path | None, key_file: str | Path | None = None) -> tuple[ControlSigner, ControlGate]:
    """The operator's signer (its key from ``key_file`` or ``RUN_DIR/keys``) and the run's gate: what the launcher and
    ``khgrl stop`` / ``khgrl ready`` use.

    :param run_dir: the run directory.
    :param key_file: an explicit private key file (``khgrl stop --key``).
    :raises RoleKeyError: a key file that is not one.
    """
    return ControlSigner.load(run_dir, OPERATOR, key_file), ControlGate.of_run(run_dir)
