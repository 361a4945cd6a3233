"""TOML text of flat tables (key = value lines), for the files trimeter writes itself.

A tiny writer rather than a dependency: the files it writes are flat tables of strings, integers and
finite floats. Strings are TOML basic strings with every character TOML forbids raw escaped, so any
Python text reads back (tomllib) as exactly itself; anything else is refused, never formatted as text.
"""

from __future__ import annotations

import math
import re

from trimeter.errors import InputError

_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")
_SHORT_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}


def _escaped(char: str) -> str:
    if char in _SHORT_ESCAPES:
        return _SHORT_ESCAPES[char]
    code = ord(char)
    if code < 0x20 or code == 0x7F:
        return f"\\u{code:04X}"
    if 0xD800 <= code <= 0xDFFF:  # a lone surrogate is no Unicode scalar value: no TOML string holds it
        raise InputError(f"{char!r} (a lone surrogate) cannot be written to a TOML file")
    return char


def toml_value(value: object) -> str:
    """One value as TOML: a basic string, a boolean, an integer or a finite float (anything else: InputError)."""
    if isinstance(value, str):
        return '"' + "".join(map(_escaped, value)) + '"'
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float) and math.isfinite(value):
        text = repr(value)
        return text if any(c in text for c in ".en") else text + ".0"  # TOML reads 1e+300; "5" would be an integer
    raise InputError(f"{value!r} cannot be written as a TOML value")


def toml_table(items: dict[str, object], comment: str = "") -> str:
    """A document of `key = value` lines (bare keys only), after an optional comment line."""
    lines = [f"# {line}" for line in comment.splitlines()]
    for key, value in items.items():
        if not _BARE_KEY.fullmatch(key):
            raise InputError(f"{key!r} is not a TOML bare key")
        lines.append(f"{key} = {toml_value(value)}")
    return "\n".join(lines) + "\n"
