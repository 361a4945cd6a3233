"""Mitsuba 3, imported lazily and set to the best variant this machine can run.

The device side has no Mitsuba: nothing in trimeter imports it at module level; callers that render
(scenes, the direct renders, the map builder) ask for it through `mitsuba()`.

Order of preference: `cuda_ad_mono` (a working GPU), `llvm_ad_mono` (needs LLVM ≥ 16: Debian's
libllvm19 — the LLVM 14/15 this machine otherwise finds aborts at JIT time, docs/platform-notes.md),
then `scalar_mono`-class fallbacks. Mitsuba 3.9's pip wheel has no `scalar_mono`, so the scalar
fallback is `scalar_rgb` only if `scalar_mono` is missing; callers read `.variant()` and record it.
"""

from __future__ import annotations

import os
from pathlib import Path
from types import ModuleType

from trimeter.errors import TrimeterError

LIBLLVM = Path("/usr/lib/x86_64-linux-gnu/libLLVM-19.so")
PREFERRED = ("cuda_ad_mono", "llvm_ad_mono", "scalar_mono", "scalar_rgb")

_chosen: str | None = None


class MitsubaUnavailable(TrimeterError):
    """Mitsuba is not installed (the device side) or no variant works on this machine."""


def _import() -> ModuleType:
    if "DRJIT_LIBLLVM_PATH" not in os.environ and LIBLLVM.exists():
        # Must be set before Dr.Jit initialises its LLVM backend, i.e. before the first import.
        os.environ["DRJIT_LIBLLVM_PATH"] = str(LIBLLVM)
    try:
        import mitsuba as mi
    except ImportError as exc:
        raise MitsubaUnavailable("rendering needs Mitsuba 3 (pip install 'trimeter[maps]')") from exc
    return mi


def mitsuba(variant: str | None = None) -> ModuleType:
    """Return the `mitsuba` module with a variant set: `variant` if given, else the best that works.

    The choice is made once per process (switching variants invalidates loaded scenes), so a second
    call without `variant` returns the same one."""
    global _chosen
    mi = _import()
    if variant is not None:
        if variant not in mi.variants():
            raise MitsubaUnavailable(f"Mitsuba variant {variant!r} is not available; have {', '.join(mi.variants())}")
        if mi.variant() != variant:
            mi.set_variant(variant)
        _chosen = variant
        return mi
    if _chosen is not None:
        if mi.variant() != _chosen:
            mi.set_variant(_chosen)
        return mi
    errors = []
    for name in PREFERRED:
        if name not in mi.variants():
            continue
        try:
            mi.set_variant(name)
            _probe(mi)
        except Exception as exc:  # noqa: BLE001 - a variant failing to initialise is expected (no GPU)
            errors.append(f"{name}: {exc}".splitlines()[0])
            continue
        _chosen = name
        return mi
    raise MitsubaUnavailable("no Mitsuba variant works here: " + "; ".join(errors))


def _probe(mi: ModuleType) -> None:
    """Force the backend to JIT a trivial kernel, so a broken CUDA/LLVM fails here, not mid-render."""
    import drjit as dr

    total = dr.sum(mi.Float([1.0, 2.0]) * 2.0)
    dr.eval(total)
    if float(total[0] if hasattr(total, "__len__") else total) != 6.0:
        raise RuntimeError("probe kernel returned a wrong value")


def variant() -> str:
    """The chosen variant's name (selects one if none was chosen yet)."""
    return mitsuba().variant()
