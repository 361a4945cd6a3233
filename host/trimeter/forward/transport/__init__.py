"""Monte Carlo light transport for the maps: one path-traced batch per (σt, g) serves every α and every background ρ.

Why it works (paper Sec. 5.1, "reusing the Monte Carlo path space samples"): at fixed σt, g
and geometry, free-flight distances, Fresnel choices and scattering directions do not depend on α or
ρ. Everything is sampled proportionally (no weights besides a constant), so a path that reaches the
light after k scattering events and m background bounces contributes w·α^k·ρ^m. We trace adjoint
paths from the detector without α, record each path's final (k, m, reached-the-light), and histogram
them. Then for every α on the map's axis

    c_m(α) = w/N · Σ_k H[m, k] α^k,     A = c0(α),  B = c1(α)

and I(ρ) = A + Bρ/(1 − Cρ) needs C, the slab's reflectance seen from the (Lambertian) background.
In the ideal geometry, where the background forgets directions, C is exactly that: a detector path
stops at its 2nd background hit, and a second set of paths starts on the background,
cosine-distributed upward, and tallies by k those that come back to it, C(α) = Σ_k R[k] α^k / N_b.
The maps use that for the device too. But there light that came back returns less each time (it
spreads over the finite stack and background, and strays further from the panels' view), so a single
C measured from under the detector overstates a white background's I, most in clear samples (figures:
the git history of maps/README.md). The bounce series is the alternative: detector paths go on to
`background_orders` ≥ 3 bounces, I(ρ) = Σ_m c_m(α)ρ^m (the tail geometric), and C is the one return
coefficient that makes the model equal that series at a reference white (ColumnTally.abc): exact there,
and close to it over the whites an instrument uses. The paths are traced to their 2nd bounce as for
the maps, and those that reach it go on in passes of their own, bounce by bounce, each from where the
last pass cut it with its own random stream (so a path is what one unbroken trace would make it, and
the loop carries no per-bounce records). Past the 2nd bounce, Russian roulette with a constant
survival (a weight, not a power of α: the polynomial stays) spares the long diffusion of light that
comes back into a dense sample from below; a pilot sets the survival (continuation_share). It is not
the maps' default yet (its cost: maps/README.md, open points).

No Russian roulette on α (it would break the polynomial): a path is traced until it escapes, is lost
(sides, past the background), or has K scattering events, where α_max^K ≤ `truncation`. The
truncated remainder of a path is worth at most w·α^K per path, so the truncation error of I is
bounded by w·α^K·(fraction of paths truncated); the tally reports that bound.

In the ideal geometry (an unbounded slab over an unbounded Lambertian background) where and how a
detector path reaches the background says nothing about where it goes next, so B = UT1·UTU factorises
(the slab's transmittance for the detector's direction × its diffuse transmittance up to the light):
detector paths stop at their first background hit and tally UT1, the background paths tally UTU
(reached the light) beside C (came back). A detector path's value then carries UTU's expectation
instead of a second 0/1 outcome, which is most of the noise on a white background at α near 1 (the
nodes that set a column's paths). Factorised columns use none of the control variates below: they
replace 0/1 outcomes by their expectation with coefficient 1, which pays where that light dominates
(clear samples at low α) and adds variance where the rest of the light is comparable (α near 1,
the nodes that set a column's paths). The device's finite stack, background and panels do not
factorise: there, detector paths carry on after the bounce as described above (`Stack.factorises`).

Variance reduction, each unbiased: a next-event estimate at each background bounce; control
variates for light that does not depend on α, which dominates the noise of clear samples (a detector
path's straight first pass to the background with its next-event value, and background paths that
come straight back off the stack: exact expectations replace their 0/1 outcomes; in a bounce series, a
detector path's return from its first bounce by one Fresnel reflection: its expected next-event value
given where it bounced replaces the realised one, series.returns_control_variate); and, where C comes
from background paths, only as many of them as C's share of the error needs (`below_share`). In the
device, whether a path that leaves the top face meets one of the two panels is the main noise of
every dense column and of light scattered in a clear sample: that 0/1 outcome is replaced by its
average over the path turned about the vertical through its start (`ROTATIONS` turns; exact wherever
the turned copies meet no side face or edge, see Walk.rotation_average; its gain was measured in
the git history of maps/README.md).

The loop is a Dr.Jit symbolic loop (compiled once, material and seed are opaque inputs; all cores
via the LLVM backend), run in waves that drop finished paths (Walk.run). The
geometry is a layer stack with closed-form plane intersections, which is exact for both presets of
hardware/geometry.toml: `ideal` (one slab, background right under it, light from the whole upper
hemisphere) and `device` (cover slide | sample | cover slide, an air gap, a finite background, two
rectangular Lambertian LED panels, a 2 mm detector spot; reflectance factor normalised by the white
reference: I = π·L / E with E the panels' irradiance at the background plane, as
trimeter.forward.scenes computes it; panels emit radiance 1 and reflect nothing).
The stack's side faces are dielectric (as in the direct-render scene): light trapped in the stack by
total internal reflection leaves through them. A ray leaving one upward counts if it reaches a panel;
one leaving downward goes on through the air to the background, whose rim outside the stack's
footprint is lit by the panels (on a white background, thin weakly scattering samples send much of
their light this way). Rays rising from that rim towards the stack meet its side faces like any other
interface (the stack shades the rim from the far panel), and a next-event estimate from the rim counts
only directions that pass the stack without entering it.

Fresnel reflection is unpolarised at every interface unless `trace_column(..., polarisation=True)` (a
recipe's `polarisation = true`): then a path carries the s-share of its intensity between scatterings and
the estimators take the s and p chains apart (the model and its limits: walk.Walk; its checks and cost:
maps/README.md). The shipped maps are traced without it.

The package, by concern: `scene` (the stack, its surroundings and lights; intersections), `sampling`
(random streams and directions), `walk` (one step of every path, the symbolic loop in waves),
`estimators` (next-event estimates and the control variates' expectations), `series` (a bounce
series' passes past the 2nd bounce), `tally` (the sums over paths and their statistics), `trace` (one
trace of one kind of path; not re-exported here, where its name would hide the module), `column` (a
column's traces, the map builder's call), `backend` (Dr.Jit), `agreement` (the tracer against Mitsuba's
volpath). The collimated beam's in-scattering has a tracer of its own (`inscatter_tracer`, numpy).
"""

from trimeter.forward.transport.backend import resolve_backend
from trimeter.forward.transport.column import k_max_for, trace_column
from trimeter.forward.transport.scene import Stack
from trimeter.forward.transport.tally import N_BACKGROUND_ORDERS, ColumnTally, Tally

__all__ = ["N_BACKGROUND_ORDERS", "ColumnTally", "Stack", "Tally", "k_max_for", "resolve_backend",
           "trace_column"]
