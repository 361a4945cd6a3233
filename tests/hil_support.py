"""What the HIL suite shares, in a uniquely named module (`from conftest import` is ambiguous across
test folders): the HIL map and the rigs — the twin, or a real trimeter on which sample changes and
button presses are asked of the operator.

    python tests/hil_support.py      # rebuilds tests/hil/data/hil-ideal-l0.4.tmap (~1 min, iadpython)
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np

from trimeter.formats.appearance import AppearanceMap

HIL_MAP = Path(__file__).resolve().parent / "hil" / "data" / "hil-ideal-l0.4.tmap"
TIME_SCALE = 50.0
THICKNESS_MM = 0.4
SAMPLE = "cyan-ink"


def build_hil_map(path, thickness_mm: float = THICKNESS_MM, n: float = 1.5) -> AppearanceMap:
    """A small exact `ideal` map from adding-doubling (iadpython, test-only) for the host's inversion; the twin
    renders its samples with the tracer (trimeter.twin.observables), so the suite measures the chain and this map's
    error."""
    from trimeter.forward.adding_doubling import ideal_abc

    alpha = 1.0 - (1.0 - np.linspace(0.0, 1.0, 17)) ** 2
    sigma_t = np.geomspace(0.3, 30.0, 17)
    g = np.linspace(0.0, 0.9, 10)
    shape = (len(alpha), len(sigma_t), len(g))
    aa, ss, gg = np.meshgrid(alpha, sigma_t, g, indexing="ij")
    abc = ideal_abc(aa.ravel(), ss.ravel(), gg.ravel(), thickness_mm=thickness_mm, n=n).reshape(*aa.shape, 3)
    A, B, C = abc[..., 0], abc[..., 1], abc[..., 2]
    recipe = {"name": f"hil-ideal-l{thickness_mm:g}", "geometry": "ideal", "n": n, "thickness_mm": thickness_mm}
    AppearanceMap(recipe=recipe, alpha=alpha, sigma_t=sigma_t, g=g, A=A, B=B, C=C, std_b=np.zeros(shape),
                  std_w=np.zeros(shape)).save(path)
    return AppearanceMap.load(path)



def twin_truth(twin, request) -> dict:
    """The twin's truth of its sample, with where it came from recorded on the test (user property
    `twin_physics`, in the JUnit XML). What a round trip against it can show depends on that source
    (trimeter.twin.optics.PHYSICS): "traced" truths come from the tracer the maps are built with, reduced
    to the maps' I(ρ) model — the map's interpolation and Monte Carlo error show, the tracer's and the
    model's do not; a "map" truth is the very map the host inverts — only the chain (protocol,
    calibration, noise) shows. A test must say which it checks: a map truth in a test not marked
    `map_truth` fails (no silent fallback), and so does the marker on a traced truth."""
    import pytest

    truth = twin.control.truth()
    assert truth is not None, "the twin holds no sample"
    request.node.user_properties.append(("twin_physics", truth["physics"]))
    marked = request.node.get_closest_marker("map_truth") is not None
    if truth["physics"] == "map" and not marked:
        pytest.fail(f"the twin's truth is the map the host inverts ({truth.get('physics_source')}): this test cannot "
                    "see the map's error; trace the set-up (tools/make_twin_observables.py) or mark it map_truth")
    if marked and truth["physics"] != "map":
        pytest.fail(f"marked map_truth, but the twin's truth was {truth['physics']} ({truth.get('physics_source')})")
    return truth


@contextlib.contextmanager
def empty_twin(tmp_path, monkeypatch, seed: int):
    """A twin with the HIL map and an empty holder; host config and data kept under tmp_path."""
    from trimeter.twin import Twin

    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("TRIMETER_CONFIG_DIR", str(tmp_path / "config"))
    with Twin(sample=None, thickness_mm=THICKNESS_MM, time_scale=TIME_SCALE, appearance_map=AppearanceMap.load(HIL_MAP),
              state_dir=tmp_path / "twin", seed=seed) as twin:
        yield twin


class TwinRig:
    is_twin = True

    def __init__(self, twin):
        self.twin = twin
        self.port = twin.modbus_port
        self.spectrometer_url = twin.spectrometer_url

    def press_button(self):
        self.twin.control.press_button()

    def insert_sample(self, name=SAMPLE, thickness_mm=THICKNESS_MM):
        self.twin.control.insert_sample(name, thickness_mm)

    def remove_sample(self):
        self.twin.control.remove_sample()

    def device_clock(self):
        return self.twin.sim_time()


class HardwareRig:
    is_twin = False

    def __init__(self, port, spectrometer_url):
        self.port, self.spectrometer_url = port, spectrometer_url

    def press_button(self):
        input("HIL: press the instrument's button, then Enter ")

    def insert_sample(self, name=SAMPLE, thickness_mm=THICKNESS_MM):
        input(f"HIL: insert the {name} sample ({thickness_mm} mm), then Enter ")

    def remove_sample(self):
        input("HIL: empty the sample holder, then Enter ")

    device_clock = None


if __name__ == "__main__":
    print(build_hil_map(HIL_MAP).path)
