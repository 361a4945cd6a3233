"""What an inversion method is to the fit: a strategy (Method) that trimeter.inversion.methods tables."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable


@dataclass(frozen=True)
class Method:
    """name: what `--method` and `fit(method=…)` take; summary: one line for help texts.
    guesser(model, options) → a trimeter.inversion.kernel.Guesser or None for the map table's own
    guess; fit_all(models, arrays, stds, thickness_rel, options) → FitResult replaces the per-thickness
    flow (then guesser is unused). needs: the map artifacts beyond the map and its table, by file
    suffix (the bench runs one variant per such file next to the map, passed as `mlp_model`);
    default_polish: Newton steps after the guess."""
    name: str
    summary: str
    guesser: Callable[[Any, dict], Any] | None = None
    fit_all: Callable[..., Any] | None = None
    needs: tuple[str, ...] = ()
    default_polish: int = 8
    # what `trimeter bench fit` runs of it: (label suffix, fit options) per variant
    bench_variants: tuple[tuple[str, dict], ...] = (("p≤8", {}),)

    @property
    def joint(self) -> bool:
        """Whether it fits several thicknesses together (else each alone, then combined)."""
        return self.fit_all is not None
