"""The shipped firmware fits on the device with the inverse core it shares with the host (the twin: the
firmware sim over its pty, the core in single precision as on the MCU): the l0.4 map's device table
flashed into a slot, its held-out materials fitted on the device and on the host from the same table
(native.TableFitter, double precision, the same float32 inputs), agreeing within the issue's on-device
tolerances; bad bins flagged, a table for another sample or in another format refused."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from trimeter import registers as regs
from trimeter.device.client import Device
from trimeter.errors import DeviceError, InputError
from trimeter.inversion import native
from trimeter.inversion.flags import UNUSABLE, FitFlag

from test_fit_on_device import _start_sim, _stop, _tiny_table

ROOT = Path(__file__).resolve().parents[2]
SIM = ROOT / "firmware" / "build" / "sim" / "trimeter-fw-sim"


@pytest.fixture(scope="module")
def device(tmp_path_factory):
    if not SIM.is_file():
        pytest.skip(f"firmware sim not built ({SIM}): run `make -C firmware sim`")
    tmp = tmp_path_factory.mktemp("shipped")
    proc = _start_sim(SIM, tmp)
    dev = Device.open(str(tmp / "modbus"))
    yield dev
    dev.close()
    _stop(proc)


@pytest.fixture(scope="module")
def heldout():
    """The l0.4 map's v2 table (tools/device_table_study.py build) and its held-out set's intensities."""
    from trimeter.bench.heldout import heldout_collimated, heldout_for, heldout_intensities
    from trimeter.formats.appearance import AppearanceMap, find_map

    if not native.available():
        pytest.skip("the compiled kernel is not built (make native)")
    spec = importlib.util.spec_from_file_location("device_table_tool", ROOT / "tools" / "device_table_study.py")
    tool = importlib.util.module_from_spec(spec)
    sys.modules["device_table_tool"] = tool
    spec.loader.exec_module(tool)
    amap = AppearanceMap.load(find_map("device-n1.5-l0.4"))
    _, _, h = heldout_for(amap)
    rb, rw = amap.reference_rhos
    I_b, I_w = heldout_intensities(h, rb, rw)
    n = len(I_b)
    return tool.build(amap).to_bytes(), (I_b, I_w, heldout_collimated(amap, h), np.full(n, rb), np.full(n, rw))


@pytest.fixture(scope="module")
def flashed(device, heldout):
    """The device with the table flashed into a slot and active (once: a 130 KB write takes seconds)."""
    device.flash_map(heldout[0], version=2)
    return device


def test_the_device_fits_as_the_host_does_with_the_same_table(flashed, heldout):
    table, bins = heldout
    device = flashed
    assert device.read("fit_available") == 1
    got = device.fit(*bins, thickness_mm=0.4, table=table)
    assert len(bins[0]) > device.fit_capacity  # more than one run
    f32 = [np.asarray(b, dtype=np.float32).astype(np.float64) for b in bins]  # what went over the wire
    alpha, sigma_t, g, flags = native.TableFitter(table).fit(*f32)
    np.testing.assert_array_equal(got.flags, flags)
    for name, host in (("alpha", alpha), ("sigma_t", sigma_t), ("g", g)):
        assert np.array_equal(np.isnan(getattr(got, name)), np.isnan(host)), name
    with np.errstate(invalid="ignore"):
        da = np.nanmax(np.abs(got.alpha - alpha))
        ds = np.nanmax(np.abs(got.sigma_t / sigma_t - 1))
        dg = np.nanmax(np.abs(got.g - g))
    assert da <= 1e-3 and ds <= 1e-3 and dg <= 2e-3, (da, ds, dg)
    assert np.isfinite(got.alpha).sum() == len(alpha)  # every held-out material fitted


def test_bad_bins_are_flagged_on_the_device_never_a_fault(flashed):
    device = flashed
    nan, inf = float("nan"), float("inf")
    I_b = np.array([nan, 0.1, -0.5, 0.1, 0.1, 1e30, 0.1, 0.1])
    I_w = np.array([0.5, 0.5, 0.5, 1.5, 0.5, 0.5, 0.05, 0.5])
    I_c = np.array([0.1, 0.1, 0.1, 0.1, inf, 0.1, 0.1, 0.0])
    rho_b = np.array([0.02, 0.5, 0.02, 0.02, 0.02, 0.02, 0.02, 0.02])
    rho_w = np.array([0.95, 0.2, 0.95, 0.95, 0.95, 0.95, 0.95, 0.95])
    got = device.fit(I_b, I_w, I_c, rho_b, rho_w, thickness_mm=0.4)
    unusable = (got.flags & int(UNUSABLE)) != 0
    assert unusable[:6].all() and np.isnan(got.alpha[:6]).all() and np.isnan(got.sigma_t[:6]).all()
    assert got.flags[6] & int(FitFlag.BLACK_NOT_BELOW_WHITE) and np.isfinite(got.alpha[6])
    assert got.flags[7] & int(FitFlag.IC_BELOW_FLOOR) and np.isfinite(got.sigma_t[7])
    assert device.read("fit_status") == regs.FitStatus.DONE


def test_a_table_for_another_sample_or_format_is_refused(flashed, heldout):
    """Last: it leaves a format-1 table active."""
    device, bins = flashed, heldout[1]
    with pytest.raises(InputError, match="not for a 0.8 mm sample"):
        device.fit(*(b[:3] for b in bins), thickness_mm=0.8)
    device.flash_map(_tiny_table(thickness_mm=0.4), version=1)  # a slot may hold format 1; the core fits with 2
    with pytest.raises(DeviceError, match="does not fit with its active map table"):
        device.fit(*(b[:3] for b in bins), thickness_mm=0.4)
    assert device.read("fit_status") == regs.FitStatus.ERROR_TABLE
