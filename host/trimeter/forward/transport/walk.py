"""The random walk of the map tracer: one trace's fixed inputs, the step every live path takes per
iteration of the Dr.Jit symbolic loop (free flight, scattering, interfaces, the gap and the background,
side faces, termination), and the waves that run the loop and drop finished paths."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from trimeter.forward.transport.backend import load_drjit
from trimeter.forward.transport.sampling import cosine_direction, henyey_greenstein
from trimeter.forward.transport.scene import Stack, panel_margin, sees_light, side_entry
from trimeter.forward.transport.tally import N_BACKGROUND_ORDERS
from trimeter.model.fresnel import fresnel, fresnel_polarised

# A bounce series' count of reflections since the last bounce once it stopped being plain.
NOT_PLAIN = 255

# The symbolic loop's state, in `Walk.step`'s argument order (then, with polarisation, the s-share of the
# path's intensity; in a bounce series' first pass, its count of reflections since the first bounce; then the
# random stream).
LOOP_STATE = ("x", "y", "z", "dx", "dy", "dz", "li", "k", "m", "it", "alive", "hit", "nee_k", "bounce_x", "bounce_y",
              "nee_u", "nee_v", "straight", "clean", "x0", "y0", "reach2", "escape")

# Per lane, what a pass leaves: the path's outcome (and the first pass, its first bounce); a bounce
# series' passes also leave, for the paths they cut at a bounce, all that a path needs to go on.
OUTCOME = [("k", np.uint32), ("m", np.uint32), ("it", np.uint32), ("hit", bool)]
FIRST_BOUNCE_RECORD = [("nee_k", np.uint32), ("bounce_x", np.float32), ("bounce_y", np.float32),
                       ("nee_u", np.float32), ("nee_v", np.float32), ("clean", bool)]
CARRIED = [(name, np.float32) for name in ("x", "y", "z", "dx", "dy", "dz", "x0", "y0", "reach2")] + [
    ("li", np.uint32)]

# A path's own way to the light is averaged over this many turns of the path (see Walk.rotation_average);
# 1: not averaged.
ROTATIONS = 32


# The s-share of unpolarised light.
UNPOLARISED = 0.5


class Walk:
    """One trace's walk: the stack and material as the kernel sees them (σt and g opaque inputs, so one
    compiled kernel serves every (σt, g) column; literals would be baked in and force a fresh LLVM
    compile per column), the options that shape the loop, and the loop itself (`step`, `run`).

    `polarisation` (off: unpolarised Fresnel at every interface, the maps' default) tracks the two
    polarisations at the interfaces. The model: the panels' and the background's light is unpolarised, and
    every scattering event depolarises (a path's light leaves it unpolarised, as Mitsuba's polarised variant
    with trimeter.forward.phase's hg_depolarising has it). Between two such events a path meets only planes
    parallel to z (the stack's faces, the cover slides' faces, the gap's bottom face), and the plane of
    incidence at each is the plane of the path's own direction and z, which reflection and refraction keep;
    so the light along the path stays a mix of s and p (no coherence between them arises from
    unpolarised light), and its state is one number, the s-share w of its intensity (UNPOLARISED: 1/2).
    At an interface with reflectances R_s, R_p a path reflects with probability P = w·R_s + (1 − w)·R_p
    (an analog choice, so its intensity stays unbiased at weight 1), then w ← w·R_s / P after a
    reflection, w ← w·T_s / (1 − P) after a refraction (T = 1 − R). w is reset to 1/2 at a scattering, at
    the background's bounce and at a side face: there the plane of incidence is another one, and the
    faces' own (unpolarised) reflectance is used; an approximation (maps/README.md: how much it moves). The
    detector's path starts unpolarised too: the adjoint of a polarisation-blind detector, and the first
    face is crossed at normal incidence, where s and p reflect alike. The adjoint walk gives the forward
    one's intensity because each interface acts on (s, p) intensities by the same diagonal factors
    both ways."""

    def __init__(self, stack: Stack, sigma_t: float, g: float, k_max: int, *, wave: int, from_below: bool,
                 backend: str, control_variates: bool, factorise: bool, next_event: bool, background_orders: int,
                 polarisation: bool = False):
        self.dr, self.B = load_drjit(backend)
        self.Float, self.UInt32, self.Bool = self.B.Float, self.B.UInt32, self.B.Bool
        dr = self.dr
        self.stack, self.k_max, self.wave = stack, k_max, wave
        self.from_below, self.factorise, self.polarisation = from_below, factorise, polarisation
        self.control_variates = control_variates and not factorise and next_event
        self.L = len(stack.layer_n)
        self.planes = [float(z) for z in stack.plane_z]
        self.layer_n = [float(v) for v in stack.layer_n]
        self.sample = stack.sample_layer
        self.W, self.WB = stack.stack_half_width, stack.background_half_width
        self.finite = math.isfinite(self.W)
        self.g_is_zero = abs(float(g)) < 1e-4
        self.sigma_t_value = float(sigma_t)
        self.sigma_t = dr.opaque(self.Float, float(sigma_t))
        self.g = dr.opaque(self.Float, float(g) if not self.g_is_zero else 0.5)
        self.max_iter = 8 * k_max + 20000  # TIR bounces between scatterings count too; a safety net only
        self.nee = next_event and not from_below
        self.margin = panel_margin(stack)
        if from_below:
            self.orders = 2                           # a background path stops when it comes back
        else:
            self.orders = 1 if factorise else int(background_orders)
        # A bounce series traces on past the 2nd bounce in passes (trace.go_on): its loop state is the
        # 2-order trace's, plus, in the first pass, for the returns' control variate, the reflections
        # since the first bounce (NOT_PLAIN once anything but an interface crossing happened).
        self.series = self.orders > N_BACKGROUND_ORDERS and self.nee and not factorise
        self.returns_cv = self.control_variates and self.series
        self.averaged = self.nee and bool(stack.panels) and ROTATIONS > 1 and self.control_variates
        self.safe_radius = min(self.W, self.WB)
        self.cut_at = None   # the bounce a pass stops its paths at (an opaque input: one kernel for every pass)
        self.slot = {name: i for i, name in enumerate(LOOP_STATE)}     # then w, the count of reflections, the stream
        if polarisation:
            self.slot["w"] = len(LOOP_STATE)
        self.slot["reflections"] = len(LOOP_STATE) + int(polarisation)

    # ------------------------------------------------------------------ helpers on Dr.Jit arrays
    def per_layer(self, li, values):
        """values[li] per lane (the last value for li ≥ len(values) − 1)."""
        dr = self.dr
        out = self.Float(values[-1])
        for i in range(len(values) - 2, -1, -1):
            out = dr.select(li == i, values[i], out)
        return out

    def light(self, px, py, pz, dx, dy, dz):
        return sees_light(self.dr, self.Bool, self.stack, px, py, pz, dx, dy, dz)

    def side_entry(self, px, py, pz, dx, dy, dz):
        return side_entry(self.dr, self.W, self.planes[-1], self.planes[0], px, py, pz, dx, dy, dz)

    def stop_at(self, bounce: int) -> None:
        self.cut_at = self.dr.opaque(self.UInt32, bounce)

    def polarisation_start(self, n_paths: int) -> list:
        """The loop state after LOOP_STATE for `n_paths` paths starting unpolarised: [w] with polarisation, else []."""
        return [self.dr.full(self.Float, UNPOLARISED, n_paths)] if self.polarisation else []

    # ------------------------------------------------------------------ one step of every path
    def step(self, x, y, z, dx, dy, dz, li, k, m, it, alive, hit, nee_k, bounce_x, bounce_y, nee_u, nee_v, straight,
             clean, x0, y0, reach2, escape, *rest):
        """The loop body: each live path's next event (a scattering, an interface, a side face, the gap
        and the background), its new position and direction, and whether it ends there. The random
        numbers are drawn in one order (free flight, scattering, interface) whatever the event."""
        dr, L = self.dr, self.L
        w: Any = rest[0] if self.polarisation else None     # the s-share (see the class's docstring)
        cv, rng = list(rest[int(self.polarisation):-1]), rest[-1]
        it = it + 1
        in_stack = li < L
        in_gap = li == L
        going_down = dz < 0

        # --- free flight: the next event is a scattering (sample only), an interface or a side face
        u_free = rng.next_float32()
        step, z_plane, scatter, wall, cross, wall_is_x = self._free_flight(x, y, z, dx, dy, dz, li, in_stack,
                                                                           going_down, u_free)
        x, y = x + step * dx, y + step * dy
        z = dr.select(cross, z_plane, z + step * dz)

        # --- scattering: Henyey-Greenstein in closed form, rotated about the current direction
        u1, u2 = rng.next_float32(), rng.next_float32()
        ndx, ndy, ndz = henyey_greenstein(dr, self.g, self.g_is_zero, u1, u2, dx, dy, dz)
        k = dr.select(scatter, k + 1, k)

        # --- interface: Fresnel reflect or refract into the neighbour (air outside the stack)
        n_here = self.per_layer(li, self.layer_n + [1.0])
        # neighbour below layer li is layer li+1 (air under the last); above it li−1 (air over the
        # first); from the gap going up, the bottom layer
        n_next = dr.select(going_down, self.per_layer(li, self.layer_n[1:] + [1.0, 1.0]),
                           self.per_layer(li, [1.0] + self.layer_n))
        u_f = rng.next_float32()
        if self.polarisation:
            R_s, R_p, cos_tr = fresnel_polarised(dr, dr.abs(dz), n_next / n_here)
            F = w * R_s + (1 - w) * R_p
        else:
            F, cos_tr = fresnel(dr, dr.abs(dz), n_next / n_here)
        ratio = n_here / n_next

        # --- the gap below the stack: background (going down) or the stack's bottom face (going up)
        gx, gy, gap_down, gap_up, on_bg, under_stack = self._gap(x, y, z, dx, dy, dz, in_gap, going_down)
        enter_interface = cross | under_stack
        reflect = enter_interface & (u_f < F)
        refract = enter_interface & ~reflect
        side, side_in, (sx, sy, sz), side_dir, side_li = self._side_faces(x, y, z, dx, dy, dz, gap_up, under_stack,
                                                                          u_f)
        x, y = dr.select(side, sx, dr.select(in_gap, gx, x)), dr.select(side, sy, dr.select(in_gap, gy, y))
        z = dr.select(side, sz, dr.select(gap_down, self.stack.background_z, dr.select(gap_up, self.planes[-1], z)))

        # --- Lambertian background bounce: m += 1, cosine-sampled upward direction
        m = dr.select(on_bg, m + 1, m)
        lx, ly, lz = cosine_direction(dr, u1, u2)
        if self.polarisation:
            # (a reflection has P = F > u_f ≥ 0, a refraction 1 − F > 0: the other branch's 0/0 is not selected)
            w = dr.select(scatter | on_bg | side | wall, UNPOLARISED,
                          dr.select(reflect, w * R_s / F, dr.select(refract, w * (1 - R_s) / (1 - F), w)))

        # --- the new direction: scattered, refracted, reflected, bounced, off a side face or on
        tx, ty = dx * ratio, dy * ratio
        tz = dr.select(going_down, -cos_tr, cos_tr)
        wall_exit, (wdx, wdy, wdz) = self._stack_walls(dx, dy, dz, wall, wall_is_x, n_here, u_f)
        side_dx, side_dy, side_dz = side_dir
        new_dx = dr.select(scatter, ndx, dr.select(refract, tx, dr.select(on_bg, lx, dr.select(
            wall, wdx, dr.select(side, side_dx, dx)))))
        new_dy = dr.select(scatter, ndy, dr.select(refract, ty, dr.select(on_bg, ly, dr.select(
            wall, wdy, dr.select(side, side_dy, dy)))))
        new_dz = dr.select(scatter, ndz, dr.select(refract, tz, dr.select(reflect, -dz, dr.select(
            on_bg, lz, dr.select(wall, wdz, dr.select(side, side_dz, dz))))))
        # A ray leaving a side face downward goes on through the air below the stack (the gap's state
        # from wherever it is): it can land on the background's rim outside the stack's footprint.
        wall_down = wall_exit & (wdz < 0)
        new_li = dr.select(refract, dr.select(in_gap, L - 1, dr.select(going_down, li + 1, li - 1)),
                           dr.select(wall_down, L, dr.select(side_in, side_li, li)))

        # --- termination: left through the top (light?), past the stack's edge, lost, or truncated
        out_top = refract & in_stack & ~going_down & (li == 0)
        escaped_up = gap_up & ~under_stack & ~side_in
        reach_light = (out_top | escaped_up | wall_exit) & self.light(x, y, z, new_dx, new_dy, new_dz)
        cut = on_bg & (m >= self.cut_at)
        lost = (gap_down & ~on_bg) | cut
        done = (out_top | escaped_up | (wall_exit & ~wall_down) | lost | (k >= self.k_max)
                | (it >= self.max_iter))

        # --- the records of the next-event estimates and control variates
        if self.nee:
            # The first bounce estimates the straight way out (u_free, u_f are unused at a bounce);
            # the path goes on, and its own straight way out is not counted again.
            first_bounce = alive & on_bg & (m == 1)
            bounce_x, bounce_y = dr.select(first_bounce, x, bounce_x), dr.select(first_bounce, y, bounce_y)
            nee_u, nee_v = dr.select(first_bounce, u_free, nee_u), dr.select(first_bounce, u_f, nee_v)
            nee_k = dr.select(first_bounce, k, nee_k)
            if cv:  # the first pass of a bounce series: it ends at the 2nd bounce, with that count
                UInt32 = self.UInt32
                counted = dr.minimum(cv[0] + dr.select(reflect, UInt32(1), UInt32(0)), NOT_PLAIN)
                cv = [dr.select(first_bounce, UInt32(0), dr.select(scatter | wall | side, UInt32(NOT_PLAIN), counted))]
            # Every bounce estimates the straight way out: the path's own is counted after none.
            straight = dr.select(alive & on_bg, True, straight & ~(scatter | reflect | wall | side))
            # Straight down needs one iteration per interface and one through the gap; any scattering
            # or reflection on the way adds iterations (a vertical ray meets no side face).
            clean = dr.select(first_bounce, it == L + 1, clean)
            reach_light &= ~straight
            escape = escape | (alive & out_top & ~straight)
        hit = hit | (alive & (cut if self.from_below and not self.factorise else reach_light))
        alive = alive & ~done
        reach2 = dr.maximum(reach2, (x - x0) * (x - x0) + (y - y0) * (y - y0))
        return (x, y, z, new_dx, new_dy, new_dz, dr.select(out_top, li, new_li), k, m, it, alive, hit, nee_k,
                bounce_x, bounce_y, nee_u, nee_v, straight, clean, x0, y0, reach2, escape,
                *([w] if self.polarisation else []), *cv, rng)

    def _free_flight(self, x, y, z, dx, dy, dz, li, in_stack, going_down, u_free):
        """How far each path goes to its next event inside a layer, and which: (step, the plane it
        would cross, scatter, side wall, interface crossing, whether the wall is an x face)."""
        dr, W = self.dr, self.W
        z_top = self.per_layer(li, self.planes[:-1] + [self.planes[-1]])
        z_bot = self.per_layer(li, self.planes[1:] + [self.stack.background_z])
        z_plane = dr.select(going_down, z_bot, z_top)
        dist_plane = dr.select(dz != 0, (z_plane - z) / dz, dr.inf)
        dist_scatter = dr.select(in_stack & (li == self.sample), -dr.log(1 - u_free) / self.sigma_t, dr.inf)
        if self.finite:
            to_wall_x = dr.select(dx > 0, (W - x) / dx, dr.select(dx < 0, (-W - x) / dx, dr.inf))
            to_wall_y = dr.select(dy > 0, (W - y) / dy, dr.select(dy < 0, (-W - y) / dy, dr.inf))
            dist_wall = dr.minimum(to_wall_x, to_wall_y)
            wall_is_x = to_wall_x <= to_wall_y
        else:
            dist_wall = self.Float(dr.inf)
            wall_is_x = self.Bool(True)
        scatter = in_stack & (dist_scatter < dist_plane) & (dist_scatter < dist_wall)
        wall = in_stack & ~scatter & (dist_wall < dist_plane)
        cross = in_stack & ~scatter & ~wall
        step = dr.select(scatter, dist_scatter, dr.select(cross, dist_plane, dr.select(wall, dist_wall, 0.0)))
        return step, z_plane, scatter, wall, cross, wall_is_x

    def _gap(self, x, y, z, dx, dy, dz, in_gap, going_down):
        """Paths in the gap: where they meet the background (going down) or the stack's bottom plane
        (going up), and whether they land on the background or come up under the stack."""
        dr, W, WB = self.dr, self.W, self.WB
        dist_bg = dr.select(going_down, (self.stack.background_z - z) / dz, (self.planes[-1] - z) / dz)
        gx, gy = x + dist_bg * dx, y + dist_bg * dy
        gap_down = in_gap & going_down
        gap_up = in_gap & ~going_down
        on_bg = gap_down & (dr.abs(gx) <= WB) & (dr.abs(gy) <= WB)
        under_stack = gap_up & (dr.abs(gx) <= W) & (dr.abs(gy) <= W)
        return gx, gy, gap_down, gap_up, on_bg, under_stack

    def _side_faces(self, x, y, z, dx, dy, dz, gap_up, under_stack, u_f):
        """A ray rising from the background's rim (outside the footprint) towards the stack can meet a
        side face, the more so the thicker the stack: Fresnel-reflected off it (it then rises away,
        past the stack) or refracted into the layer there. Not straight (see the next-event records).
        (meets one, goes in, where, the new direction, the layer it goes into)."""
        dr, Float, UInt32 = self.dr, self.Float, self.UInt32
        if not self.finite:
            zero = Float(0.0)
            return self.Bool(False), self.Bool(False), (zero, zero, zero), (zero, zero, zero), UInt32(0)
        meets_x, meets_y, t_side = self.side_entry(x, y, z, dx, dy, dz)
        side = gap_up & ~under_stack & (meets_x | meets_y)
        sx, sy, sz = x + t_side * dx, y + t_side * dy, z + t_side * dz
        side_li = UInt32(0)
        for i in range(1, self.L):
            side_li = side_li + dr.select(sz < self.planes[i], UInt32(1), UInt32(0))
        n_side = self.per_layer(side_li, self.layer_n)
        F_s, cos_s = fresnel(dr, dr.select(meets_x, dr.abs(dx), dr.abs(dy)), n_side)
        side_reflect = side & (u_f < F_s)
        side_in = side & ~side_reflect
        inward_x, inward_y = dr.select(dx > 0, cos_s, -cos_s), dr.select(dy > 0, cos_s, -cos_s)
        side_dx = dr.select(meets_x, dr.select(side_reflect, -dx, inward_x),
                            dr.select(side_reflect, dx, dx / n_side))
        side_dy = dr.select(meets_x, dr.select(side_reflect, dy, dy / n_side),
                            dr.select(side_reflect, -dy, inward_y))
        side_dz = dr.select(side_reflect, dz, dz / n_side)
        return side, side_in, (sx, sy, sz), (side_dx, side_dy, side_dz), side_li

    def _stack_walls(self, dx, dy, dz, wall, wall_is_x, n_here, u_f):
        """Side faces of the stack from inside (device): a dielectric layer|air; reflect back in, or
        leave into the air. (leaves, the direction after the wall)."""
        dr = self.dr
        d_norm = dr.select(wall_is_x, dx, dy)
        F_w, cos_w = fresnel(dr, dr.abs(d_norm), 1.0 / n_here)
        wall_reflect = wall & (u_f < F_w)
        wall_exit = wall & ~wall_reflect
        out_norm = dr.select(d_norm > 0, cos_w, -cos_w)
        wdx = dr.select(wall_reflect, dr.select(wall_is_x, -dx, dx),
                        dr.select(wall_is_x, out_norm, dx * n_here))
        wdy = dr.select(wall_reflect, dr.select(wall_is_x, dy, -dy),
                        dr.select(wall_is_x, dy * n_here, out_norm))
        wdz = dr.select(wall_reflect, dz, dz * n_here)
        return wall_exit, (wdx, wdy, wdz)

    # ------------------------------------------------------------------ the rotation average
    def rotation_average(self, s):
        """A detector path's own way to the light (h = 1 if it reached a panel), averaged over the
        path turned about the vertical through its start by 2πi/ROTATIONS, i = 0…ROTATIONS−1.
        Unbiased (Rao-Blackwell over a rotation group): inside a disc around the axis where the stack
        and background are unbounded for every turned copy (the path and its start within
        min(W, WB) of it), the layers, the Lambertian background and the straight-down start are
        symmetric about any vertical, so each turned copy is as likely as the path itself; only
        the panels break the symmetry, and they are what is averaged. Elsewhere h stays 0/1."""
        dr, slot = self.dr, self.slot
        px, py, pz, ux, uy, uz = (s[slot[name]] for name in ("x", "y", "z", "dx", "dy", "dz"))
        sx, sy, reach, left = (s[slot[name]] for name in ("x0", "y0", "reach2", "escape"))
        inside = dr.sqrt(sx * sx + sy * sy) + dr.sqrt(reach) < self.safe_radius
        total = self.Float(0.0)
        for i in range(ROTATIONS):
            c, sn = math.cos(2 * math.pi * i / ROTATIONS), math.sin(2 * math.pi * i / ROTATIONS)
            rx, ry = sx + c * (px - sx) - sn * (py - sy), sy + sn * (px - sx) + c * (py - sy)
            total += dr.select(self.light(rx, ry, pz, c * ux - sn * uy, sn * ux + c * uy, uz), 1.0, 0.0)
        return dr.select(left & inside, total / ROTATIONS, dr.select(s[slot["hit"]], 1.0, 0.0))

    # ------------------------------------------------------------------ the loop, in waves
    def run(self, state, recorded, cut_bounce=None, wave_length=None):
        """Runs the paths of `state` to their end, `wave_length` iterations at a time: each lane's final
        values of `recorded` (name, dtype); with `cut_bounce`, those of CARRIED and the random stream
        too, for the lanes that ended cut at that bounce (the others' stay 0).
        Waves: a symbolic loop runs each SIMD packet until its *slowest* lane is done, and path lengths
        are heavy-tailed; so run `wave_length` iterations at a time, then keep only the live paths (the
        kernel is compiled once: the wave limit is an opaque input). A lane's random stream is its own,
        so the result does not depend on the wave length."""
        dr, B, UInt32, slot = self.dr, self.B, self.UInt32, self.slot
        wave_length = self.wave if wave_length is None else wave_length
        alive_slot, it_slot = slot["alive"], slot["it"]
        n = dr.width(state[0])
        lane = dr.arange(UInt32, n)
        final = {name: np.zeros(n, dtype=dtype) for name, dtype in recorded}   # the kernel's own types: no casts
        if self.averaged:
            final["light"] = np.zeros(n, dtype=np.float32)
        cut_record = {}
        if cut_bounce is not None:
            cut_record = {name: np.zeros(n, dtype=dtype) for name, dtype in CARRIED}
            cut_record.update(rng_state=np.zeros(n, dtype=np.uint64), rng_inc=np.zeros(n, dtype=np.uint64))
        limit = 0
        while True:
            limit += wave_length
            wave_limit = dr.opaque(UInt32, limit)
            state = list(dr.while_loop(tuple(state), lambda *s, bound=wave_limit: s[alive_slot] & (s[it_slot] < bound),
                                       self.step))
            dr.eval(state)
            alive_now = np.asarray(state[slot["alive"]], dtype=bool)
            # Every lane's values, live or not: a live path's are overwritten in the wave where it ends.
            # (Selecting the finished ones first was as slow as the first wave's kernel on large traces.)
            ids = slice(None) if limit == wave_length else np.asarray(lane, dtype=np.int64)
            for name in final:
                if name in slot:
                    final[name][ids] = np.asarray(state[slot[name]])
            if self.averaged:
                light_seen = self.rotation_average(state)
                dr.eval(light_seen)
                final["light"][ids] = np.asarray(light_seen)
            if cut_bounce is not None:   # few lanes, gathered before leaving Dr.Jit
                ended = np.flatnonzero(~alive_now & (final["m"][ids] == cut_bounce))
                if len(ended):
                    lanes = np.arange(n) if isinstance(ids, slice) else ids
                    at = UInt32(ended.astype(np.uint32))
                    sources = [state[slot[name]] for name, _ in CARRIED] + [state[-1].state, state[-1].inc]
                    gathered = [dr.gather(type(v), v, at) for v in sources]
                    dr.eval(gathered)           # one kernel for all
                    for name, values in zip([name for name, _ in CARRIED] + ["rng_state", "rng_inc"], gathered,
                                            strict=True):
                        cut_record[name][lanes[ended]] = np.asarray(values)
            if not alive_now.any():
                return final, cut_record
            keep = UInt32(np.flatnonzero(alive_now).astype(np.uint32))
            rng_old = state[-1]
            rng_new = B.PCG32(rng_old)
            rng_new.state = dr.gather(B.UInt64, rng_old.state, keep)
            rng_new.inc = dr.gather(B.UInt64, rng_old.inc, keep)
            state = [dr.gather(type(v), v, keep) for v in state[:-1]] + [rng_new]
            lane = dr.gather(UInt32, lane, keep)
