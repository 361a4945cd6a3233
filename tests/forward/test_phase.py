"""trimeter.forward.phase: `hg_depolarising` is Mitsuba's `hg` with a depolarising Mueller matrix."""

from __future__ import annotations

import numpy as np
import pytest

from trimeter.errors import InputError

pytestmark = pytest.mark.slow  # renders with Mitsuba (a few seconds)


@pytest.fixture(scope="module")
def mitsuba_variants():
    pytest.importorskip("mitsuba")
    from trimeter.bench.polarisation import variants
    from trimeter.forward.mitsuba_env import MitsubaUnavailable

    try:
        return variants()
    except MitsubaUnavailable as exc:
        pytest.skip(str(exc))


def test_unpolarised_it_renders_as_hg_bit_for_bit_after_the_material_changes(mitsuba_variants):
    """Same random numbers, same directions, same weights: in the unpolarised variant the two plugins are one
    function. The scene is loaded with other values and updated in place, so g reaches the plugin."""
    from trimeter.forward.mitsuba_env import mitsuba
    from trimeter.forward.render import render_diffuse_batches

    mitsuba(mitsuba_variants[0])
    out = {phase: render_diffuse_batches("ideal", 0.9, 4.0, 0.8, 1.5, 0.5, 0.5, spp=4096, seed=2, phase=phase)
           for phase in ("hg", "hg_depolarising")}
    np.testing.assert_array_equal(out["hg_depolarising"], out["hg"])
    other_g = render_diffuse_batches("ideal", 0.9, 4.0, -0.3, 1.5, 0.5, 0.5, spp=4096, seed=2,
                                     phase="hg_depolarising")
    assert abs(other_g.mean() - out["hg"].mean()) > 0.01  # g = −0.3 back-scatters more: the update took


def test_polarised_it_samples_as_hg_and_returns_a_depolariser(mitsuba_variants):
    import drjit as dr

    from trimeter.forward.mitsuba_env import mitsuba
    from trimeter.forward.phase import register_phases

    mi = mitsuba(mitsuba_variants[1])
    try:
        register_phases(mi)
        hg, depolarising = (mi.load_dict({"type": t, "g": 0.6}) for t in ("hg", "hg_depolarising"))
        mei = dr.zeros(mi.MediumInteraction3f, 5)
        mei.wi = dr.normalize(mi.Vector3f([0.1, 0.3, -0.5, 0.0, 0.2], [0.2, -0.1, 0.4, 0.0, 0.9],
                                          [1.0, 0.8, -0.6, 1.0, -0.1]))
        mei.sh_frame = mi.Frame3f(mei.wi)
        ctx = mi.PhaseFunctionContext()
        u = mi.Point2f([0.1, 0.5, 0.9, 0.33, 0.7], [0.2, 0.8, 0.4, 0.6, 0.05])
        (wo_hg, w_hg, pdf_hg), (wo_d, w_d, pdf_d) = (p.sample(ctx, mei, 0.5, u) for p in (hg, depolarising))
        np.testing.assert_allclose(np.array(wo_d), np.array(wo_hg), atol=1e-6)
        np.testing.assert_allclose(np.array(pdf_d), np.array(pdf_hg), rtol=1e-5)
        value_hg, _ = hg.eval_pdf(ctx, mei, wo_hg)
        value_d, pdf = depolarising.eval_pdf(ctx, mei, wo_hg)
        np.testing.assert_allclose(np.array(pdf), np.array(pdf_hg), rtol=1e-5)
        m_hg, m_d = np.array(value_hg).squeeze(), np.array(value_d).squeeze()  # (4, 4, lanes)
        np.testing.assert_allclose(m_hg, np.einsum("ij,k->ijk", np.eye(4), m_hg[0, 0]), rtol=1e-6)  # Mitsuba's hg
        np.testing.assert_allclose(m_d[0, 0], m_hg[0, 0], rtol=1e-5)
        m_d[0, 0] = 0
        assert not m_d.any()  # only intensity out, whatever came in
        assert not np.array(w_d).squeeze()[1:, :].any() and not np.array(w_d).squeeze()[:, 1:].any()
    finally:
        mitsuba(mitsuba_variants[0])


def test_an_unknown_phase_is_refused(mitsuba_variants):
    from trimeter.forward.render import render_diffuse_batches

    with pytest.raises(InputError, match="phase"):
        render_diffuse_batches("ideal", 0.9, 4.0, 0.8, 1.5, 0.5, 0.5, spp=64, phase="rayleigh")
