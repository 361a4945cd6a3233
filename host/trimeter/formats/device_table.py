"""The self-sufficient device table (`.tlut` format version 2): everything a fit needs in one map slot
(≤ MAP_SLOT_CAPACITY_BYTES), with nothing else on the file system — the compact forward model for the
polish, the in-scattering correction, the map's own error at its nodes, the inverse table for the
initial guess, the sample set-up, the geometry it was traced for and its parent map's SHA-256.

The forward model is trimeter.model.compact.CompactForward: per g node, cubic B-spline coefficients
in (α, ln σt) of A, B, C, and PCHIP along g, evaluated on the fly from a 4×4×4 window (a host may
instead sample it onto a refined grid at load). Every array is little-endian, starts at an offset
that is a multiple of 8 (a C reader maps the file in place) and is named with its offset and length
in the header, and every quantized array is value = offset + step · q with (offset, step) in SCALES.
The splines' knots are not stored: they are the not-a-knot knots of the stored α and ln σt axes
(x₀ four times, x₂ … x₋₃, x₋₁ four times; trimeter.model.compact.not_a_knot_knots).

    offset size  field
    0      8     magic b"\\x89TRLUT\\r\\n"
    8      u16   format version (2)
    10     u16   header size (256)
    12     u32   total size in bytes, including the trailing CRC-32
    16     32    SHA-256 of the parent appearance map (raw digest)
    48     32    SHA-256 of the in-scattering table file it carries (raw digest; zeros: none known)
    80     f32×6 n, thickness_mm ℓ, cover_slide_n (0: none), rho_b_ref, rho_w_ref, mc_stderr
    104    f32×3 in-scattering axes' ends: u_max (u = −ln(1 − α)), tau_max (τ = σt·ℓ), v_max (v = −ln(1 − g))
    116    u16×8 n_alpha, n_sigma, n_g, n_inverse, n_u, n_tau, n_v, reserved (0)
    132    24    map name, UTF-8, NUL-padded
    156    u32×2 per section below, in this order: (offset, length in bytes)
    244    12    reserved (0)
    256          the sections, each padded with zeros to a multiple of 8 bytes:
      alpha         f32[n_alpha]                      α nodes
      log_sigma_t   f32[n_sigma]                      ln σt nodes (σt in 1/mm)
      g             f32[n_g]                          g nodes
      scales        f32[6][2]                         (offset, step) of A, B, C, std_b, std_w, L
      spline        u16[n_g][n_alpha][n_sigma][3]     B-spline coefficients of A, B, C
      model_std     u16[n_alpha][n_sigma][n_g][2]     the map's own error std of (I_b, I_w) at the nodes,
                                                      at the reference backgrounds (MC + interpolation)
      inscatter     u16[n_u][n_tau][n_v]              L = ln(1 + r), regular in (u, τ, v) from 0
      inv_frame     f32[n_sigma][6]                   (x0, y0, m00, m01, m10, m11) per σt node, as in v1
      inv_alpha_q   u16[n_sigma][n_inverse][n_inverse] α = α_0 + (α_last − α_0)·q/65535 (as in v1)
      inv_g_q       u16[n_sigma][n_inverse][n_inverse] g = g_0 + (g_last − g_0)·q/65535
      geometry      UTF-8 JSON                        the geometry parameters the in-scattering was traced for
    end−4  u32   CRC-32/IEEE (zlib.crc32) of every byte before it

`DeviceTable.from_bytes` checks every field before any array is used and names the field of the
first defect in a MapFileError; `load` refuses a file larger than the slot before reading it.
"""

from __future__ import annotations

import hashlib
import json
import os
import struct
import zlib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from collections.abc import Callable
from typing import Any, NoReturn

import numpy as np

from trimeter.atomic import atomic_write
from trimeter.errors import MapFileError
from trimeter.formats.container import read_bounded
from trimeter.model.compact import CompactForward
from trimeter.model.inscatter_table import InscatterTable
from trimeter.model.sample_setup import SampleSetup
from trimeter.registers import MAP_SLOT_CAPACITY_BYTES

