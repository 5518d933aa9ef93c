"""Acks, weights and ``transitions`` batches signed per role (docs/protocol.md, "Trust model").

The run's key (:mod:`~khgrl.common.delivery.run_key`) is shared by every process, so its ``mac`` proves only that a
message comes from *some* process of the run: an actor holds it as well as the learner. With the run's role keys
(:mod:`~khgrl.common.delivery.role_keys`) each message also carries ``signer`` (a key id) and ``sig``: the Ed25519
signature of that key over :func:`signed_bytes` (the signer's id and a BLAKE2b digest of exactly the fields the
``mac`` covers). The learner signs its acks and weights as ``learner:<id>``; each actor signs its batches (and a
re-stamped re-send again) as ``actor:<id>``. A process that has the run's ``public.json`` takes

- acks and weights only when signed by a ``learner:`` key (the learner id it expects, when it knows it);
- a batch of actor X only when signed by ``actor:X``;

so a process holding one role's private key cannot speak as another. The ``mac`` stays: it costs a hash, not a
public-key operation, and is checked first, so a process without the run's key (another user on the router) is
turned away before any signature is verified. A process without role keys (started by hand, no ``keys/``) behaves as
before, with a warning at its start.

:class:`DataKeys` bundles what a process holds; the functions here take it, the bare run key (bytes: only the
``mac``, as before) or None (nothing signed, nothing checked).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Union

from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from khgrl.common.delivery import run_key
from khgrl.common.delivery.role_keys import PublicKeys, key_id, load_private, role_of

__all__ = ["DataKeys", "Keyish", "signed_bytes", "sign", "sign_batch", "wire_sign", "checking", "check", "check_mac",
           "check_sig", "run_of"]

log = logging.getLogger("khgrl.trust")

# the digest's BLAKE2b key: public, it only separates this digest from the run key's mac
_DIGEST_KEY = b"khgrl-role-signed-digest".ljust(32, b"\0")


@dataclass
class DataKeys:
    """What one process holds to sign and check data messages.

    :param run: the run's key (the ``mac``; None: none).
    :param kid: this process's key id (``learner:<id>``, ``actor:<id>``).
    :param private: its private key (None: it signs nothing).
    :param public: the run's public keys (None or empty: nothing is checked for a signature).
    :param peer: the key id that must sign what this process receives, when one is (an actor: ``learner:<id>``);
        None: decided per message (a learner: ``actor:<the batch's actor>``; an actor that does not know the
        learner's id: any ``learner:`` key).
    """

    run: bytes | None = None
    kid: str = ""
    private: Ed25519PrivateKey | None = None
    public: PublicKeys | None = None
    peer: str | None = None

    @classmethod
    def of_run(cls, run_dir: str | Path | None, role: str, ident: str, peer: str | None = None) -> "DataKeys | None":
        """The keys of process ``role:ident`` of the run in ``run_dir`` (None: the run has neither a run key nor role
        keys; a warning when it has no role keys).

        :param run_dir: the run directory.
        :param role: ``learner`` or ``actor``.
        :param ident: the process's id.
        :param peer: the key id that must sign what it receives (an actor: its learner's).
        :raises RunKeyError: ``run.key`` is not a key.
        :raises RoleKeyError: a key file is not one.
        """
        kid = key_id(role, ident)
        run, public = run_key.load(run_dir), PublicKeys(run_dir)
        private = load_private(run_dir, kid)
        if not public.present:
            log.warning("no role keys in %s (khgrl keys RUN_DIR): acks, weights and batches are not signed per role, "
                        "any process with the run's key may speak as the learner or another actor", run_dir)
        elif private is None:
            log.warning("%s has no private key in %s: its messages go unsigned and its peers refuse them", kid,
                        run_dir)
        if run is None and not public.present:
            return None
        return cls(run=run, kid=kid, private=private, public=public if public.present else None, peer=peer)

    @property
    def checking(self) -> bool:
        """Whether received messages must be signed (the run has public keys)."""
        return self.public is not None


Keyish = Union[DataKeys, bytes, None]


def run_of(keys: Keyish) -> bytes | None:
    """The run key in ``keys`` (the ``mac``'s).

    :param keys: :class:`DataKeys`, a bare run key, or None.
    """
    return keys.run if isinstance(keys, DataKeys) else keys


def signed_bytes(signer: str, kind: str, digest: bytes) -> bytes:
    """What a data signature covers: the kind, the signer's key id and the digest of the message's fields.

    :param signer: the signer's key id.
    :param kind: ``ack``, ``weights`` or ``transitions``.
    :param digest: :func:`_digest` of the message.
    """
    return b"khgrl-data\0" + kind.encode() + b"\0" + signer.encode() + b"\0" + digest


def _digest(msg: Any, seq: int | None = None) -> bytes:
    """The digest of exactly the fields the ``mac`` covers (a batch: with its envelope ``seq``)."""
    if msg.KIND == "transitions":
        return run_key.batch_mac(msg, _DIGEST_KEY, msg.envelope.seq if seq is None else seq)
    return run_key.mac_of(msg, _DIGEST_KEY)


def _sig_fields(keys: Keyish, kind: str, digest_of) -> dict:
    if not isinstance(keys, DataKeys) or keys.private is None:
        return {}
    return {"signer": keys.kid, "sig": keys.private.sign(signed_bytes(keys.kid, kind, digest_of()))}


def sign(msg: Any, keys: Keyish) -> Any:
    """An ack or weights message with its ``mac`` and (with a private key) ``signer`` and ``sig`` set.

    :param msg: an :class:`~khgrl.common.wire.messages.Ack` or :class:`~khgrl.common.wire.messages.Weights`.
    :param keys: the sender's keys.
    """
    msg = run_key.sign(msg, run_of(keys))
    extra = _sig_fields(keys, msg.KIND, lambda: _digest(msg))
    return msg.replace(**extra) if extra else msg


def sign_batch(msg: Any, keys: Keyish, seq: int) -> Any:
    """A ``transitions`` batch to be sent with envelope ``seq``, with its ``mac`` and signature set.

    :param msg: the batch.
    :param keys: the actor's keys.
    :param seq: the envelope's seq.
    """
    msg = run_key.sign_batch(msg, run_of(keys), seq)
    extra = _sig_fields(keys, msg.KIND, lambda: _digest(msg, seq))
    return msg.replace(**extra) if extra else msg


def wire_sign(m: dict, keys: Keyish) -> dict:
    """The ``mac``, ``signer`` and ``sig`` of a re-stamped batch as its msgpack map (fields to set).

    :param m: the map (:func:`~khgrl.common.wire.protocol.with_base_seq`).
    :param keys: the actor's keys.
    """
    run = run_of(keys)
    out = {} if run is None else {"mac": run_key.wire_batch_mac(m, run)}
    out.update(_sig_fields(keys, "transitions", lambda: run_key.wire_batch_mac(m, _DIGEST_KEY)))
    return out


def _expected(keys: DataKeys, msg: Any) -> tuple[str | None, str]:
    """The key id that must have signed ``msg`` (None: any of the role) and that role."""
    if msg.KIND == "transitions":
        return key_id("actor", msg.actor), "actor"
    return keys.peer, "learner"


def checking(keys: Keyish) -> bool:
    """Whether ``keys`` make received messages be signed per role.

    :param keys: the receiver's keys.
    """
    return isinstance(keys, DataKeys) and keys.checking


def check(msg: Any, keys: Keyish) -> str | None:
    """Why ``msg`` (a received ack, weights or transitions message) is not authentic: the run key's ``mac`` first
    (a hash), then the signer's signature when the run has role keys. None: it is, or nothing is checked.

    :param msg: the decoded message.
    :param keys: the receiver's keys.
    """
    return check_mac(msg, keys) or check_sig(msg, keys)


def check_mac(msg: Any, keys: Keyish) -> str | None:
    """Why ``msg``'s ``mac`` is not the run key's (None: it is, or there is no run key).

    :param msg: the decoded message.
    :param keys: the receiver's keys.
    """
    return run_key.check(msg, run_of(keys))


def check_sig(msg: Any, keys: Keyish) -> str | None:
    """Why ``msg`` is not signed by the role that may send it (None: it is, or the run has no role keys).

    :param msg: the decoded message.
    :param keys: the receiver's keys.
    """
    if not isinstance(keys, DataKeys) or not keys.checking:
        return None
    want, role = _expected(keys, msg)
    signer = getattr(msg, "signer", None)
    if signer is None or msg.sig is None:
        return f"{msg.KIND} not signed (the run has role keys: {want or role} would sign it)"
    if (want is not None and signer != want) or role_of(signer) != role:
        return f"{msg.KIND} signed by {signer!r}, not by {want or 'a ' + role}"
    return keys.public.verify(signer, msg.sig, signed_bytes(signer, msg.KIND, _digest(msg)))
