"""measurement.json through the typed provenance: a record the service wrote reads back and writes out with
the same keys and values, and a measurement is built from (thickness, map) samples that check themselves."""

import dataclasses
import json

import pytest

from trimeter.domain import Calibration, InstrumentInfo, MapIdentity, Measurement, Provenance, Sample
from trimeter.errors import InputError
from trimeter.results import write_measurement

# measurement.json as `trimeter serve` wrote it (two samples, a device table that did not match)
SERVICE_RECORD = {
    "label": "two", "method": "lut", "maps": ["device-n1.5-l0.4", "device-n1.5-l0.8"],
    "declared_thicknesses_mm": [0.4, 0.8], "map_thicknesses_mm": [0.4, 0.8],
    "map_checksums": ["sha256:aa", "sha256:bb"],
    "timing": {"wall_s": 2.1, "exposure_s": 19.6, "requests": 150, "fit_wall_s": 0.001},
    "device": {"firmware": [1, 4, 0], "regmap_hash": "0x00C0FFEE"},
    "calibration_created_utc": None,   # replaced by the fixture calibration's own below
    "device_map_table": {"slot": "A", "crc32": "0x2144DF1C", "length": 9000, "version": 3,
                         "matches_fit_table": False, "map": "device-n1.5-l0.4"},
    "noise_rel_measured": [0.0021, None], "incomplete": None, "advice": ["31 of 1016 bins are NaN"],
    "link": {"requests": 150, "retries": 0},
}


def _two_samples(measurement, record):
    maps = [MapIdentity(n, t, c) for n, t, c in zip(record["maps"], record["map_thicknesses_mm"],
                                                    record["map_checksums"], strict=True)]
    capture = measurement.captures[0]
    return [dataclasses.replace(capture, sample=Sample(t, m)) for t, m in zip(record["declared_thicknesses_mm"],
                                                                               maps, strict=True)]


def test_a_service_record_reads_back_and_writes_out_with_the_same_keys_values_and_order(measurement):
    record = dict(SERVICE_RECORD, calibration_created_utc=measurement.calibration.created_utc)
    again = Measurement(measurement.calibration, _two_samples(measurement, record), measurement.parameters,
                        provenance=Provenance.from_record(record)).record()
    assert list(again) == list(record)
    assert json.dumps(again) == json.dumps(record)


def test_an_old_record_keeps_keys_this_version_does_not_know_and_tolerates_missing_ones(measurement):
    old = {"method": "paper", "maps": ["m"], "thicknesses_mm": [0.4], "operator": "kim", "device": "garbled"}
    provenance = Provenance.from_record(old)
    assert provenance.method == "paper" and provenance.instrument is None and provenance.advice == []
    assert provenance.extra == {"operator": "kim"}
    assert Measurement(measurement.calibration, measurement.captures, measurement.parameters,
                       provenance=provenance).record()["operator"] == "kim"
    with pytest.raises(InputError, match="object"):
        Provenance.from_record(["not", "a", "record"])


def test_the_written_file_derives_thicknesses_and_maps_from_the_samples(tmp_path, measurement):
    record = dict(SERVICE_RECORD, calibration_created_utc=measurement.calibration.created_utc)
    m = Measurement(measurement.calibration, _two_samples(measurement, record), measurement.parameters,
                    provenance=Provenance.from_record(record))
    meta = json.loads((write_measurement(tmp_path, m, figure=False, medium=False) / "measurement.json").read_text())
    assert meta["thicknesses_mm"] == [0.4, 0.8] and meta["maps"] == record["maps"]
    assert list(meta)[-2:] == ["written_utc", "thicknesses_mm"]


def test_a_sample_refuses_a_bad_thickness_and_a_map_of_another_thickness():
    amap = MapIdentity("device-n1.5-l0.4", 0.4, "sha256:aa")
    for bad in (0, -0.4, float("nan"), float("inf"), "thick"):
        with pytest.raises(InputError, match="not a positive thickness"):
            Sample(bad, amap)
    Sample(0.4, amap).check_map()
    with pytest.raises(InputError, match=r"is for ℓ = 0.4 mm, not the declared 0.8 mm"):
        Sample(0.8, amap).check_map()


def test_the_calibrations_instrument_round_trips_and_an_old_empty_one_reads_as_none(tmp_path, measurement):
    cal = dataclasses.replace(measurement.calibration,
                              device=InstrumentInfo((1, 4, 0), 0xC0FFEE, vendor_id=0x7472, model_id=1))
    cal.save(tmp_path)
    saved = json.loads((tmp_path / "calibration.json").read_text())["device"]
    assert saved == {"vendor_id": 0x7472, "model_id": 1, "firmware": [1, 4, 0], "regmap_hash": "0x00C0FFEE"}
    assert list(saved) == ["vendor_id", "model_id", "firmware", "regmap_hash"]
    assert Calibration.load(tmp_path).device == cal.device
    assert cal.device.to_json(with_model=False) == {"firmware": [1, 4, 0], "regmap_hash": "0x00C0FFEE"}
    dataclasses.replace(cal, device=None).save(tmp_path)
    assert json.loads((tmp_path / "calibration.json").read_text())["device"] == {}
    assert Calibration.load(tmp_path).device is None
    assert not cal.device.same_model(InstrumentInfo((1, 4, 0), 0xC0FFEE, vendor_id=0x7472, model_id=2))
    assert cal.device.same_model(InstrumentInfo((1, 4, 0), 0xC0FFEE))