MAGIC = b"\x89TRLUT\r\n"
FORMAT_VERSION = 2
SUFFIX = ".tlut"
HEADER_SIZE = 256
ALIGN = 8
MAX_BYTES = MAP_SLOT_CAPACITY_BYTES
SECTIONS = ("alpha", "log_sigma_t", "g", "scales", "spline", "model_std", "inscatter", "inv_frame", "inv_alpha_q",
            "inv_g_q", "geometry")
SCALE_ROWS = ("A", "B", "C", "std_b", "std_w", "L")
_HEAD = struct.Struct("<8sHHI32s32s6f3f8H24s")
_DIRECTORY = struct.Struct(f"<{2 * len(SECTIONS)}I")
_RESERVED = HEADER_SIZE - _HEAD.size - _DIRECTORY.size
_Q = 65535.0
# the fewest (α, σt, g) nodes the compact model's splines take (cubic along α and ln σt, PCHIP along g)
MIN_NODES = (4, 4, 3)


def _padded(n: int) -> int:
    return -(-n // ALIGN) * ALIGN


def _layout(na: int, ns: int, ng: int, n_inv: int, nu: int, nt: int, nv: int,
            geometry_bytes: int) -> tuple[dict[str, tuple[int, int, str, tuple[int, ...]]], int]:
    """{section: (offset, nbytes, dtype, shape)} and the total size, from the counts alone."""
    specs = {"alpha": ("<f4", (na,)), "log_sigma_t": ("<f4", (ns,)), "g": ("<f4", (ng,)),
             "scales": ("<f4", (len(SCALE_ROWS), 2)), "spline": ("<u2", (ng, na, ns, 3)),
             "model_std": ("<u2", (na, ns, ng, 2)), "inscatter": ("<u2", (nu, nt, nv)),
             "inv_frame": ("<f4", (ns, 6)), "inv_alpha_q": ("<u2", (ns, n_inv, n_inv)),
             "inv_g_q": ("<u2", (ns, n_inv, n_inv)), "geometry": ("u1", (geometry_bytes,))}
    layout, offset = {}, HEADER_SIZE
    for name in SECTIONS:
        dtype, shape = specs[name]
        nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
        layout[name] = (offset, nbytes, dtype, shape)
        offset += _padded(nbytes)
    return layout, offset + 4


def table_size(na: int, ns: int, ng: int, n_inv: int, nu: int, nt: int, nv: int, geometry_bytes: int) -> int:
    """The file's size in bytes for these counts."""
    return _layout(na, ns, ng, n_inv, nu, nt, nv, geometry_bytes)[1]


def geometry_bytes(geometry: dict) -> bytes:
    """The geometry section: canonical JSON (sorted keys, no spaces)."""
    return json.dumps(geometry, sort_keys=True, separators=(",", ":")).encode()


def quantize(values: np.ndarray) -> tuple[np.ndarray, tuple[float, float]]:
    """u16 codes of `values` over their own range and the (offset, step) that decodes them (float32,
    as stored: the codes are rounded against the stored scale)."""
    v = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(v)):
        raise MapFileError("device table: a quantity to store is not finite")
    lo = np.float32(v.min())
    step = np.float32((float(v.max()) - float(lo)) / _Q) or np.float32(1.0)
    q = np.clip(np.round((v - np.float64(lo)) / np.float64(step)), 0, _Q).astype(np.uint16)
    return q, (float(lo), float(step))


# a reader's report of the first defect: (field, why) → MapFileError
Fail = Callable[[str, str], NoReturn]


def _check_format(magic: bytes, version: int, header_size: int, fail: Fail) -> None:
    if magic != MAGIC:
        fail("magic", "not a trimeter map table")
    if version != FORMAT_VERSION:
        retired = " (format 1 is retired: rebuild it with `trimeter map build RECIPE --stages tlut`)" \
            if version == 1 else ""
        fail("format_version", f"{version}, this reader reads {FORMAT_VERSION}{retired}")
    if header_size != HEADER_SIZE:
        fail("header_size", f"{header_size}, not {HEADER_SIZE}")


