"""The table of inversion methods: name → strategy (trimeter.inversion.strategy.Method). The CLI, the
service, the web API and the bench read it; adding a method is one module that defines a `Method` and
one registration (a line in the tuple below, or `register(METHOD)` for a method outside the package).

Two kinds of strategy:
- a per-bin guess (`guesser`) polished on the map's forward grid, one thickness at a time, then
  combined by inverse-variance weighting (lut: the map table's guess; mlp: a network's);
- a whole fit of its own over all thicknesses (`fit_all`: the paper's ε-median pools its samples).
"""

from __future__ import annotations

from trimeter.errors import InputError
from trimeter.inversion import lut, mlp, paper
from trimeter.inversion.strategy import Method

METHODS: dict[str, Method] = {m.name: m for m in (lut.METHOD, mlp.METHOD, paper.METHOD)}


def register(method: Method) -> Method:
    """Add a method to the table (its name must be new)."""
    if method.name in METHODS:
        raise ValueError(f"inversion method {method.name!r} is registered already")
    METHODS[method.name] = method
    return method


def unregister(name: str) -> None:
    METHODS.pop(name, None)


def get_method(name: str) -> Method:
    try:
        return METHODS[name]
    except (KeyError, TypeError):
        raise InputError(f"method must be one of {', '.join(METHODS)}, got {name!r}") from None
