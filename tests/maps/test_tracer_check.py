"""The map tracer against Mitsuba's volpath over seeded random materials (slow): a subset of
`trimeter bench tracer-check` (which runs 40 materials per geometry and judges p95 |z| ≤ 2.5, |mean z| ≤ 0.5).
Here 16 z-scores per geometry, 8 materials on both backgrounds (each pair from the same renders' seeds), so
the bench's bounds would fail a perfect tracer too often: the mean must lie within 3 of its own standard
error, and p95 |z|, which for 16 values is nearly their largest, ≤ 3.0 (how often a perfect tracer exceeds
either bound, simulated: maps/README.md)."""

import math

import numpy as np
import pytest

from trimeter.forward.validate import random_materials
from trimeter.forward.transport.agreement import Z_P95_MAX, tracer_agreement, z_summary

MATERIALS = 8
P95_MAX = 3.0          # for 16 z-scores (see the module's docstring); the bench's 80 are held to Z_P95_MAX


@pytest.mark.slow
@pytest.mark.parametrize("geometry, ell", [("ideal", 0.5), ("device", 0.4)])
def test_tracer_z_scores_against_volpath(geometry, ell):
    materials = random_materials(MATERIALS, seed=31 if geometry == "ideal" else 32)
    rows = tracer_agreement(geometry, materials, 1.5, ell, paths=1 << 18, spp=1 << 16, seed=5)
    s = z_summary([r["z"] for r in rows])
    print(f"\n{geometry}: {s['count']} z-scores, mean {s['mean']:+.2f} ± {s['mean_stderr']:.2f}, "
          f"p95 |z| {s['p95_abs']:.2f}, max {s['max_abs']:.2f}")
    assert s["count"] == 2 * MATERIALS
    assert s["p95_abs"] <= P95_MAX, rows
    assert abs(s["mean"]) <= 3 * s["mean_stderr"], rows
    if geometry == "ideal":
        z_iad = np.array([r["z_iad"] for r in rows])
        assert np.percentile(np.abs(z_iad), 95) <= Z_P95_MAX, rows


@pytest.mark.parametrize("geometry, orders", [("ideal", 6), ("device", 2), ("device", 17)])
def test_bounce_series_needs_the_device_and_three_to_sixteen_orders(geometry, orders):
    from trimeter.errors import InputError

    with pytest.raises(InputError):
        tracer_agreement(geometry, random_materials(1, seed=3), 1.5, 0.4, series_orders=orders)


def test_z_summary_flags_a_bias_and_a_wide_spread():
    rng = np.random.default_rng(0)
    fair = rng.standard_normal(400)
    assert z_summary(fair)["ok"]
    assert not z_summary(fair + 0.8)["ok"]            # biased
    assert not z_summary(fair * 2.0)["ok"]            # std-errors too small by half
    s = z_summary([1.0, -1.0, 3.0])
    assert s["count"] == 3 and math.isclose(s["mean"], 1.0) and s["max_abs"] == 3.0
    with pytest.raises(ValueError):
        z_summary([])


@pytest.mark.parametrize("argv", [["--geometry", "both", "--series-orders", "4"],
                                  ["--geometry", "device", "--series-orders", "2"]])
def test_the_bench_refuses_bad_series_orders_before_it_starts(capsys, argv):
    from trimeter.cli import main

    assert main(["bench", "tracer-check", "--materials", "1", *argv]) == 2
    out = capsys.readouterr()
    assert "trimeter: error: series orders: 3…16" in out.err and out.out == ""