def _check_setup(n: float, thickness: float, cover_n: float, rho_b: float, rho_w: float, mc_stderr: float,
                 ends: tuple[float, float, float], fail: Fail) -> None:
    """The header's set-up numbers: each in its range, ρ_b < ρ_w, a known cover slide."""
    u_max, tau_max, v_max = ends
    header = dict(n=(n, 1, 3), thickness_mm=(thickness, 1e-6, 100), rho_b_ref=(rho_b, 0, 1),
                  rho_w_ref=(rho_w, 0, 1), mc_stderr=(mc_stderr, 0, 1), u_max=(u_max, 1e-6, 50),
                  tau_max=(tau_max, 1e-6, 1e3), v_max=(v_max, 1e-6, 50))
    for key, (value, lo, hi) in header.items():
        if not (np.isfinite(value) and lo <= value <= hi):
            fail(key, f"{value} is not a number in [{lo}, {hi}]")
    if not rho_b < rho_w:
        fail("rho_w_ref", f"{rho_w} is not above rho_b_ref {rho_b}")
    if not (cover_n == 0 or 1 <= cover_n <= 3):
        fail("cover_slide_n", f"{cover_n}: 0 (none) or an index in [1, 3]")


def _decode_name(raw: bytes, fail: Fail) -> str:
    try:
        name = raw.rstrip(b"\0").decode()
    except UnicodeDecodeError:
        fail("name", "not NUL-padded UTF-8")
    if "\0" in name:
        fail("name", "not NUL-padded UTF-8")
    return name


def _decode_geometry(raw: bytes, fail: Fail) -> dict[str, Any]:
    try:
        geometry = json.loads(raw.decode())
    except (UnicodeDecodeError, ValueError):
        fail("geometry", "not UTF-8 JSON")
    if not isinstance(geometry, dict):
        fail("geometry", "not a JSON object")
    return geometry


