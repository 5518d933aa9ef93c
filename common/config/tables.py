"""A settings dataclass from a table of a TOML/JSON file, of flags or of both: :func:`merge` stacks tables (defaults
< a file < flags), :func:`build` makes the frozen dataclass, refusing an unknown key, a value of the wrong type or
outside the field's choices with an error that names the setting (``config.tqc.batch_size: expected an integer``).
"""

from __future__ import annotations

from dataclasses import fields, is_dataclass
from typing import Any, get_type_hints

__all__ = ["build", "merge"]


def merge(base: dict, over: dict) -> dict:
    """``base`` with ``over`` on top, table by table (a value in ``over`` wins; nested tables merge).

    :param base: the lower table
    :param over: the higher one
    """
    out = dict(base)
    for k, v in over.items():
        out[k] = merge(out.get(k, {}), v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _coerce(value: Any, typ: Any, where: str) -> Any:
    if typ is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{where}: expected true/false, got {value!r}")
        return value
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{where}: expected an integer, got {value!r}")
        return value
    if typ is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if typ is str:
        if not isinstance(value, str):
            raise ValueError(f"{where}: expected a string, got {value!r}")
        return value
    if not isinstance(value, (list, tuple)):  # tuple[int, ...]
        raise ValueError(f"{where}: expected a list of integers, got {value!r}")
    return tuple(_coerce(v, int, where) for v in value)


def build(cls, data: dict, where: str):
    """An instance of the settings dataclass ``cls`` from ``data`` (its defaults for what is missing): every key a
    field, every value checked against the field's type and choices, a nested table for nested settings.

    :param cls: a settings dataclass (:class:`~khgrl.common.config.settings.RunConfig`, or one of its parts)
    :param data: the table (from a file, flags or both)
    :param where: where the table comes from, for the errors (``config``, a file's path)
    """
    hints = get_type_hints(cls)
    names = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"{where}: unknown setting(s) {', '.join(unknown)}")
    kw = {}
    for f in fields(cls):
        if f.name not in data:
            continue
        typ, value = hints[f.name], data[f.name]
        if is_dataclass(typ):
            if not isinstance(value, dict):
                raise ValueError(f"{where}.{f.name}: expected a table")
            kw[f.name] = build(typ, value, f"{where}.{f.name}")
            continue
        kw[f.name] = _coerce(value, typ, f"{where}.{f.name}")
        choices = f.metadata.get("choices")
        if choices and kw[f.name] not in choices:
            raise ValueError(f"{where}.{f.name}: {kw[f.name]!r} is not one of {', '.join(choices)}")
    return cls(**kw)
