"""A signing key per role (Ed25519): who is the operator, a human-input client, an actor or the learner, without
trusting the network (docs/protocol.md, "Trust model").

The run's key (:mod:`~khgrl.common.delivery.run_key`) is shared by every process of a run, so it proves only that a
message comes from *some* process of the run. A role key proves *which*: each process holds only its own private key
and every process the public keys of all. ``khgrl up`` (and ``khgrl keys`` for processes started by hand) writes

- ``RUN_DIR/keys/public.json``: ``{"v": 1, "keys": {KEY_ID: hex public key}}`` (mode 0644: public);
- ``RUN_DIR/keys/<role>-<id>.key``: one private key each (32 raw bytes, mode 0600).

A key's id is ``<role>:<id>`` (:func:`key_id`): ``operator:launcher`` (the launcher and ``khgrl stop`` / ``khgrl
ready`` run by the operator), ``learner:<id>``, ``actor:<id>``, ``human:<id>``. A process finds its private key by
its role and id in its run directory (:func:`load_private`); across machines, copy ``public.json`` to each machine's
run directory and each private key only to the machine of its process. Another user of a machine cannot read a 0600
file; processes of one user on one machine can (run them as different users to separate them there).
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

__all__ = ["ROLES", "KEY_DIR", "PUBLIC_FILE", "RoleKeyError", "key_id", "role_of", "private_path", "make_keys",
           "make_run_keys", "load_private", "PublicKeys", "SIG_BYTES"]

log = logging.getLogger("khgrl.trust")

ROLES = ("operator", "learner", "actor", "human")
KEY_DIR = "keys"
PUBLIC_FILE = "public.json"
SIG_BYTES = 64  # an Ed25519 signature
_RAW = 32  # an Ed25519 private or public key, raw


class RoleKeyError(ValueError):
    """A key file that is not one (wrong size, bad JSON, unknown role), or a private key missing."""


def key_id(role: str, ident: str) -> str:
    """The id of a role's key: ``key_id("human", "gui") == "human:gui"``.

    :param role: one of :data:`ROLES`.
    :param ident: the process's id (the launcher's: ``launcher``).
    """
    if role not in ROLES:
        raise RoleKeyError(f"role {role!r} not one of {', '.join(ROLES)}")
    if not ident or any(c in ident for c in "/*$?#: \\") or ident in (".", ".."):
        raise RoleKeyError(f"bad process id {ident!r} for a key")
    return f"{role}:{ident}"


def role_of(kid: str) -> str:
    """The role of a key id (``""`` for a malformed one).

    :param kid: a key id (:func:`key_id`).
    """
    role, sep, _ = kid.partition(":")
    return role if sep and role in ROLES else ""


def private_path(run_dir: str | Path, kid: str) -> Path:
    """Where the private key ``kid`` lives: ``RUN_DIR/keys/<role>-<id>.key``.

    :param run_dir: the run directory.
    :param kid: a key id.
    """
    return Path(run_dir) / KEY_DIR / (kid.replace(":", "-", 1) + ".key")


def _write(path: Path, data: bytes, mode: int) -> None:
    """``data`` to ``path`` with ``mode`` from the first byte (atomically)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        os.write(fd, data)
    finally:
        os.close(fd)
    os.chmod(tmp, mode)
    os.replace(tmp, path)


def make_keys(run_dir: str | Path, kids: list[str], fresh: bool = False) -> list[str]:
    """Make a key pair for each of ``kids`` that has none yet (all of them if ``fresh``: a new run), and add their
    public keys to ``public.json``; returns the ids made. Keys not in ``kids`` are kept.

    :param run_dir: the run directory (``keys/`` is made if missing).
    :param kids: key ids (:func:`key_id`).
    :param fresh: replace the keys of ``kids`` that exist.
    """
    folder = Path(run_dir) / KEY_DIR
    folder.mkdir(parents=True, exist_ok=True)
    table = {} if fresh else PublicKeys.read_table(run_dir)
    made = []
    for kid in kids:
        role, _, ident = kid.partition(":")
        key_id(role, ident)  # (raises for a bad id)
        if not fresh and kid in table and private_path(run_dir, kid).is_file():
            continue
        key = Ed25519PrivateKey.generate()
        _write(private_path(run_dir, kid), key.private_bytes_raw(), 0o600)
        table[kid] = key.public_key().public_bytes_raw().hex()
        made.append(kid)
    _write(folder / PUBLIC_FILE, json.dumps({"v": 1, "keys": dict(sorted(table.items()))}, indent=1).encode(), 0o644)
    return made


