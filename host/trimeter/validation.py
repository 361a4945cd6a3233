"""Range checks that name the offending field, shared by recipes, the CLI and the fit entry point."""

from __future__ import annotations

from typing import Any
import math

from trimeter.errors import InputError

SHOWN_CHARS = 60  # characters of an offending value quoted in a message


def shown(value: object, limit: int = SHOWN_CHARS) -> str:
    """repr(value) cut to `limit` characters + '…': a hostile file's 10 MB value is not echoed back.
    Containers are summarised by type and length (a deep one is not walked), huge integers by size."""
    if isinstance(value, (dict, list, tuple)):
        return f"a {type(value).__name__} of {len(value)} item(s)"
    if isinstance(value, int) and value.bit_length() > 4 * limit:
        return f"an integer of {value.bit_length()} bits"
    text = repr(value[:limit + 1] if isinstance(value, str) else value)
    return text if len(text) <= limit else text[:limit] + "…"


def require_number(field: str, value: Any, *, lo: float | None = None, hi: float | None = None,
                   lo_open: bool = False, hi_open: bool = False) -> float:
    """Return `value` as a float, or raise InputError naming `field` if it is not finite or out of range."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{field} must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise InputError(f"{field} must be finite, got {value!r}")
    if lo is not None and (x < lo or (lo_open and x == lo)):
        raise InputError(f"{field} must be {'>' if lo_open else '>='} {lo:g}, got {x:g}")
    if hi is not None and (x > hi or (hi_open and x == hi)):
        raise InputError(f"{field} must be {'<' if hi_open else '<='} {hi:g}, got {x:g}")
    return x


def require_material(alpha: Any, sigma_t: Any, g: Any) -> tuple[float, float, float]:
    """The physically possible material: α ∈ [0, 1], σt ≥ 0 [1/mm], |g| < 1."""
    return (require_number("alpha", alpha, lo=0.0, hi=1.0),
            require_number("sigma_t", sigma_t, lo=0.0),
            require_number("g", g, lo=-1.0, hi=1.0, lo_open=True, hi_open=True))


def require_sample(n: Any, thickness_mm: Any) -> tuple[float, float]:
    """A sample's refractive index n ≥ 1 and thickness ℓ > 0 [mm]."""
    return (require_number("n", n, lo=1.0), require_number("thickness_mm", thickness_mm, lo=0.0, lo_open=True))


def require_reflectance(field: str, rho: Any) -> float:
    """A background reflectance ρ ∈ [0, 1]."""
    return require_number(field, rho, lo=0.0, hi=1.0)
