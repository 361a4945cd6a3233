# %% [markdown]
# # Tutorial: measure, load, render and mix a material
#
# This notebook drives the whole instrument from Python: it starts the **twin** (the simulated trimeter: the
# real firmware built for this computer, with simulated motors, lamps, optics and spectrometer), calibrates,
# measures two virtual samples, loads a result with `trimeter.load`, plots α, σt and g with their error bars,
# exports the material to Mitsuba 3 and renders a small image of it, and predicts the colour of a 50/50
# mixture.
#
# It needs the repository built (`make demo` does it). On a real instrument only section 1 changes: give the
# serial port and the spectrometer instead of the twin's. Everything here is simulated: the twin's samples
# are rendered by this project's tracer, so the figures below say how the chain behaves, not how a real
# ink measures.
#
# (This notebook is generated from `tools/tutorial.py` by `tools/gen_tutorial.py`; `make test` runs it.)

# %%
import json
import os
import tempfile
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import trimeter

# Everything this notebook writes (calibration, results, exports) goes into a fresh directory: your own
# calibration and results are never touched.
work = Path(tempfile.mkdtemp(prefix="trimeter-tutorial-"))
os.environ["TRIMETER_DATA_DIR"] = str(work / "data")
os.environ["TRIMETER_CONFIG_DIR"] = str(work / "config")
started = time.monotonic()
print("working in", work)

# %% [markdown]
# ## 1. Start the twin
#
# The twin carries the device table of the shipped 0.4 mm map in its active slot, as an instrument carries the
# table flashed into it (`trimeter map flash`). `time_scale=50` runs its clock 50 times faster than real
# time: the lamps' warm-up and the motors take minutes on a real instrument.

# %%
from trimeter.twin import Twin

twin = Twin(thickness_mm=0.4, time_scale=50, state_dir=work / "twin", seed=1, map_table="device-n1.5-l0.4")
twin.start()
print("instrument (Modbus) port:", twin.modbus_port)
print("spectrometer:", twin.spectrometer_url)

# %% [markdown]
# ## 2. Connect and calibrate
#
# A `Service` is what `trimeter calibrate`, `trimeter measure` and the button loop of `trimeter serve` run on:
# it opens the instrument and the spectrometer and runs the sequences. The calibration needs the holder
# empty; it warms the lamps up and measures the references (black and white backgrounds, the collimated
# beam).

# %%
from trimeter.device import Device
from trimeter.sequences.service import Service
from trimeter.sequences.settings import HostSettings
from trimeter.spectrometer import open_spectrometer

settings = HostSettings()
settings.set("port", twin.modbus_port)
settings.set("spectrometer", twin.spectrometer_url)
settings.set("results_dir", str(work / "results"))
service = Service(lambda: Device.open(settings.port), lambda: open_spectrometer(settings.spectrometer), settings,
                  device_clock=twin.sim_time)
service.connect()
calibration = service.calibrate()
usable = calibration.flags == 0
print(f"calibrated: {usable.sum()} of {len(usable)} wavelength bins usable, "
      f"{calibration.wavelengths_nm[0]:.0f}-{calibration.wavelengths_nm[-1]:.0f} nm")

# %% [markdown]
# ## 3. Measure two samples
#
# Insert a virtual sample 0.4 mm thick (the twin's catalogue: `trimeter sim --list-materials`) and measure it;
# then a second one. Without a map named, the fit uses the table the instrument carries. Each measurement
# is a results directory.

# %%
measured, truths = {}, {}
for name in ("cyan-ink", "white-ink"):
    twin.control.insert_sample(name, 0.4)
    samples = service.resolve_samples([(0.4, None)])
    measured[name] = service.measure(samples, label=name)
    truths[name] = twin.control.truth()  # the twin knows what it rendered: the sample's true α, σt, g
    print(name, "→", measured[name])
service.close()
twin.close()

# %% [markdown]
# ## 4. Load a result
#
# `trimeter.load` reads a results directory: α, σt, g and their standard deviations as numpy arrays over
# wavelength, the fit's flags per bin and what to do about them, the provenance, and (on first use) the
# calibration, the reflectances and the raw spectra.

# %%
cyan = trimeter.load(measured["cyan-ink"])
white = trimeter.load(measured["white-ink"])
print(cyan)
i = int(np.argmin(abs(cyan.wavelength_nm - 550)))
print(f"at {cyan.wavelength_nm[i]:.1f} nm: α = {cyan.alpha[i]:.4f} ± {cyan.alpha_std[i]:.4f}, "
      f"σt = {cyan.sigma_t[i]:.3f} ± {cyan.sigma_t_std[i]:.3f} /mm, g = {cyan.g[i]:.3f} ± {cyan.g_std[i]:.3f}")
print(f"{np.count_nonzero(cyan.flags)} of {len(cyan.flags)} bins flagged")
for note in cyan.advice:
    print("advice:", note)

# %% [markdown]
# ## 5. Plot α, σt and g with their error bars
#
# Bins the fit flagged (see `cyan.flag_names` and the advice above) are drawn grey, without error bars. The
# twin knows what it rendered, so its true spectra are drawn beside the measurement.

