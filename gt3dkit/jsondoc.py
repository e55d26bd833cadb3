"""Reading a JSON document back (``meta.json``, a run's report) with its types checked: the
value at a path of keys as an object, a list, a number or text, and an absent or wrongly typed
value as none (instead of an ``AttributeError`` three calls later)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from gt3dkit.types import JsonValue


def json_at(doc: JsonValue, *keys: str) -> JsonValue:
    """``doc[k1][k2]...`` of a JSON document read back (``meta.json``); None where a key is
    missing or a value on the way is not an object."""
    v = doc
    for k in keys:
        v = v.get(k) if isinstance(v, Mapping) else None
    return v


def json_obj(doc: JsonValue, *keys: str) -> Mapping[str, JsonValue]:
    """:func:`json_at` as an object; empty where it is none."""
    v = json_at(doc, *keys)
    return v if isinstance(v, Mapping) else {}


def json_list(doc: JsonValue, *keys: str) -> Sequence[JsonValue]:
    """:func:`json_at` as a list; empty where it is none."""
    v = json_at(doc, *keys)
    return v if isinstance(v, Sequence) and not isinstance(v, str) else []


def json_num(doc: JsonValue, *keys: str) -> float | None:
    """:func:`json_at` as a number (true/false are not); None where it is none."""
    v = json_at(doc, *keys)
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else None


def json_str(doc: JsonValue, *keys: str) -> str | None:
    """:func:`json_at` as text; None where it is none."""
    v = json_at(doc, *keys)
    return v if isinstance(v, str) else None
