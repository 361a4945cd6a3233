"""Cells and resampling on the model's axes: the operations every interpolant here shares (and invert.c
mirrors, operation for operation)."""

from __future__ import annotations

import numpy as np


def regular_cell(p: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(cell, weight) on an evenly spaced axis of n nodes at p = (x − x0)/step, clamped to the axis
    (invert.c inscatter_log1p's τ cell)."""
    i = np.clip(np.floor(p), 0, n - 2)
    return i.astype(np.intp), np.clip(p - i, 0.0, 1.0)


def trilinear(L: np.ndarray, i: np.ndarray, wi: np.ndarray, j: np.ndarray, wj: np.ndarray, k: np.ndarray,
              wk: np.ndarray) -> np.ndarray:
    """L (3-D) between its nodes: cells i, j, k with weights wi, wj, wk, interpolated along the last axis,
    then the middle, then the first (invert.c inscatter_log1p, operation for operation)."""
    def along_k(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return L[a, b, k] + (L[a, b, k + 1] - L[a, b, k]) * wk

    def lerp(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
        return a + (b - a) * w

    return lerp(lerp(along_k(i, j), along_k(i, j + 1), wj), lerp(along_k(i + 1, j), along_k(i + 1, j + 1), wj), wi)


def refine_axis(axis: np.ndarray, factor: int) -> np.ndarray:
    """`factor` − 1 evenly spaced points inserted into every interval of `axis`."""
    t = np.linspace(0, len(axis) - 1, (len(axis) - 1) * factor + 1)
    return np.interp(t, np.arange(len(axis)), np.asarray(axis, dtype=np.float64))


def cubic_resample(values: np.ndarray, old: np.ndarray, new: np.ndarray, axis: int, kind: str = "cubic") -> np.ndarray:
    """`values` along `axis` from nodes `old` onto `new`: a cubic spline ("cubic") or PCHIP ("pchip")
    through the nodes (both reproduce them exactly); linear with fewer than 4 nodes."""
    from scipy.interpolate import BSpline, PchipInterpolator, make_interp_spline

    x = np.array(old, dtype=np.float64)  # a copy: container arrays can be unaligned (scipy refuses those)
    front = np.moveaxis(np.asarray(values, dtype=np.float64), axis, 0)
    flat = np.array(front.reshape(len(x), -1))
    curve: PchipInterpolator | BSpline
    if kind == "pchip" and len(x) >= 3:
        curve = PchipInterpolator(x, flat, axis=0)
    else:
        curve = make_interp_spline(x, flat, k=3 if len(x) >= 4 else 1)
    out = curve(np.asarray(new, dtype=np.float64)).reshape(len(new), *front.shape[1:])
    return np.moveaxis(out, 0, axis)


def linear_resample(values: np.ndarray, old: np.ndarray, new: np.ndarray, axis: int) -> np.ndarray:
    """`values` along `axis` from nodes `old` onto `new`, piecewise linear (clamped at the ends)."""
    i = np.clip(np.searchsorted(old, new, side="right") - 1, 0, len(old) - 2)
    w = np.clip((new - old[i]) / (old[i + 1] - old[i]), 0.0, 1.0)
    front = np.moveaxis(values, axis, 0)
    shape = (-1,) + (1,) * (front.ndim - 1)
    out = front[i] * (1.0 - w.reshape(shape)) + front[i + 1] * w.reshape(shape)
    return np.moveaxis(out, 0, axis)