def make_run_keys(run_dir: str | Path, identities: list[tuple[str, str]], fresh: bool = False) -> list[str]:
    """:func:`make_keys` for the operator (``operator:launcher``), each (role, id) of ``identities`` and the spare
    client ``human:user`` (the client a user plugs in: ``--secure``'s ``human-user`` certificate).

    :param run_dir: the run directory.
    :param identities: (role, id) of the run's processes besides the operator.
    :param fresh: new keys for all of them (a new run).
    """
    kids = [key_id("operator", "launcher")] + [key_id(r, i) for r, i in [*identities, ("human", "user")]]
    return make_keys(run_dir, list(dict.fromkeys(kids)), fresh)


def load_private(run_dir: str | Path | None, kid: str, path: str | Path | None = None) -> Ed25519PrivateKey | None:
    """This process's private key: ``path``, or ``RUN_DIR/keys/<role>-<id>.key`` (None: no such file). A file that
    other users may read is used, with a warning.

    :param run_dir: the run directory (None: only ``path``).
    :param kid: the key's id.
    :param path: an explicit key file (it must exist).
    """
    if path is None:
        if not run_dir or not private_path(run_dir, kid).is_file():
            return None
        path = private_path(run_dir, kid)
    path = Path(path)
    try:
        raw, mode = path.read_bytes(), path.stat().st_mode
    except OSError as exc:
        raise RoleKeyError(f"{path}: {exc.strerror or exc}") from None
    if len(raw) != _RAW:
        raise RoleKeyError(f"{path}: {len(raw)} bytes, expected a raw Ed25519 key of {_RAW}")
    if mode & 0o077:
        log.warning("%s is readable by other users (mode %o): anyone who reads it can sign as %s", path, mode & 0o777,
                    kid)
    return Ed25519PrivateKey.from_private_bytes(raw)


@dataclass
class PublicKeys:
    """The run's public keys (``RUN_DIR/keys/public.json``), re-read when the file changes (a client added by ``khgrl
    keys`` while the run goes on is known at its first message).

    :param run_dir: the run directory (None: no keys: nothing is known).
    """

    run_dir: str | Path | None
    keys: dict[str, Ed25519PublicKey] = field(default_factory=dict)
    _stamp: tuple = field(default=(), init=False, repr=False)  # (mtime, size, inode) of the file last read

    def __post_init__(self) -> None:
        self.refresh()

    @property
    def path(self) -> Path | None:
        return Path(self.run_dir) / KEY_DIR / PUBLIC_FILE if self.run_dir else None

    @property
    def present(self) -> bool:
        """Whether the run has role keys (then control must be signed)."""
        return bool(self.keys)

    @staticmethod
    def read_table(run_dir: str | Path | None) -> dict[str, str]:
        """``public.json``'s ``keys`` (key id -> hex); empty without the file.

        :param run_dir: the run directory.
        """
        path = Path(run_dir) / KEY_DIR / PUBLIC_FILE if run_dir else None
        if path is None or not path.is_file():
            return {}
        try:
            doc = json.loads(path.read_text())
            table = doc["keys"]
            if doc.get("v") != 1 or not isinstance(table, dict):
                raise ValueError("not version 1")
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise RoleKeyError(f"{path}: not a key table ({exc})") from None
        for kid, hexkey in table.items():
            if not role_of(kid) or not isinstance(hexkey, str) or len(hexkey) != 2 * _RAW:
                raise RoleKeyError(f"{path}: bad entry {kid!r}")
        return table

    def refresh(self) -> bool:
        """Re-read the file if it changed since the last read; whether it did.

        :raises RoleKeyError: the file is not a key table.
        """
        path = self.path
        try:
            st = path.stat() if path is not None else None
        except OSError:
            st = None
        stamp = (st.st_mtime_ns, st.st_size, st.st_ino) if st is not None else ()
        if stamp == self._stamp:
            return False
        table = self.read_table(self.run_dir) if st is not None else {}
        try:
            self.keys = {kid: Ed25519PublicKey.from_public_bytes(bytes.fromhex(h)) for kid, h in table.items()}
        except ValueError as exc:  # (not hex, not a key)
            raise RoleKeyError(f"{path}: {exc}") from None
        self._stamp = stamp
        return True

    def verify(self, kid: str, sig: bytes, data: bytes) -> str | None:
        """Why ``sig`` is not ``kid``'s signature of ``data`` (None: it is).

        :param kid: the claimed signer's key id.
        :param sig: the signature.
        :param data: the signed bytes.
        """
        pub = self.keys.get(kid)
        if pub is None:
            try:
                pub = self.keys.get(kid) if self.refresh() else None
            except RoleKeyError as exc:  # (the table was damaged while the run goes on: the known keys stay)
                return f"signed by {kid!r}, not known; {exc}"
        if pub is None:
            return f"signed by {kid!r}, a key this run does not know"
        try:
            pub.verify(sig, data)
        except InvalidSignature:
            return f"wrong signature for {kid!r}"
        return None