@dataclass(frozen=True, eq=False)
class DeviceTable:
    name: str
    parent_sha256: str                   # hex
    inscatter_sha256: str                # hex, "" when unknown
    n: float
    thickness_mm: float
    cover_slide_n: float | None
    rho_b_ref: float
    rho_w_ref: float
    mc_stderr: float
    inscatter_ends: tuple[float, float, float]   # u_max, tau_max, v_max
    alpha: np.ndarray                    # f32 axes as stored
    log_sigma_t: np.ndarray
    g: np.ndarray
    scales: np.ndarray                   # f32 (6, 2)
    spline: np.ndarray                   # u16 (ng, na, ns, 3)
    model_std: np.ndarray                # u16 (na, ns, ng, 2)
    inscatter: np.ndarray                # u16 (nu, nt, nv)
    inv_frame: np.ndarray                # f32 (ns, 6)
    inv_alpha_q: np.ndarray                # u16 (ns, n_inv, n_inv)
    inv_g_q: np.ndarray                    # u16 (ns, n_inv, n_inv)
    geometry: dict
    path: Path | None = field(default=None, compare=False)

    # ------------------------------------------------------------------------------------ build
    @classmethod
    def build(cls, *, name: str, parent_sha256: str, inscatter_sha256: str, n: float, thickness_mm: float,
              cover_slide_n: float | None, reference_rhos: tuple[float, float], mc_stderr: float,
              alpha: np.ndarray, log_sigma_t: np.ndarray, g: np.ndarray, nodes: np.ndarray, model_std: np.ndarray,
              inscatter_L: np.ndarray,
              inscatter_ends: tuple[float, float, float], inv_frame: np.ndarray, inv_alpha_q: np.ndarray,
              inv_g_q: np.ndarray, geometry: dict[str, Any]) -> DeviceTable:
        """From float arrays: A, B, C at the map's nodes (na, ns, ng, 3), the model error stds
        (na, ns, ng, 2), L (nu, nt, nv); the inverse grid already as v1 codes (u16)."""
        a32, s32, g32 = (np.asarray(x, dtype=np.float32) for x in (alpha, log_sigma_t, g))
        # the splines through the nodes on the axes as stored, so that a reader rebuilds the same model
        coef = CompactForward.from_nodes(a32, s32, g32, nodes).coefficients
        spline_q, scales = [], []
        for i in range(3):
            q, sc = quantize(coef[..., i])
            spline_q.append(q)
            scales.append(sc)
        std_q = []
        for i in range(2):
            q, sc = quantize(model_std[..., i])
            std_q.append(q)
            scales.append(sc)
        L_q, sc = quantize(inscatter_L)
        scales.append(sc)
        table = cls(name=name[:24], parent_sha256=parent_sha256, inscatter_sha256=inscatter_sha256 or "", n=n,
                    thickness_mm=thickness_mm, cover_slide_n=cover_slide_n, rho_b_ref=reference_rhos[0],
                    rho_w_ref=reference_rhos[1], mc_stderr=mc_stderr,
                    inscatter_ends=(float(inscatter_ends[0]), float(inscatter_ends[1]), float(inscatter_ends[2])),
                    alpha=a32, log_sigma_t=s32, g=g32,
                    scales=np.array(scales, dtype=np.float32), spline=np.stack(spline_q, axis=-1),
                    model_std=np.stack(std_q, axis=-1), inscatter=L_q,
                    inv_frame=np.asarray(inv_frame, dtype=np.float32), inv_alpha_q=np.asarray(inv_alpha_q, np.uint16),
                    inv_g_q=np.asarray(inv_g_q, np.uint16), geometry=geometry)
        return cls.from_bytes(table.to_bytes(), source="device table being built")  # every check, once

    # ----------------------------------------------------------------------------- decoded views
    def _decoded(self, codes: np.ndarray, row: int) -> np.ndarray:
        offset, step = (float(x) for x in self.scales[row])
        return offset + step * codes.astype(np.float64)

    def forward(self) -> CompactForward:
        coef = np.stack([self._decoded(self.spline[..., i], i) for i in range(3)], axis=-1)
        return CompactForward(self.alpha, self.log_sigma_t, self.g, coef)

    def model_variance(self) -> np.ndarray:
        """(na, ns, ng, 2): variances of I_b, I_w's model error at the nodes."""
        return np.stack([self._decoded(self.model_std[..., i], 3 + i) for i in range(2)], axis=-1) ** 2

    def inscatter_L(self) -> np.ndarray:
        return self._decoded(self.inscatter, 5)

    @cached_property
    def coefficients_grid(self) -> np.ndarray:
        """A, B, C at the map's nodes (na, ns, ng, 3) from the compact model: a map's node values, from
        which ForwardGrid.between_nodes refines exactly the compact model's splines."""
        return self.forward().nodes()

    @cached_property
    def inverse_alpha(self) -> np.ndarray:
        a0, a1 = float(self.alpha[0]), float(self.alpha[-1])
        return a0 + (a1 - a0) * self.inv_alpha_q.astype(np.float64) / _Q

    @cached_property
    def inverse_g(self) -> np.ndarray:
        g0, g1 = float(self.g[0]), float(self.g[-1])
        return g0 + (g1 - g0) * self.inv_g_q.astype(np.float64) / _Q

    @property
    def reference_rhos(self) -> tuple[float, float]:
        return self.rho_b_ref, self.rho_w_ref

    @cached_property
    def setup(self) -> SampleSetup:
        return SampleSetup(self.n, self.thickness_mm, self.cover_slide_n, geometry_params=self.geometry)

    @property
    def carries_inscatter(self) -> bool:
        """False for a map traced without the device's collimated set-up (an ideal map): its section is
        then all zeros (L = 0 everywhere: no correction)."""
        return bool(self.inscatter.any()) or float(self.scales[5, 0]) != 0.0

    def inscatter_table(self, L: np.ndarray | None = None) -> InscatterTable | None:
        """The in-scattering lookup it carries (L: other values on its grid, e.g. unquantized); None when
        it carries none."""
        if L is None and not self.carries_inscatter:
            return None
        u_max, tau_max, v_max = self.inscatter_ends
        return InscatterTable(self.inscatter_L() if L is None else L, u_max=u_max, tau_max=tau_max, v_max=v_max,
                              n=self.n, thickness_mm=self.thickness_mm, geometry_params=self.geometry)

    def _geometry_bytes(self) -> bytes:
        return geometry_bytes(self.geometry)

    def _counts(self) -> tuple[int, int, int, int, int, int, int]:
        nu, nt, nv = self.inscatter.shape
        return len(self.alpha), len(self.log_sigma_t), len(self.g), self.inv_alpha_q.shape[1], nu, nt, nv

    @property
    def size_bytes(self) -> int:
        return table_size(*self._counts(), len(self._geometry_bytes()))

    def sizes(self) -> dict[str, int]:
        """Bytes per part of the file (sections padded as stored)."""
        layout, total = _layout(*self._counts(), len(self._geometry_bytes()))
        return {"header": HEADER_SIZE, **{k: _padded(v[1]) for k, v in layout.items()}, "crc": 4, "total": total}

    @cached_property
    def sha256(self) -> str:
        """The SHA-256 of the file's bytes (hex): what names this table."""
        return hashlib.sha256(self.to_bytes()).hexdigest()

    @property
    def crc32(self) -> int:
        """Its own trailing CRC-32 (what the device's fit_table_crc32 register reports)."""
        return zlib.crc32(self.to_bytes()[:-4])

    # what a measurement records of the model it fits with (trimeter.domain.measurement.MapRef)
    @property
    def checksum(self) -> str:
        return self.sha256

    @property
    def A(self) -> np.ndarray:
        return self.coefficients_grid[..., 0]

    @property
    def B(self) -> np.ndarray:
        return self.coefficients_grid[..., 1]

    @property
    def C(self) -> np.ndarray:
        return self.coefficients_grid[..., 2]

    def info(self) -> dict:
        """`trimeter map info` for a table."""
        sigma_t = np.exp(self.log_sigma_t.astype(np.float64))
        n_inv = self.inv_alpha_q.shape[1]
        return {
            "kind": "device-table", "format_version": FORMAT_VERSION, "name": self.name,
            "path": str(self.path) if self.path else None, "size_bytes": self.size_bytes,
            "slot_capacity_bytes": MAX_BYTES, "sha256": self.sha256, "crc32": f"{self.crc32:08x}",
            "parent_map_sha256": self.parent_sha256, "inscatter_sha256": self.inscatter_sha256 or None,
            "sample": {"n": self.n, "thickness_mm": self.thickness_mm, "cover_slide_n": self.cover_slide_n},
            "reference_rho": {"black": self.rho_b_ref, "white": self.rho_w_ref},
            "forward_grid": {"alpha": len(self.alpha), "sigma_t": len(self.log_sigma_t), "g": len(self.g)},
            "inverse_grid": {"sigma_t": len(self.log_sigma_t), "x": n_inv, "y": n_inv},
            "inscatter_grid": list(self.inscatter.shape) if self.carries_inscatter else None,
            "range": {"alpha": [float(self.alpha[0]), float(self.alpha[-1])],
                      "sigma_t": [float(sigma_t[0]), float(sigma_t[-1])], "g": [float(self.g[0]), float(self.g[-1])]},
            "mc_stderr": self.mc_stderr, "bytes_per_part": self.sizes(),
        }

    # ---------------------------------------------------------------------------------- encoding
    def to_bytes(self) -> bytes:
        geometry = self._geometry_bytes()
        layout, total = _layout(*self._counts(), len(geometry))
        directory = [x for name in SECTIONS for x in layout[name][:2]]
        head = _HEAD.pack(MAGIC, FORMAT_VERSION, HEADER_SIZE, total,
                          bytes.fromhex(self.parent_sha256) if self.parent_sha256 else b"\0" * 32,
                          bytes.fromhex(self.inscatter_sha256) if self.inscatter_sha256 else b"\0" * 32,
                          self.n, self.thickness_mm, self.cover_slide_n or 0.0, self.rho_b_ref, self.rho_w_ref,
                          self.mc_stderr, *self.inscatter_ends, *self._counts()[:4], *self.inscatter.shape, 0,
                          self.name.encode()[:24])
        out = bytearray(head + _DIRECTORY.pack(*directory) + b"\0" * _RESERVED)
        arrays = {name: getattr(self, name) for name in SECTIONS if name != "geometry"}
        for name in SECTIONS:
            offset, nbytes, dtype, _ = layout[name]
            data = geometry if name == "geometry" else np.ascontiguousarray(arrays[name], dtype=dtype).tobytes()
            out += data + b"\0" * (_padded(nbytes) - nbytes)
        return bytes(out) + struct.pack("<I", zlib.crc32(out))

    @classmethod
    def from_bytes(cls, data: bytes, source: str = "device table") -> DeviceTable:
        data = bytes(data)

        def fail(name: str, why: str) -> NoReturn:
            raise MapFileError(f"{source}: {name}: {why}")

        if len(data) > MAX_BYTES:
            fail("total_size", f"{len(data)} bytes is more than the {MAX_BYTES}-byte map slot")
        if len(data) < HEADER_SIZE + 4:
            fail("total_size", f"truncated ({len(data)} bytes, shorter than the header)")
        (magic, version, header_size, total, parent, tins, n, thickness, cover_n, rho_b, rho_w, mc_stderr, u_max,
         tau_max, v_max, na, ns, ng, n_inv, nu, nt, nv, reserved, name) = _HEAD.unpack_from(data)
        _check_format(magic, version, header_size, fail)
        if total != len(data):
            fail("total_size", f"the header says {total} bytes, the data has {len(data)} (truncated or padded)")
        (crc,) = struct.unpack_from("<I", data, len(data) - 4)
        if zlib.crc32(data[:-4]) != crc:
            fail("crc32", "mismatch: the table is corrupt")
        counts = dict(n_alpha=(na, MIN_NODES[0]), n_sigma=(ns, MIN_NODES[1]), n_g=(ng, MIN_NODES[2]),
                      n_inverse=(n_inv, 2), n_u=(nu, 2), n_tau=(nt, 2), n_v=(nv, 2))
        for key, (value, least) in counts.items():
            if value < least:
                fail(key, f"{value}, at least {least} needed")
        if reserved or any(data[_HEAD.size + _DIRECTORY.size:HEADER_SIZE]):
            fail("reserved", "not zero (written by a newer or broken tool)")
        directory = _DIRECTORY.unpack_from(data, _HEAD.size)
        geometry_len = directory[-1]
        layout, expected_total = _layout(na, ns, ng, n_inv, nu, nt, nv, geometry_len)
        if expected_total != total:
            fail("total_size", f"{total} bytes, the counts in the header make {expected_total}")
        arrays = {}
        for i, key in enumerate(SECTIONS):
            offset, nbytes, dtype, shape = layout[key]
            if directory[2 * i:2 * i + 2] != (offset, nbytes):
                fail(key, f"at ({directory[2 * i]}, {directory[2 * i + 1]} bytes), expected ({offset}, {nbytes})")
            if any(data[offset + nbytes:offset + _padded(nbytes)]):
                fail(key, "padding after it is not zero")
            arrays[key] = np.frombuffer(data, dtype=dtype, count=int(np.prod(shape)), offset=offset).reshape(shape)
        for key in ("alpha", "log_sigma_t", "g"):
            axis = arrays[key]
            if not (np.all(np.isfinite(axis)) and np.all(np.diff(axis) > 0)):
                fail(key, "not finite and strictly increasing")
        if not (arrays["alpha"][0] >= 0 and arrays["alpha"][-1] <= 1):
            fail("alpha", "outside [0, 1]")
        if not (arrays["g"][0] > -1 and arrays["g"][-1] < 1):
            fail("g", "outside (−1, 1)")
        _check_setup(n, thickness, cover_n, rho_b, rho_w, mc_stderr, (u_max, tau_max, v_max), fail)
        scales = arrays["scales"]
        if not (np.all(np.isfinite(scales)) and np.all(scales[:, 1] > 0)):
            fail("scales", "not finite, or a step that is not positive")
        if not (scales[3:, 0] >= 0).all():
            fail("scales", "a model error std or in-scattering L that can be negative")
        if not np.all(np.isfinite(arrays["inv_frame"])):
            fail("inv_frame", "not finite")
        name_str = _decode_name(name, fail)
        geometry = _decode_geometry(arrays.pop("geometry").tobytes(), fail)
        return cls(name=name_str, parent_sha256=parent.hex(), inscatter_sha256="" if not any(tins) else tins.hex(),
                   n=float(n), thickness_mm=float(thickness), cover_slide_n=float(cover_n) or None,
                   rho_b_ref=float(rho_b), rho_w_ref=float(rho_w), mc_stderr=float(mc_stderr),
                   inscatter_ends=(float(u_max), float(tau_max), float(v_max)), geometry=geometry,
                   alpha=arrays["alpha"], log_sigma_t=arrays["log_sigma_t"], g=arrays["g"], scales=arrays["scales"],
                   spline=arrays["spline"], model_std=arrays["model_std"], inscatter=arrays["inscatter"],
                   inv_frame=arrays["inv_frame"], inv_alpha_q=arrays["inv_alpha_q"], inv_g_q=arrays["inv_g_q"])

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        atomic_write(path, self.to_bytes())
        return path

    @classmethod
    def load(cls, path: str | Path) -> DeviceTable:
        path = Path(path)
        table = cls.from_bytes(read_bounded(path, MAX_BYTES, "map table"), source=str(path))
        object.__setattr__(table, "path", path)
        return table


