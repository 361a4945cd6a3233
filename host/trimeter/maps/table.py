"""The map table: the compact, self-contained inverse of one appearance map, as the instrument stores
it in a map slot (A/B flash sectors, written over Modbus file records by `trimeter map flash`) and as
the `lut` method reads it. File name convention: maps/<map-name>.tlut next to maps/<map-name>.tmap.

What it holds (everything the `lut` fit needs, without the map file):
- the forward map: A, B, C on the map's own (α, ln σt, g) grid, so that
  I(ρ) = A + Bρ/(1 − Cρ) can be evaluated (trilinear) for a Newton polish at any ρ_b(λ), ρ_w(λ);
- the sample set-up (n, ℓ, cover slides) for the analytic I_c and its exact Beer-Lambert inverse;
- an inverse grid for the initial guess: for each σt node k, (α, g) over a regular (u, v) grid in
  [0, 1]², where (u, v) is an affine image of (x, y) = (√I_b, √I_w) at the reference backgrounds,
  aligned with that slice's gamut (its principal axes), so the grid covers the gamut tightly.

Binary layout, version 1 — all little-endian, no padding, total ≤ MAP_SLOT_CAPACITY_BYTES (128 KiB):

    offset size  field
    0      8     magic b"\\x89TRLUT\\r\\n"
    8      u16   format version (1)
    10     u16   header size in bytes (128)
    12     u32   total size in bytes, including the trailing CRC-32
    16     32    SHA-256 of the source appearance map (raw digest bytes)
    48     f32   n                 sample refractive index
    52     f32   thickness_mm      sample thickness ℓ
    56     f32   cover_slide_n     0 = no cover slides
    60     f32   rho_b_ref         reference black background reflectance (inverse grid built at it)
    64     f32   rho_w_ref         reference white background reflectance
    68     f32   mc_stderr         the map's median Monte Carlo standard error of I
    72     u16   n_alpha, n_sigma, n_g       forward grid
    78     u16   n_x, n_y                    inverse grid (per σt node)
    82     u16   reserved (0)
    84     24    map name, UTF-8, NUL-padded
    108    20    reserved (0)
    128          payload, in this order:
                 f32[n_alpha]  α axis
                 f32[n_sigma]  ln σt axis (σt in 1/mm)
                 f32[n_g]      g axis
                 f32[3][2]     (offset, step) of A, B, C: value = offset + step · q
                 u16[3][n_alpha][n_sigma][n_g]   q of A, B, C (C order: α slowest, g fastest)
                 f32[n_sigma][6]                 inverse frame (x0, y0, m00, m01, m10, m11) per σt node:
                                                 u = m00(x−x0) + m01(y−y0), v = m10(x−x0) + m11(y−y0)
                 u16[n_sigma][n_y][n_x]          α = α_0 + (α_last − α_0) · q / 65535 at u = i/(n_x−1), v = j/(n_y−1)
                 u16[n_sigma][n_y][n_x]          g = g_0 + (g_last − g_0) · q / 65535
    end−4  u32   CRC-32/IEEE (zlib.crc32) of every byte before it

`MapTable.from_bytes` checks size, magic, version, header size, total size, CRC and every count
before decoding anything, and raises MapFileError on any defect; `to_bytes(from_bytes(b)) == b`.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from trimeter.errors import MapFileError
from trimeter.maps.container import read_bounded
from trimeter.model.cells import refine_axis
from trimeter.model.grid import ForwardGrid
from trimeter.model.setup import SampleSetup
from trimeter.registers import MAP_SLOT_CAPACITY_BYTES

TABLE_MAGIC = b"\x89TRLUT\r\n"
TABLE_FORMAT_VERSION = 1
TABLE_SUFFIX = ".tlut"
HEADER_SIZE = 128
MAX_TABLE_BYTES = MAP_SLOT_CAPACITY_BYTES
_HEADER = struct.Struct("<8sHHI32s6f5HH24s20s")
assert _HEADER.size == HEADER_SIZE
_Q = 65535.0


@dataclass(frozen=True, eq=False)
class MapTable:
    name: str
    source_checksum: str            # hex SHA-256 of the appearance map it was built from
    n: float
    thickness_mm: float
    cover_slide_n: float | None
    rho_b_ref: float
    rho_w_ref: float
    mc_stderr: float
    alpha: np.ndarray               # f32 axes as stored
    log_sigma_t: np.ndarray
    g: np.ndarray
    coef_quant: np.ndarray          # f32 (3, 2): (offset, step) per coefficient
    coef_q: np.ndarray              # u16 (3, n_alpha, n_sigma, n_g)
    inv_frame: np.ndarray           # f32 (n_sigma, 6): (x0, y0, m00, m01, m10, m11)
    inv_alpha_q: np.ndarray         # u16 (n_sigma, n_y, n_x)
    inv_g_q: np.ndarray             # u16 (n_sigma, n_y, n_x)
    path: Path | None = field(default=None, compare=False)

    # ------------------------------------------------------------------------------ decoded views
    @cached_property
    def setup(self) -> SampleSetup:
        """The sample set-up as the table holds it (its f32 fields): what a fit on the table uses."""
        return SampleSetup(self.n, self.thickness_mm, self.cover_slide_n)

    @cached_property
    def sigma_t(self) -> np.ndarray:
        return np.exp(self.log_sigma_t.astype(np.float64))

    @cached_property
    def coefficients_grid(self) -> np.ndarray:
        """float64 (n_alpha, n_sigma, n_g, 3): A, B, C packed last so one gather fetches all three."""
        q = self.coef_q.astype(np.float64)
        off, step = self.coef_quant[:, 0].astype(np.float64), self.coef_quant[:, 1].astype(np.float64)
        return np.moveaxis(off[:, None, None, None] + step[:, None, None, None] * q, 0, -1).copy()

    @cached_property
    def inverse_alpha(self) -> np.ndarray:
        a0, a1 = float(self.alpha[0]), float(self.alpha[-1])
        return a0 + (a1 - a0) * self.inv_alpha_q.astype(np.float64) / _Q

    @cached_property
    def inverse_g(self) -> np.ndarray:
        g0, g1 = float(self.g[0]), float(self.g[-1])
        return g0 + (g1 - g0) * self.inv_g_q.astype(np.float64) / _Q

    @property
    def size_bytes(self) -> int:
        return _total_size(len(self.alpha), len(self.log_sigma_t), len(self.g),
                           self.inv_alpha_q.shape[2], self.inv_alpha_q.shape[1])

    # --------------------------------------------------------------------------------- encoding
    def to_bytes(self) -> bytes:
        na, ns, ng = len(self.alpha), len(self.log_sigma_t), len(self.g)
        ny, nx = self.inv_alpha_q.shape[1:]
        header = _HEADER.pack(
            TABLE_MAGIC, TABLE_FORMAT_VERSION, HEADER_SIZE, self.size_bytes,
            bytes.fromhex(self.source_checksum) if self.source_checksum else b"\0" * 32,
            self.n, self.thickness_mm, self.cover_slide_n or 0.0, self.rho_b_ref, self.rho_w_ref,
            self.mc_stderr, na, ns, ng, nx, ny, 0, self.name.encode()[:24], b"")
        parts = [header]
        for arr, dtype in ((self.alpha, "<f4"), (self.log_sigma_t, "<f4"), (self.g, "<f4"),
                           (self.coef_quant, "<f4"), (self.coef_q, "<u2"), (self.inv_frame, "<f4"),
                           (self.inv_alpha_q, "<u2"), (self.inv_g_q, "<u2")):
            parts.append(np.ascontiguousarray(arr, dtype=dtype).tobytes())
        body = b"".join(parts)
        return body + struct.pack("<I", zlib.crc32(body))

    @classmethod
    def from_bytes(cls, data: bytes, source: str = "map table") -> "MapTable":
        data = bytes(data)
        if len(data) < HEADER_SIZE + 4:
            raise MapFileError(f"{source}: truncated ({len(data)} bytes) — not a complete map table")
        (magic, version, header_size, total, digest, n, thickness, cover_n, rho_b, rho_w, mc_stderr,
         na, ns, ng, nx, ny, _reserved, name, _pad) = _HEADER.unpack_from(data)
        if magic != TABLE_MAGIC:
            raise MapFileError(f"{source}: not a trimeter map table (bad magic)")
        if version != TABLE_FORMAT_VERSION:
            raise MapFileError(f"{source}: map table version {version} is not supported "
                               f"(this trimeter reads {TABLE_FORMAT_VERSION})")
        if header_size != HEADER_SIZE:
            raise MapFileError(f"{source}: header size {header_size} is not {HEADER_SIZE}")
        if total != len(data):
            raise MapFileError(f"{source}: header says {total} bytes but the data has {len(data)} "
                               f"— truncated or padded")
        (crc,) = struct.unpack_from("<I", data, len(data) - 4)
        if zlib.crc32(data[:-4]) != crc:
            raise MapFileError(f"{source}: CRC-32 mismatch — the table is corrupt")
        if min(na, ns, ng) < 2 or min(nx, ny) < 2 or _total_size(na, ns, ng, nx, ny) != total:
            raise MapFileError(f"{source}: grid sizes ({na}, {ns}, {ng}; {nx}×{ny}) do not match its length")
        offset = HEADER_SIZE

        def take(dtype, shape):
            nonlocal offset
            count = int(np.prod(shape))
            arr = np.frombuffer(data, dtype=dtype, count=count, offset=offset).reshape(shape)
            offset += arr.nbytes
            return arr

        arrays = dict(alpha=take("<f4", (na,)), log_sigma_t=take("<f4", (ns,)), g=take("<f4", (ng,)),
                      coef_quant=take("<f4", (3, 2)), coef_q=take("<u2", (3, na, ns, ng)),
                      inv_frame=take("<f4", (ns, 6)), inv_alpha_q=take("<u2", (ns, ny, nx)),
                      inv_g_q=take("<u2", (ns, ny, nx)))
        for axis in ("alpha", "log_sigma_t", "g"):
            a = arrays[axis]
            if not (np.all(np.isfinite(a)) and np.all(np.diff(a) > 0)):
                raise MapFileError(f"{source}: axis {axis} is not finite and strictly increasing")
        floats = np.array([n, thickness, cover_n, rho_b, rho_w, mc_stderr])
        if not (np.all(np.isfinite(floats)) and np.all(np.isfinite(arrays["coef_quant"]))
                and np.all(np.isfinite(arrays["inv_frame"]))):
            raise MapFileError(f"{source}: non-finite number in the header or payload")
        if not (1 <= n <= 3 and 0 < thickness <= 100 and 0 <= rho_b < rho_w <= 1 and arrays["alpha"][0] >= 0
                and arrays["alpha"][-1] <= 1 and arrays["g"][0] > -1 and arrays["g"][-1] < 1):
            raise MapFileError(f"{source}: impossible sample set-up or axis range in the header")
        if _reserved or any(_pad) or b"\0" in name.rstrip(b"\0"):
            raise MapFileError(f"{source}: reserved header bytes are not zero (written by a newer or broken tool)")
        if not (cover_n == 0 or 1 <= cover_n <= 3) or mc_stderr < 0:
            raise MapFileError(f"{source}: impossible cover-slide index or MC std-error in the header")
        try:
            name_str = name.rstrip(b"\0").decode()
        except UnicodeDecodeError:
            raise MapFileError(f"{source}: map name is not UTF-8") from None
        return cls(name=name_str, source_checksum=digest.hex(), n=float(n), thickness_mm=float(thickness),
                   cover_slide_n=float(cover_n) or None, rho_b_ref=float(rho_b), rho_w_ref=float(rho_w),
                   mc_stderr=float(mc_stderr), **arrays)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_bytes(self.to_bytes())
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "MapTable":
        path = Path(path)
        table = cls.from_bytes(read_bounded(path, MAX_TABLE_BYTES, "map table"), source=str(path))
        object.__setattr__(table, "path", path)
        return table

    def info(self) -> dict:
        ny, nx = self.inv_alpha_q.shape[1:]
        return {
            "kind": "map-table", "format_version": TABLE_FORMAT_VERSION, "name": self.name,
            "path": str(self.path) if self.path else None, "size_bytes": self.size_bytes,
            "slot_capacity_bytes": MAX_TABLE_BYTES, "source_map_sha256": self.source_checksum,
            "crc32": f"{zlib.crc32(self.to_bytes()[:-4]):08x}",
            "sample": {"n": self.n, "thickness_mm": self.thickness_mm, "cover_slide_n": self.cover_slide_n},
            "reference_rho": {"black": self.rho_b_ref, "white": self.rho_w_ref},
            "forward_grid": {"alpha": len(self.alpha), "sigma_t": len(self.log_sigma_t), "g": len(self.g)},
            "inverse_grid": {"sigma_t": len(self.log_sigma_t), "x": nx, "y": ny},
            "range": {"alpha": [float(self.alpha[0]), float(self.alpha[-1])],
                      "sigma_t": [float(self.sigma_t[0]), float(self.sigma_t[-1])],
                      "g": [float(self.g[0]), float(self.g[-1])]},
            "mc_stderr": self.mc_stderr,
        }


def _total_size(na: int, ns: int, ng: int, nx: int, ny: int) -> int:
    return (HEADER_SIZE + 4 * (na + ns + ng + 6) + 2 * 3 * na * ns * ng + 24 * ns
            + 2 * 2 * ns * nx * ny + 4)


def describe_table(path_or_bytes) -> dict:
    """`trimeter map info` for a .tlut file (path) or raw table bytes (e.g. read back from a slot)."""
    if isinstance(path_or_bytes, (bytes, bytearray, memoryview)):
        return MapTable.from_bytes(bytes(path_or_bytes)).info()
    return MapTable.load(path_or_bytes).info()


def table_path_for(map_path: str | Path) -> Path:
    """maps/<name>.tmap → maps/<name>.tlut."""
    return Path(map_path).with_suffix(TABLE_SUFFIX)


# ------------------------------------------------------------------------------------------ build
def _quantize(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    scaled = np.round((np.asarray(values, dtype=np.float64) - lo) / max(hi - lo, 1e-30) * _Q)
    return np.clip(np.nan_to_num(scaled, nan=0.0), 0, _Q).astype(np.uint16)


def _inverse_size_for(na: int, ns: int, ng: int, budget: int, max_xy: int) -> int:
    for nxy in range(max_xy, 7, -1):
        if _total_size(na, ns, ng, nxy, nxy) <= budget:
            return nxy
    raise MapFileError(f"a {na}×{ns}×{ng} map does not fit a {budget}-byte map table even with an 8×8 "
                       f"inverse grid; build the table from a coarser map")


# Forward-grid refinement (α, σt, g factors) used when the map is smooth enough to gain from it: on a
# smooth map refining σt is what helps, while splines through a noisy map's nodes make g worse, so
# noisy maps keep their own grid (figures: maps/README.md).
_REFINE_SMOOTH = (1, 2, 1)
_SMOOTH_STDERR = 5e-4
_MIN_XY = 9


def build_from_map(amap, n_xy: int | None = None, budget: int = MAX_TABLE_BYTES, max_xy: int = 64,
                   refine: tuple[int, int, int] | None = None) -> MapTable:
    """The map table of an AppearanceMap.

    The forward section is the map resampled onto its axes refined by `refine` (ForwardGrid.refined)
    (default: _REFINE_SMOOTH for a map whose MC std-error is below _SMOOTH_STDERR and that still
    fits, else the map's own grid), so the run-time trilinear evaluation follows the map's curvature
    between its nodes. `n_xy` (the inverse grid's side) defaults to the largest that fits `budget`
    bytes."""
    na0, ns0, ng0 = amap.A.shape
    if refine is None:
        mc = float(np.median(np.concatenate([np.ravel(amap.std_b), np.ravel(amap.std_w)])))
        na, ns, ng = ((n - 1) * r + 1 for n, r in zip((na0, ns0, ng0), _REFINE_SMOOTH, strict=True))
        smooth_fits = mc < _SMOOTH_STDERR and _total_size(na, ns, ng, _MIN_XY, _MIN_XY) <= budget
        refine = _REFINE_SMOOTH if smooth_fits else (1, 1, 1)
    # the map between its nodes (ForwardGrid.refined); an axis with fewer than 4 nodes stays as it is
    factors = [r if len(ax) >= 4 else 1 for ax, r in zip((amap.alpha, amap.sigma_t, amap.g), refine, strict=True)]
    grid = ForwardGrid.from_map(amap).refined(*factors)
    alpha_axis, log_s_axis, g_axis = grid.alpha, grid.log_sigma_t, grid.g
    coef = np.moveaxis(grid.coefficients_grid, -1, 0)  # (A, B, C) first
    na, ns, ng = coef.shape[1:]
    nxy = n_xy if n_xy is not None else _inverse_size_for(na, ns, ng, budget, max_xy)
    if _total_size(na, ns, ng, nxy, nxy) > budget:
        raise MapFileError(f"map table would be {_total_size(na, ns, ng, nxy, nxy)} bytes, "
                           f"over the {budget}-byte budget")
    rho_b, rho_w = amap.reference_rhos
    quant = np.array([[c.min(), (c.max() - c.min()) / _Q or 1.0] for c in coef], dtype=np.float32)
    coef_q = np.stack([_quantize(c, float(q[0]), float(q[0]) + float(q[1]) * _Q)
                       for c, q in zip(coef, quant, strict=True)])

    frames, inv_a, inv_g = inverse_grid(grid, nxy, (rho_b, rho_w))
    mc = float(np.median(np.concatenate([amap.std_b.ravel(), amap.std_w.ravel()])))
    return MapTable(name=amap.name[:24], source_checksum=amap.checksum or "", n=amap.n,
                    thickness_mm=amap.thickness_mm, cover_slide_n=amap.cover_slide_n,
                    rho_b_ref=rho_b, rho_w_ref=rho_w, mc_stderr=mc,
                    alpha=alpha_axis.astype(np.float32), log_sigma_t=log_s_axis.astype(np.float32),
                    g=g_axis.astype(np.float32), coef_quant=quant, coef_q=coef_q, inv_frame=frames,
                    inv_alpha_q=inv_a, inv_g_q=inv_g)


def inverse_grid(grid: ForwardGrid, nxy: int, reference_rhos: tuple[float, float]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The inverse slices of a forward grid at the reference backgrounds, as a map table stores them:
    (frames f32 (ns, 6), α codes u16 (ns, nxy, nxy), g codes u16 (ns, nxy, nxy)).

    For each σt node, (α, g) at every (x, y) = (√I_b, √I_w) grid point of the slice's bounding box.
    Start from the nearest of a dense forward sample (the grid's axes refined), then polish with the
    forward kernel's Newton solve, so stored entries are the map's own inverse (projected onto the
    gamut where a grid point lies outside it)."""
    from scipy.spatial import cKDTree

    from trimeter.inversion.kernel import default_kernel

    rho_b, rho_w = reference_rhos
    alpha_axis, log_s_axis, g_axis = grid.alpha, grid.log_sigma_t, grid.g
    ns = len(log_s_axis)
    aa, gg = (v.ravel() for v in np.meshgrid(refine_axis(alpha_axis, 2), refine_axis(g_axis, 2), indexing="ij"))
    frames = np.zeros((ns, 6), dtype=np.float32)
    starts_a, starts_g = np.zeros((ns, nxy, nxy)), np.zeros((ns, nxy, nxy))
    targets = np.zeros((ns, nxy, nxy, 2))
    uv = np.linspace(0.0, 1.0, nxy)
    for k in range(ns):  # one KD-tree per σt node (build time only)
        cell = grid.sigma_cell(np.full(aa.shape, np.exp(log_s_axis[k])))
        coef, _, _ = grid.coefficients(aa, cell, gg)
        xy = np.sqrt(np.clip(np.column_stack([grid.diffuse(coef, rho_b)[0], grid.diffuse(coef, rho_w)[0]]), 0, None))
        frame = _gamut_frame(xy)
        frames[k] = frame
        uu, vv = np.meshgrid(uv, uv)  # (n_y, n_x): u along x-index, v along y-index
        gxy = _from_frame(frames[k].astype(np.float64), uu.ravel(), vv.ravel())
        _, nearest = cKDTree(xy).query(gxy)
        starts_a[k] = aa[nearest].reshape(nxy, nxy)
        starts_g[k] = gg[nearest].reshape(nxy, nxy)
        targets[k] = (np.clip(gxy, 0, 1) ** 2).reshape(nxy, nxy, 2)
    node = np.broadcast_to(np.exp(log_s_axis)[:, None, None], (ns, nxy, nxy)).ravel()
    m = node.size
    alpha_sol, g_sol, _, _ = default_kernel().solve_alpha_g(
        grid, targets[..., 0].ravel(), targets[..., 1].ravel(), grid.sigma_cell(node), np.full(m, rho_b),
        np.full(m, rho_w), starts_a.ravel(), starts_g.ravel(), iterations=12)
    inv_a = _quantize(alpha_sol, alpha_axis[0], alpha_axis[-1]).reshape(ns, nxy, nxy)
    inv_g = _quantize(g_sol, g_axis[0], g_axis[-1]).reshape(ns, nxy, nxy)
    return frames, inv_a, inv_g


def _gamut_frame(xy: np.ndarray) -> np.ndarray:
    """(x0, y0, m00, m01, m10, m11): the affine map taking the point cloud's principal-axes bounding
    box onto [0, 1]², u along the major axis."""
    centre = xy.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov((xy - centre).T) + 1e-18 * np.eye(2))
    rot = vecs[:, ::-1].T  # rows: major, minor axis
    proj = (xy - centre) @ rot.T
    lo, hi = proj.min(axis=0), proj.max(axis=0)
    span = np.maximum(hi - lo, 1e-7)
    m = rot / span[:, None]
    origin = centre + rot.T @ lo  # the point mapping to (u, v) = (0, 0)
    return np.array([origin[0], origin[1], m[0, 0], m[0, 1], m[1, 0], m[1, 1]])


def _from_frame(frame: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Inverse of the frame: (u, v) → (x, y), shape (N, 2)."""
    m = frame[2:].reshape(2, 2)
    return frame[:2] + np.column_stack([u, v]) @ np.linalg.inv(m).T
