"""The ``human_clients`` setting: which actors each human-input client may pause and correct (issue 21)."""

from __future__ import annotations

__all__ = ["parse_assignments"]


def parse_assignments(spec: str) -> dict[str, frozenset[str]] | None:
    """The ``human_clients`` setting: ``"h0=a0,a1;user=a0 scripted=*"`` -> {client: actor ids} (``*``: every
    actor); "" -> None (every client may drive every actor). Entries are separated by ``;`` or spaces; raises
    :class:`ValueError` on a malformed one.

    :param spec: the setting.
    """
    if not spec.strip():
        return None
    out: dict[str, frozenset[str]] = {}
    for entry in spec.replace(";", " ").split():
        client, sep, actors = entry.partition("=")
        ids = frozenset(a for a in actors.split(",") if a)
        if not sep or not client or not ids or any(c in client + actors for c in "/$?#"):
            raise ValueError(f"human_clients: {entry!r} is not CLIENT=ACTOR[,ACTOR...] (or CLIENT=*)")
        out[client] = out.get(client, frozenset()) | ids
    return out
