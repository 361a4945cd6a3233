"""Phase functions the scenes can name (scene_dict's `phase`): Mitsuba's `hg`, and `hg_depolarising`.

In Mitsuba's polarised variants `hg` returns its value times the identity Mueller matrix: a scattered ray
keeps its Stokes vector (not even rotated into the new direction's frame), so the light stays as polarised
as the faces made it. `hg_depolarising` is the same Henyey-Greenstein distribution, sampled the same way
(same random numbers, same directions), whose Mueller matrix is a depolariser: every scattering event leaves
unpolarised light. A real medium lies between the two (multiple scattering depolarises; a single particle
also polarises), so the two bound what tracking polarisation at the faces changes. In unpolarised variants
the two are the same function (tests/forward/test_phase.py renders them bit for bit alike).
"""

from __future__ import annotations

from types import ModuleType

PHASES = ("hg", "hg_depolarising")

_registered: set[str] = set()  # variants whose plugin registry has hg_depolarising


def register_phases(mi: ModuleType) -> None:
    """Register `hg_depolarising` with the current variant (each variant has its own registry; idempotent)."""
    variant = mi.variant()
    if variant in _registered:
        return
    import drjit as dr

    class DepolarisingHG(mi.PhaseFunction):  # type: ignore[name-defined]
        """Henyey-Greenstein with a depolarising Mueller matrix; sampling as Mitsuba's hg (src/phase/hg.cpp)."""

        def __init__(self, props):
            mi.PhaseFunction.__init__(self, props)
            self.g = mi.Float(props.get("g", 0.8))
            self.m_flags = mi.PhaseFunctionFlags.Anisotropic

        def _hg(self, cos_theta):
            temp = 1.0 + self.g * self.g + 2.0 * self.g * cos_theta
            return dr.inv_four_pi * (1.0 - self.g * self.g) / (temp * dr.sqrt(temp))

        def sample(self, ctx, mei, sample1, sample2, active=True):
            g = self.g
            sqr = (1.0 - g * g) / (1.0 - g + 2.0 * g * sample2.x)
            cos_theta = dr.select(dr.abs(g) < dr.epsilon(mi.Float), 1.0 - 2.0 * sample2.x,
                                  (1.0 + g * g - sqr * sqr) / (2.0 * g))
            sin_theta = dr.safe_sqrt(1.0 - cos_theta * cos_theta)
            sin_phi, cos_phi = dr.sincos(2.0 * dr.pi * sample2.y)
            # the shading frame's z is wi (pointing back along the ray), so forward scattering is −z
            wo = mei.to_world(mi.Vector3f(sin_theta * cos_phi, sin_theta * sin_phi, -cos_theta))
            return wo, mi.depolarizer(mi.Spectrum(1.0)), self._hg(-cos_theta)

        def eval_pdf(self, ctx, mei, wo, active=True):
            pdf = self._hg(dr.dot(wo, mei.wi))
            return mi.depolarizer(mi.Spectrum(pdf)), pdf

        def traverse(self, callback):
            callback.put("g", self.g, mi.ParamFlags.NonDifferentiable)

        def parameters_changed(self, keys=None):
            pass

        def to_string(self):
            return f"DepolarisingHG[g = {self.g}]"

    mi.register_phase("hg_depolarising", lambda props: DepolarisingHG(props))
    _registered.add(variant)
