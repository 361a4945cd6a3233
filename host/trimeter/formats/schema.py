"""Declarative checks for untrusted file headers: the header of every trimeter container and the
metadata of each file kind are described here once, as data, and checked before any array is used.

A schema is a tree of specs (Number, Text, Flag, Table, Items, Json) for the JSON header, and an
`ArraySpec` per array: its allowed dtypes, its dimensions (symbols such as "n_alpha" are bound by
the first array that names them, so every array's shape must agree with the axes), and its values
(finite, in a range, strictly increasing). A failure raises SchemaError naming the field, e.g.
`meta.recipe.thickness_mm must be > 0, got 0`; the readers prefix it with the file.

Why not jsonschema: it is not a dependency, and these files need array-shape relations it lacks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, NoReturn, Protocol

import numpy as np

from trimeter.validation import shown


class SchemaError(ValueError):
    """A header field that breaks its schema; `str()` names the field."""


def _fail(where: str, message: str) -> NoReturn:
    raise SchemaError(f"{where} {message}")


class Spec(Protocol):
    """What a field of a JSON header is checked against (Number, Text, Flag, Json, Items, Table)."""

    def check(self, value: Any, where: str) -> None: ...


@dataclass(frozen=True)
class Number:
    """A finite JSON number (never a bool), optionally an integer, within [lo, hi] (open ends optional)."""
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    integer: bool = False

    def check(self, value, where: str) -> None:
        kinds = (int,) if self.integer else (int, float)
        if isinstance(value, bool) or not isinstance(value, kinds):
            _fail(where, f"must be {'an integer' if self.integer else 'a number'}, got {shown(value)}")
        if isinstance(value, float) and not math.isfinite(value):
            _fail(where, f"must be finite, got {shown(value)}")
        if self.lo is not None and (value < self.lo or (self.lo_open and value == self.lo)):
            _fail(where, f"must be {'>' if self.lo_open else '>='} {self.lo:g}, got {shown(value)}")
        if self.hi is not None and (value > self.hi or (self.hi_open and value == self.hi)):
            _fail(where, f"must be {'<' if self.hi_open else '<='} {self.hi:g}, got {shown(value)}")


@dataclass(frozen=True)
class Text:
    max_len: int = 1024
    choices: tuple[str, ...] | None = None

    def check(self, value, where: str) -> None:
        if not isinstance(value, str):
            _fail(where, f"must be a string, got {shown(value)}")
        if len(value) > self.max_len:
            _fail(where, f"is longer than {self.max_len} characters ({shown(value)})")
        if self.choices is not None and value not in self.choices:
            _fail(where, f"must be one of {', '.join(self.choices)}, got {shown(value)}")


@dataclass(frozen=True)
class Flag:
    def check(self, value, where: str) -> None:
        if not isinstance(value, bool):
            _fail(where, f"must be true or false, got {shown(value)}")


@dataclass(frozen=True)
class Json:
    """Free-form JSON (provenance, descriptions) kept small: bounded nesting and item count. Checked
    without recursion, so a hostile depth cannot exhaust the stack."""
    max_depth: int = 8
    max_items: int = 10_000
    kind: type | None = dict

    def check(self, value, where: str) -> None:
        if self.kind is not None and not isinstance(value, self.kind):
            _fail(where, f"must be a {'table' if self.kind is dict else self.kind.__name__}, got {shown(value)}")
        stack, items = [(value, 0)], 0
        while stack:
            node, depth = stack.pop()
            if isinstance(node, float) and not math.isfinite(node):
                _fail(where, "holds a non-finite number")
            if not isinstance(node, (dict, list)):
                continue
            if depth >= self.max_depth:
                _fail(where, f"is nested deeper than {self.max_depth} levels")
            items += len(node)
            if items > self.max_items:
                _fail(where, f"has more than {self.max_items} items")
            stack.extend((child, depth + 1) for child in (node.values() if isinstance(node, dict) else node))


@dataclass(frozen=True)
class Items:
    """A JSON list of `of`, min_len … max_len long."""
    of: Spec
    min_len: int = 0
    max_len: int = 64

    def check(self, value, where: str) -> None:
        if not isinstance(value, list):
            _fail(where, f"must be a list, got {shown(value)}")
        if not self.min_len <= len(value) <= self.max_len:
            _fail(where, f"must have {self.min_len}…{self.max_len} items, has {len(value)}")
        for i, item in enumerate(value):
            self.of.check(item, f"{where}[{i}]")


@dataclass(frozen=True)
class Table:
    """A JSON object: `fields` by name (those in `required` must be present), other keys checked
    with `extra` (None: refused). `rules` are (predicate, message) over the whole table, checked
    once its fields passed (relations such as ρ_b < ρ_w)."""
    fields: dict[str, Spec] = field(default_factory=dict)
    required: tuple[str, ...] = ()
    extra: Spec | None = Json(kind=None)
    max_keys: int = 256
    rules: tuple = ()

    def check(self, value, where: str) -> None:
        if not isinstance(value, dict):
            _fail(where, f"must be a table, got {shown(value)}")
        if len(value) > self.max_keys:
            _fail(where, f"has {len(value)} keys, more than {self.max_keys}")
        missing = [k for k in self.required if k not in value]
        if missing:
            _fail(where, f"lacks {', '.join(missing)}")
        for key, item in value.items():
            spec = self.fields.get(key, self.extra)
            name = f"{where}.{shown(key, 40).strip(chr(39))}" if where else shown(key, 40).strip(chr(39))
            if spec is None:
                _fail(name, "is not a known field")
            spec.check(item, name)
        for predicate, message in self.rules:
            if not predicate(value):
                _fail(where, message)


FLOATS = ("<f4", "<f8")
# Plain little-endian numbers only: no complex, object, structured, datetime or big-endian data.
ALLOWED_DTYPES = ("|b1", "|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", *FLOATS)


@dataclass(frozen=True)
class ArraySpec:
    """One named array: dtypes, dimensions (ints, or symbols shared across arrays), and its values."""
    dims: tuple
    dtypes: tuple[str, ...] = FLOATS
    min_len: int = 1            # for each symbolic dimension
    finite: bool = True
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    increasing: bool = False    # strictly, along its only axis

    def check_values(self, arr: np.ndarray, where: str) -> None:
        with np.errstate(invalid="ignore"):
            if self.finite and not np.all(np.isfinite(arr)):
                _fail(where, "holds NaN or infinite values")
            if self.lo is not None and arr.size and (np.nanmin(arr) < self.lo
                                                     or (self.lo_open and np.nanmin(arr) == self.lo)):
                _fail(where, f"must be {'>' if self.lo_open else '>='} {self.lo:g}, has {np.nanmin(arr):g}")
            if self.hi is not None and arr.size and (np.nanmax(arr) > self.hi
                                                     or (self.hi_open and np.nanmax(arr) == self.hi)):
                _fail(where, f"must be {'<' if self.hi_open else '<='} {self.hi:g}, has {np.nanmax(arr):g}")
            if self.increasing and not np.all(np.diff(arr) > 0):
                _fail(where, "must be strictly increasing")


@dataclass(frozen=True)
class ContainerSchema:
    """What one file kind's container must hold: `meta` (a Table) and `arrays` by name (all
    required; others refused). `version` = (meta key, label, the version this trimeter reads) is
    checked first, so a file from another format version says so rather than failing a field."""
    meta: Table
    arrays: dict
    version: tuple[str, str, int] | None = None

    def check_header(self, meta: dict, descriptors: dict) -> None:
        """Before any array is read: the metadata, the array names, dtypes and shapes."""
        if self.version is not None:
            key, label, expected = self.version
            found = meta.get(key) if isinstance(meta, dict) else None
            if found != expected or isinstance(found, bool):
                _fail(label, f"{shown(found)} is not supported (expected {expected})")
        self.meta.check(meta, "meta")
        missing = [name for name in self.arrays if name not in descriptors]
        if missing:
            _fail("arrays", f"lack {', '.join(missing)}")
        unknown = [shown(name, 40) for name in descriptors if name not in self.arrays]
        if unknown:
            _fail("arrays", f"hold unexpected {', '.join(unknown[:5])}")
        bound: dict[str, tuple[int, str]] = {}
        for name, spec in self.arrays.items():
            d = descriptors[name]
            where = f"arrays.{name}"
            if d["dtype"] not in spec.dtypes:
                _fail(f"{where}.dtype", f"must be one of {', '.join(spec.dtypes)}, got {shown(d['dtype'])}")
            shape = d["shape"]
            if len(shape) != len(spec.dims):
                _fail(f"{where}.shape", f"must have {len(spec.dims)} dimension(s), has {len(shape)}")
            for size, dim in zip(shape, spec.dims, strict=True):
                if isinstance(dim, int):
                    if size != dim:
                        _fail(f"{where}.shape", f"must be {list(spec.dims)}, got {shape}")
                elif dim in bound:
                    if size != bound[dim][0]:
                        _fail(f"{where}.shape", f"{shape} does not match {bound[dim][1]} ({dim} = {bound[dim][0]})")
                else:
                    if size < spec.min_len:
                        _fail(f"{where}.shape", f"needs at least {spec.min_len} points along {dim}, has {size}")
                    bound[dim] = (size, f"arrays.{name}")

    def check_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        """After reading: each array's values."""
        for name, spec in self.arrays.items():
            spec.check_values(arrays[name], f"arrays.{name}")


