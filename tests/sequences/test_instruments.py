"""Several instruments in the host config ([[instruments]] through the settings schema) and what `serve` makes of
them (trimeter.sequences.instruments): each one's settings, calibration and bus; bad entries and an address
collision are one clear error each."""

from __future__ import annotations

import pytest

from fakes import FakeInstrument
from trimeter.cli import main
from trimeter.device.transport import LinkStats
from trimeter.errors import DeviceError, InputError
from trimeter.paths import data_dir
from trimeter.sequences.instruments import Instrument, Lab, instruments_of, settings_for
from trimeter.sequences.settings import HostSettings, checked


@pytest.fixture(autouse=True)
def dirs(tmp_path, monkeypatch):
    monkeypatch.setenv("TRIMETER_CONFIG_DIR", str(tmp_path / "config"))
    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))


THREE = [{"name": "left", "port": "/dev/ttyUSB0", "address": 1, "spectrometer": "sim:/dev/pts/1"},
         {"name": "middle", "port": "/dev/ttyUSB0", "address": 2, "spectrometer": "sim:/dev/pts/2"},
         {"name": "other-port", "port": "/dev/ttyUSB1", "address": 1, "spectrometer": "sim:/dev/pts/3"}]


def test_instruments_in_the_host_config_file_are_read_checked_and_written_back(tmp_path):
    settings = HostSettings()
    settings.set("instruments", THREE)
    settings.set("timeout_s", 0.2)
    path = settings.save()
    text = path.read_text()
    assert text.count("[[instruments]]") == 3 and "timeout_s = 0.2" in text
    loaded = HostSettings.load()
    assert loaded.instruments == THREE and loaded.timeout_s == 0.2
    assert [i.name for i in instruments_of(loaded)] == ["left", "middle", "other-port"]


BAD = [
    ([{**THREE[0]}, {**THREE[1], "address": 1}], r"instruments\[2\]: address collision on the bus /dev/ttyUSB0: "
                                                 r"'middle' and 'left' are both at Modbus address 1"),
    ([THREE[0], {**THREE[1], "name": "left"}], r"instruments\[2\]\.name: 'left' is already instruments\[1\]"),
    ([{**THREE[0], "name": "../etc"}], r"instruments\[1\]\.name: '\.\./etc' is not an instrument name"),
    ([{**THREE[0], "name": ""}], r"instruments\[1\]\.name: '' is not an instrument name"),
    ([{"name": "a", "address": 2}], r"instruments\[1\]\.port: instrument 'a' names no serial port"),
    ([{**THREE[0], "address": 248}], r"instruments\[1\]\.address: 248 is not within \[1, 247\]"),
    ([{**THREE[0], "address": True}], r"instruments\[1\]\.address: True is not a int"),
    ([{**THREE[0], "baud": 9600}], r"instruments\[1\]\.baud: no such instrument setting"),
    (["left"], r"instruments\[1\]: must be a table"),
    ("left", r"instruments: must be a list"),
    ([THREE[0]] * 65, r"instruments: must be a list of at most 64"),
]


@pytest.mark.parametrize("value,message", BAD, ids=[m[:30] for _, m in BAD])
def test_bad_instrument_entries_are_one_clear_error_and_change_nothing(value, message):
    settings = HostSettings()
    settings.set("instruments", THREE)
    with pytest.raises(InputError, match=message):
        settings.set("instruments", value)
    assert settings.instruments == THREE


def test_a_collision_in_the_config_file_is_named_at_load(capsys):
    path = HostSettings.path()
    path.parent.mkdir(parents=True)
    path.write_text('[[instruments]]\nname = "a"\nport = "/dev/ttyUSB0"\naddress = 3\n'
                    '[[instruments]]\nname = "b"\nport = "/dev/ttyUSB0"\naddress = 3\n')
    assert main(["config", "list", "--host"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "address collision on the bus /dev/ttyUSB0: 'b' and 'a'" in err, err


def test_the_instrument_name_is_a_checked_setting_and_keys_its_calibration():
    assert checked("name", "") == "" and checked("name", "lab-2") == "lab-2"
    with pytest.raises(InputError, match="not an instrument name"):
        checked("name", "a/b")
    settings = HostSettings()
    assert settings.calibration_path == data_dir() / "calibration"  # a single instrument keeps its old place
    settings.set("address", 3)
    assert settings.calibration_path == data_dir() / "calibration" / "address-3"
    settings.set("name", "left")
    assert settings.calibration_path == data_dir() / "calibration" / "instruments" / "left"


def test_each_instrument_sees_the_host_settings_with_its_own_port_address_spectrometer_and_name():
    settings = HostSettings()
    settings.update({"instruments": THREE, "frames": 4})
    own = settings_for(settings, instruments_of(settings)[1])
    assert (own.name, own.port, own.address, own.spectrometer, own.frames) == (
        "middle", "/dev/ttyUSB0", 2, "sim:/dev/pts/2", 4)
    assert own.instruments == [] and settings.instruments == THREE  # the host's own settings untouched
    single = HostSettings()
    single.update({"port": "/dev/ttyACM0", "address": 5})
    assert instruments_of(single) == [Instrument("instrument", "/dev/ttyACM0", 5, "")]


class FakeBus:
    opened: list[str] = []

    def __init__(self, port: str) -> None:
        self.port = port
        FakeBus.opened.append(port)
        self.closed = False

    def member(self, address: int):
        fake = FakeInstrument()
        fake.stats = LinkStats()
        return fake

    def close(self) -> None:
        self.closed = True


def test_the_lab_opens_one_bus_per_port_and_checks_every_shared_one(monkeypatch):
    settings = HostSettings()
    settings.set("instruments", THREE)
    FakeBus.opened = []
    lab = Lab(settings, open_bus=FakeBus)
    probed = []

    def probe(bus, address):
        probed.append((bus.port, address))
        if address == 2:
            raise DeviceError(f"address collision on the bus {bus.port}: more than one device answers at Modbus "
                              f"address 2")

    monkeypatch.setattr("trimeter.sequences.instruments.probe_address", probe)
    with pytest.raises(DeviceError, match=r"^instrument 'middle': address collision on the bus /dev/ttyUSB0"):
        lab.check_buses()
    assert probed == [("/dev/ttyUSB0", 1), ("/dev/ttyUSB0", 2)]  # a port with one instrument is not probed
    devices = [lab.open_device(i) for i in lab.instruments]
    assert len(devices) == 3 and FakeBus.opened == ["/dev/ttyUSB0", "/dev/ttyUSB1"]
    with pytest.raises(InputError, match="no instrument named 'nope' \\(left, middle, other-port\\)"):
        lab.by_name("nope")
    polls = [lab.service(i).poll_s for i in lab.instruments]
    assert polls == pytest.approx([0.1, 0.1, 0.05])  # two instruments share /dev/ttyUSB0: each polls half as often
    buses = list(lab.buses.values())
    lab.close()
    assert all(bus.closed for bus in buses)


def test_an_instrument_without_a_port_is_refused_before_anything_opens():
    with pytest.raises(InputError, match="no instrument port given"):
        Lab(HostSettings())
