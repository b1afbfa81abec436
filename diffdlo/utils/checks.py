"""Checks of user-given values shared by every command line and options type (env, planners, learners, benchmarks):
each message names the option, what is allowed and the bad value.

An options dataclass declares each field's rule beside it with ``option``::

    lr: float = option(3e-4, "(0, inf)", help="Adam's learning rate")
    obs: str = option("points", choices=OBS_TYPES, help="observation type")

and ``check_fields(obj)`` checks every field against its declared type (the real annotation, resolved once per
class) and its rule; a ``check()`` method keeps only the rules that tie several fields together.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing
from typing import Any, Sequence

MISSING = dataclasses.MISSING


def check_interval(name: str, v: Any, interval: str) -> None:
    """Raise ValueError unless the number ``v`` lies in ``interval``, written "[lo, hi]", "(lo, hi)" or mixed, with
    inf for no bound (e.g. "[1, inf)", "(0, 1]"). NaN is never inside."""
    lo, hi = (float(x) for x in interval[1:-1].split(","))
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and not math.isnan(v)
    ok = ok and (v >= lo if interval[0] == "[" else v > lo) and (v <= hi if interval[-1] == "]" else v < hi)
    if not ok:
        raise ValueError(f"{name} must be in {interval}, got {v!r}")


def check_choice(name: str, v: Any, allowed: Sequence[Any]) -> None:
    if not isinstance(v, typing.Hashable) or v not in allowed:
        raise ValueError(f"unknown {name} {v!r}: use one of {list(allowed)}")


def option(default: Any = MISSING, interval: str | None = None, *, choices: Sequence[Any] | None = None,
           factory: Any = MISSING, layers: bool = False, says: str | None = None, help: str = "") -> Any:
    """A dataclass field with its rule beside it: ``interval`` for a number ("[1, inf)"; None values pass),
    ``choices`` for a value from a list, ``layers`` for a list of positive layer sizes; ``help`` says what it is.
    ``says`` words a broken interval or choice as "<name> must be <says>, got <value>" (e.g. "a positive integer")
    in place of the interval's or the choices' own message. ``factory`` makes a mutable default (a list)."""
    meta = {"interval": interval, "choices": None if choices is None else tuple(choices), "layers": layers,
            "says": says, "help": help}
    if factory is not MISSING:
        return dataclasses.field(default_factory=factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def field_help(cls: type, name: str) -> str:
    """The ``help`` declared beside field ``name`` of options class ``cls`` ("" when none)."""
    return next((f.metadata.get("help", "") for f in dataclasses.fields(cls) if f.name == name), "")


@functools.lru_cache(maxsize=None)
def field_kinds(cls: type) -> dict[str, tuple[type, ...] | None]:
    """field name -> the types its annotation allows (None: any), from the class's resolved annotations."""
    hints = typing.get_type_hints(cls)
    kinds: dict[str, tuple[type, ...] | None] = {}
    for f in dataclasses.fields(cls):
        kinds[f.name] = _kinds(hints.get(f.name, Any))
    return kinds


def _kinds(hint: Any) -> tuple[type, ...] | None:
    if hint is Any or callable(hint) and getattr(hint, "__module__", "") == "collections.abc":
        return None
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        parts = [_kinds(a) for a in typing.get_args(hint)]
        return None if any(p is None for p in parts) else tuple(k for p in parts for k in p)
    if origin is not None:                       # list[int], dict[str, Any], Callable[...]
        return None if origin.__module__ == "collections.abc" else (origin,)
    if hint is None or hint is type(None):
        return (type(None),)
    return (hint,) if isinstance(hint, type) else None


def _is(kind: type, v: Any) -> bool:
    if kind is float:
        return isinstance(v, (int, float)) and not isinstance(v, bool)
    if kind is int:
        return isinstance(v, int) and not isinstance(v, bool)
    return isinstance(v, kind)


def _wanted(kinds: tuple[type, ...]) -> str:
    if kinds == (bool,):
        return "true or false"
    return " or ".join("None" if k is type(None) else k.__name__ for k in kinds)


def check_fields(obj: Any, skip: Sequence[str] = ()) -> None:
    """Every field of dataclass ``obj`` (but ``skip``) holds a value of its declared type and obeys the rule declared
    beside it with ``option``; the ValueError names the field, what is allowed and the value."""
    kinds = field_kinds(type(obj))
    for f in dataclasses.fields(obj):
        if f.name in skip:
            continue
        v = getattr(obj, f.name)
        k = kinds[f.name]
        meta = f.metadata
        if k is not None and not any(_is(t, v) for t in k):
            if meta.get("choices") is not None:
                check_choice(f.name, v, meta["choices"])      # a value of the wrong type is not one of the choices
            if meta.get("says"):
                raise ValueError(f"{f.name} must be {meta['says']}, got {v!r}")
            raise ValueError(f"{f.name} must be {_wanted(k)}, got {v!r} ({type(v).__name__})")
        if v is None:
            continue
        try:
            if meta.get("interval"):
                check_interval(f.name, v, meta["interval"])
            if meta.get("choices") is not None:
                check_choice(f.name, v, meta["choices"])
        except ValueError:
            if not meta.get("says"):
                raise
            raise ValueError(f"{f.name} must be {meta['says']}, got {v!r}") from None
        if meta.get("layers") and (not isinstance(v, list) or not all(_is(int, x) and x >= 1 for x in v)):
            raise ValueError(f"{f.name} must be a list of positive layer sizes, e.g. [256, 256], got {v!r}")