# ------------------------------------------------------------------ fields shared by the file kinds
SAMPLE_N = Number(lo=1.0, hi=3.0)                        # a sample's refractive index
THICKNESS_MM = Number(lo=0.0, lo_open=True, hi=100.0)     # a sample's thickness ℓ
REFLECTANCE = Number(lo=0.0, hi=1.0)
# The instrument geometry a map or table was made for: the fields the host reads are typed, the
# rest (positions, sizes, descriptions) is bounded free-form data.
GEOMETRY_PARAMS = Table(
    {"cover_slides": Flag(), "cover_slide_n": SAMPLE_N, "cover_slide_thickness_mm": Number(lo=0.0, hi=10.0),
     "collimated": Table({name: Number(lo=0.0, lo_open=True, hi=1e4) for name in
                          ("aperture_diameter_mm", "aperture_distance_mm", "beam_diameter_mm")})},
    rules=((lambda p: not p.get("cover_slides") or "cover_slide_n" in p, "lacks cover_slide_n (cover_slides is on)"),))
PROVENANCE = Json(max_depth=8)
# The stamp a derived file (a map's .tins, .tlut, .onnx) carries: its parent's SHA-256 and who made it
# (trimeter.maps.pipeline); a loader compares the former with the parent's actual checksum.
PARENT_SHA256 = Text(max_len=64)
PRODUCER = Table({"name": Text(max_len=256), "version": Text(max_len=64)}, required=("name", "version"), extra=None)
