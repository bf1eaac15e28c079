"""Whether a value read from a config file or `--set` fits the setting it is for.

One rule for `d3lvo run --config`, training configs and solver `--set`: a value must be of the
kind of the setting's default (or type hint), so that a hand-edited `threads = "two"` or
`pt_stop=nan` is one error naming the key at start-up, not a failure deep inside a run. Torch-free,
so the runtime and the training side share it.
"""

from __future__ import annotations

import math
from pathlib import Path


def _kind(like) -> type:
    """The kind a default value or a type stands for."""
    if isinstance(like, type):
        return like
    return type(like)


def _number(value, whole: bool) -> bool:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    return isinstance(value, int) if whole else math.isfinite(value)


def fits(value, like) -> bool:
    """True when `value` may stand where `like` (a default value, or a type) stands: booleans for
    booleans, whole numbers for ints, finite numbers (ints too) for floats, strings for strings
    and paths, and for a list or tuple default a list or tuple of values fitting its first element
    (strings where the default is empty)."""
    kind = _kind(like)
    if kind is bool:
        return isinstance(value, bool)
    if kind in (int, float):
        return _number(value, whole=kind is int)
    if kind in (tuple, list):
        element = like[0] if isinstance(like, (tuple, list)) and like else ""
        return isinstance(value, (tuple, list)) and all(fits(v, element) for v in value)
    if issubclass(kind, (str, Path)):
        return isinstance(value, str)
    return isinstance(value, kind)


def describe(like) -> str:
    """What `fits` wants where `like` stands, in words for an error message (for a list or tuple,
    what its elements are: the caller says how they are written)."""
    kind = _kind(like)
    if kind is bool:
        return "true or false"
    if kind is int:
        return "a whole number"
    if kind is float:
        return "a finite number"
    if kind in (tuple, list):
        element = like[0] if isinstance(like, (tuple, list)) and like else ""
        return {bool: "true or false values", int: "whole numbers", float: "numbers"}.get(
            _kind(element), "quoted strings")
    if issubclass(kind, Path):
        return "a quoted string (a path)"
    if issubclass(kind, str):
        return "a quoted string"
    return f"a {kind.__name__}"


def converted(value, like):
    """`value` (which fits) as the setting holds it: a float for a float, a Path for a path, a
    tuple for a tuple default."""
    kind = _kind(like)
    if kind is float:
        return float(value)
    if kind is tuple:
        return tuple(value)
    if isinstance(kind, type) and issubclass(kind, Path):
        return Path(value)
    return value