def read_header(path: str | Path) -> dict[str, Any]:
    """A table file's identity from its header and geometry section alone (a few hundred bytes: neither the
    arrays nor the CRC-32 are read, DeviceTable.load checks those): name, the parent map's SHA-256, n,
    thickness_mm, cover_slide_n, geometry and size_bytes. MapFileError naming the first defect found."""
    path = Path(path)

    def fail(name: str, why: str) -> NoReturn:
        raise MapFileError(f"{path}: {name}: {why}")

    try:
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            if not HEADER_SIZE + 4 <= size <= MAX_BYTES:
                fail("total_size", f"{size} bytes, not within a table's [{HEADER_SIZE + 4}, {MAX_BYTES}]")
            head = f.read(HEADER_SIZE)
            if len(head) != HEADER_SIZE:  # shrunk since fstat
                fail("total_size", f"truncated ({len(head)} bytes, shorter than the header)")
            (magic, version, header_size, total, parent, _tins, n, thickness, cover_n, rho_b, rho_w, mc_stderr,
             u_max, tau_max, v_max, *_counts, name) = _HEAD.unpack_from(head)
            _check_format(magic, version, header_size, fail)
            if total != size:
                fail("total_size", f"the header says {total} bytes, the file has {size} (truncated or padded)")
            _check_setup(n, thickness, cover_n, rho_b, rho_w, mc_stderr, (u_max, tau_max, v_max), fail)
            geometry_at, geometry_len = _DIRECTORY.unpack_from(head, _HEAD.size)[-2:]
            if not HEADER_SIZE <= geometry_at <= geometry_at + geometry_len <= size - 4:
                fail("geometry", f"at ({geometry_at}, {geometry_len} bytes), outside the file")
            f.seek(geometry_at)
            geometry = _decode_geometry(f.read(geometry_len), fail)
    except OSError as exc:
        raise MapFileError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    return {"name": _decode_name(name, fail), "parent_map_sha256": parent.hex(), "n": float(n),
            "thickness_mm": float(thickness), "cover_slide_n": float(cover_n) or None, "geometry": geometry,
            "size_bytes": size}


def table_path_for(map_path: str | Path) -> Path:
    """maps/<name>.tmap → maps/<name>.tlut."""
    return Path(map_path).with_suffix(SUFFIX)


def describe_table(path_or_bytes: str | Path | bytes) -> dict:
    """`trimeter map info` for a .tlut file (path) or raw table bytes (e.g. read back from a slot)."""
    if isinstance(path_or_bytes, (bytes, bytearray, memoryview)):
        return DeviceTable.from_bytes(bytes(path_or_bytes)).info()
    return DeviceTable.load(path_or_bytes).info()