# %%
truth = truths["cyan-ink"]
assert truth is not None
fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
clean = cyan.flags == 0
for ax, key, title in zip(axes, ("alpha", "sigma_t", "g"), ("albedo α", "extinction σt [1/mm]", "anisotropy g"),
                          strict=True):
    value, std = getattr(cyan, key), getattr(cyan, f"{key}_std")
    ax.errorbar(cyan.wavelength_nm[clean], value[clean], yerr=std[clean], fmt=".", ms=3, elinewidth=0.8,
                label="measured ± 1σ")
    ax.plot(cyan.wavelength_nm[~clean], value[~clean], ".", ms=2, color="0.6", label="flagged bins")
    ax.plot(truth["wavelengths_nm"], truth[key], "-", color="tab:orange", lw=1.2, label="the twin's truth")
    ax.set_xlim(400, 720)
    ax.set_xlabel("wavelength [nm]")
    ax.set_title(f"cyan ink: {title}")
axes[0].legend(fontsize=8)
fig.tight_layout()
plt.show()

# %% [markdown]
# ## 6. Export to Mitsuba 3 and render
#
# `Measurement.export(to="mitsuba")` writes the material as a Mitsuba medium (`medium.xml` for a scene file,
# `medium.json` for `mitsuba.load_dict`) with σt in 1/mm, so the scene's unit is the millimetre. Here a sphere
# 20 mm across of the cyan ink, in a smooth dielectric boundary (n = 1.5), sits on a checker floor under an
# area light. A spectral variant keeps the medium's spectra. The image is kept tiny so this runs in seconds;
# `tools/render_medium.py RESULT_DIR` renders a larger one of the same kind.

# %%
provenance = cyan.export(to="mitsuba", out_dir=work / "mitsuba")
print("written:", ", ".join(provenance["files"]))
medium = json.loads((work / "mitsuba" / "medium.json").read_text())

from trimeter.forward.mitsuba_env import mitsuba

mi = mitsuba("scalar_spectral")
T = mi.ScalarTransform4f
scene = mi.load_dict({
    "type": "scene",
    "integrator": {"type": "volpath", "max_depth": 96, "rr_depth": 24},
    "sensor": {"type": "perspective", "fov": 32,
               "to_world": T().look_at(origin=[0, -62, 30], target=[0, 0, 8], up=[0, 0, 1]),
               "film": {"type": "hdrfilm", "width": 120, "height": 100},
               "sampler": {"type": "independent", "sample_count": 64}},
    "sky": {"type": "constant", "radiance": {"type": "d65", "scale": 0.15}},
    "light": {"type": "rectangle",
              "to_world": T().look_at(origin=[-30, -25, 70], target=[0, 0, 0], up=[0, 0, 1]) @ T().scale(15),
              "emitter": {"type": "area", "radiance": {"type": "d65", "scale": 6.0}}},
    "sphere": {"type": "sphere", "center": [0, 0, 10], "radius": 10,
               "bsdf": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0}, "interior": medium},
    "floor": {"type": "rectangle", "to_world": T().scale(80),
              "bsdf": {"type": "diffuse", "reflectance": {
                  "type": "checkerboard", "color0": {"type": "rgb", "value": 0.15},
                  "color1": {"type": "rgb", "value": 0.7}, "to_uv": mi.ScalarTransform3f().scale([16, 16])}}},
})
t0 = time.monotonic()
image = mi.render(scene)
print(f"rendered in {time.monotonic() - t0:.1f} s ({mi.variant()})")
rgb = mi.Bitmap(image).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=True)
plt.figure(figsize=(4, 3.4))
plt.imshow(np.clip(np.asarray(rgb), 0, 1))
plt.axis("off")
plt.title("the measured cyan ink, 20 mm sphere")
plt.show()

# %% [markdown]
# ## 7. Predict a 50/50 mixture
#
# `trimeter.predict` traces a slab of any thickness, here 5 mm, on black and on white, for a measured material
# or a mixture by volume fractions (paper Sec. 5.2), and gives its reflectance per wavelength and its sRGB
# colour. `paths` is kept low so this runs in seconds; the default is four times more.

# %%
from trimeter.prediction import hex_colour

slabs = {"cyan ink": trimeter.predict(cyan, 5.0, paths=1 << 14),
         "white ink": trimeter.predict(white, 5.0, paths=1 << 14),
         "50/50 mixture": trimeter.predict([cyan, white], 5.0, fractions=[0.5, 0.5], paths=1 << 14)}
fig, (spectra, swatches) = plt.subplots(1, 2, figsize=(12, 3.6), gridspec_kw={"width_ratios": [2, 1]})
for name, p in slabs.items():
    spectra.plot(p.wavelengths_nm, p.on_white, label=f"{name} on white")
    print(f"{name:14s} on white {hex_colour(p.srgb_white)}, on black {hex_colour(p.srgb_black)}")
spectra.set_xlabel("wavelength [nm]")
spectra.set_ylabel("reflectance factor, 5 mm slab")
spectra.legend(fontsize=8)
for k, (name, p) in enumerate(slabs.items()):
    for row, colour in enumerate((p.srgb_white, p.srgb_black)):
        swatches.add_patch(plt.Rectangle((k, 1 - row), 0.9, 0.9, color=hex_colour(colour)))
    swatches.text(k + 0.45, -0.15, name, ha="center", fontsize=8)
swatches.set_xlim(-0.1, 3)
swatches.set_ylim(-0.3, 2)
swatches.axis("off")
swatches.set_title("on white (top), on black (bottom)")
fig.tight_layout()
plt.show()
print(f"the whole tutorial: {time.monotonic() - started:.0f} s")
