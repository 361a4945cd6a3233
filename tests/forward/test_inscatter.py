"""The collimated-beam light tracer: it reproduces the analytic I_c, its next-event estimate agrees with
analog tallies, and in-scattering stays small against I_c where I_c is measurable (paper Fig. 6)."""

import math

import numpy as np
import pytest

from trimeter.forward.transport.inscatter_tracer import collimated_with_inscatter
from trimeter.geometry import load_geometry


def test_unscattered_light_reproduces_the_analytic_collimated_transmittance():
    r = collimated_with_inscatter(0.0, 2.0, 0.9, 0.8, 1.5, photons=40_000, seed=1)
    assert r["inscattered"] == 0.0
    binomial = math.sqrt(r["analytic"] * (1 - r["analytic"]) / r["photons"])
    assert r["unscattered"] == pytest.approx(r["analytic"], abs=4 * binomial)


def test_next_event_estimate_matches_analog_counting_on_a_wide_aperture():
    # A 30 mm aperture makes analog hits common enough to count; the NEE must agree.
    geometry = load_geometry("device")
    geometry["collimated"] = {**geometry["collimated"], "aperture_diameter_mm": 30.0}
    nee = collimated_with_inscatter(0.9, 2.0, 0.9, 0.4, 1.5, photons=40_000, seed=2, geometry=geometry)
    analog = collimated_with_inscatter(0.9, 2.0, 0.9, 0.4, 1.5, photons=40_000, seed=3, geometry=geometry, nee=False)
    assert nee["inscattered"] == pytest.approx(analog["inscattered"], rel=0.06)
    assert nee["inscattered"] > 0.01         # not vacuous: a wide aperture does see scattered light


@pytest.mark.parametrize("thickness", [0.4, 0.8])
def test_inscattering_is_negligible_where_ic_is_measurable(thickness):
    # Worst case for forward scattering: g = 0.9, α = 0.999, σt·ℓ = 1.6 (I_c ≈ 0.2).
    r = collimated_with_inscatter(0.999, 1.6 / thickness, 0.9, thickness, 1.5, photons=20_000, seed=4)
    assert r["inscattered"] < 0.01 * r["analytic"]


def test_one_trace_serves_every_albedo():
    """Light by scattering order: α = 0 leaves only the unscattered beam, and the in-scattered light grows
    with α as a polynomial with non-negative coefficients; a separate trace agrees within its noise."""
    from trimeter.forward.transport.inscatter_tracer import _trace_orders

    unscattered, tally, _ = _trace_orders(5.0, 0.9, 0.8, 1.5, 20_000, 7, None, nee=True)
    assert tally[0] == 0.0 and np.all(tally >= 0) and tally[1:].sum() > 0
    at = [collimated_with_inscatter(a, 5.0, 0.9, 0.8, 1.5, photons=20_000, seed=7)["inscattered"]
          for a in (0.0, 0.5, 0.9, 0.999)]
    assert at[0] == 0.0 and at[1] < at[2] < at[3]
    other = collimated_with_inscatter(0.9, 5.0, 0.9, 0.8, 1.5, photons=20_000, seed=8)["inscattered"]
    assert other == pytest.approx(at[2], rel=0.1)


def test_the_inscatter_table_round_trips_and_refuses_another_map(tmp_path):
    """A small table: its nodes come back as traced, the file round-trips with its checksum, a damaged
    file is refused, and a map refuses a table traced for another thickness or geometry."""
    import shutil

    from trimeter.errors import MapFileError
    from trimeter.forward.transport.inscatter_tracer import build_inscatter_table
    from trimeter.maps.appearance import AppearanceMap, find_map
    from trimeter.maps.inscatter_file import load_inscatter, save_inscatter
    from trimeter.model.inscatter import InscatterTable

    geometry = load_geometry("device")
    table = build_inscatter_table(1.5, 0.8, geometry, photons=3000, shape=(4, 3, 3))
    alphas, taus, gs = InscatterTable.axes(4, 3, 3)
    a, t, g = np.meshgrid(alphas, taus, gs, indexing="ij")
    np.testing.assert_allclose(table.log1p_ratio(a, t / 0.8, g), table.L, atol=1e-12)
    assert np.all(table.L[:, 0] == 0) and np.all(table.L[0] == 0)  # nothing scatters at τ = 0 or α = 0
    assert table.L[-1, -1, -1] > table.L[-1, -1, 0] > 0  # forward scattering sends more into the aperture
    path = tmp_path / "t.tins"
    checksum = save_inscatter(table, path)
    back = load_inscatter(path)
    assert back.checksum == checksum and np.array_equal(back.L, table.L) and back.tau_max == table.tau_max
    data = bytearray(path.read_bytes())
    data[200] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(MapFileError):
        load_inscatter(path)
    shipped = AppearanceMap.load(find_map("device-n1.5-l0.4"))
    shutil.copy(shipped.path, tmp_path / "m.tmap")
    save_inscatter(table, tmp_path / "m.tins")  # traced for ℓ = 0.8 mm, not the map's 0.4
    with pytest.raises(MapFileError, match="does not belong to map"):
        AppearanceMap.load(tmp_path / "m.tmap").inscatter
