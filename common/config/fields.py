"""How a setting is declared (:func:`_opt`) and the commands it can belong to (:data:`ROLES`): shared by the
settings tables (:mod:`khgrl.common.config.settings`, :mod:`khgrl.common.config.safety`)."""

from __future__ import annotations

from dataclasses import field
from typing import Any

__all__ = ["UP", "LEARNER", "ACTOR", "HUMAN", "REFERENCE", "ROLES"]

# The commands whose flags a setting is: ``khgrl up`` takes every setting (and writes them all into the run's
# config file); each other command takes the settings whose roles name it.
UP, LEARNER, ACTOR, HUMAN, REFERENCE = "up", "learner", "actor", "human", "reference"
ROLES = (UP, LEARNER, ACTOR, HUMAN, REFERENCE)
_LA, _LAH, _LR, _LAR = (LEARNER, ACTOR), (LEARNER, ACTOR, HUMAN), (LEARNER, REFERENCE), (LEARNER, ACTOR, REFERENCE)


def _opt(default: Any, help: str, choices: tuple | None = None, *, roles: tuple[str, ...],  # noqa: A002
         shown: str | None = None):
    """A config field: its default, help text, allowed values, ``roles`` (the commands besides ``khgrl up`` whose
    flag it is; () : ``khgrl up`` only; every field must say, so a new setting cannot silently be no flag) and, where
    the default needs words, what ``--help`` shows as the default (``shown``)."""
    if isinstance(default, (list, dict)):
        raise TypeError("use tuples for sequence defaults (frozen settings)")
    unknown = set(roles) - set(ROLES)
    if unknown:
        raise ValueError(f"unknown role(s) {sorted(unknown)}; roles are {ROLES}")
    return field(default=default, metadata={"help": help, "choices": choices, "roles": frozenset((UP, *roles)),
                                                   "shown": shown})
