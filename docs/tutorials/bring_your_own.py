"""Bring your own camera images and lattice.

A measurement leaves behind camera frames, background frames, a table of which
frame was taken at which knob values, and a lattice file of the beamline. This
tutorial writes such a folder from a known beam, so that every number can be
checked against the truth, describes it in an `experiment.yaml` (its schema:
"Experiment descriptions" in [file formats](../../file_formats.md)), imports it
with `diffaccel data import` and reconstructs the beam. Reading PNG/TIFF and YAML
needs `pip install diffaccel[images]`, reading lattice files
`pip install diffaccel[cheetah]`.

The beamline is an elegant lattice (Bmad and LatticeJSON files work the same,
see [lattice files](../../lattices.md)): a scanned quadrupole `Q1`, a fixed
quadrupole `Q2` and a screen `YAG`, whose point spread is one pixel rms. The
camera is mounted turned by 90 degrees and records 16-bit frames with a
pedestal of 400 counts, 8 counts rms read noise and shot noise: 11 settings of
`Q1.k1`, 3 shots each, 4 background frames. The folder is written three times
with different camera noise and imported four ways: as the default does
(background frames subtracted, pixels left signed), clipped at zero, clipped
and thresholded, and with the camera's rotation left out. The rms beam sizes
of the imported images are compared with those of the known beam; a 4D
reconstruction of the default and of the clipped import is compared with its
emittances.

Reading the output: the default's rms sizes scatter about the truth by the
camera noise (by up to about 2 % here; the noise of the 4 background frames is
common to every image, so one noise draw shifts all settings alike). Clipping
leaves a positive floor under the whole frame that widens every image, by far
more where the beam is small against the frame; the threshold removes the floor
and with it the tails, a few percent too narrow. Leaving out the rotation swaps
x and y. Tell the import the point spread of screen and optics
(`resolution_pixels`): the reconstruction models its images with it.
"""

import matplotlib

matplotlib.use("Agg")

import csv
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import matplotlib.pyplot as plt
import numpy as np
import torch
import yaml

from diffaccel.data import make_synthetic_quad_scan, read_scans
from diffaccel.data.experiment import import_experiment
from diffaccel.data.synthetic import sample_preset_beam
from diffaccel.dynamics import Beamline, emittance
from diffaccel.plotting import plot_image_comparison
from diffaccel.reconstruction import ReconstructionConfig, reconstruct


def diffaccel(*args: str) -> None:
    """Run the command line tool as a shell would; show what it printed."""
    cmd = [sys.executable, "-m", "diffaccel", *args]
    proc = subprocess.run(cmd, check=True, capture_output=True, text=True)
    print(f"$ diffaccel {' '.join(args)}\n{proc.stdout.rstrip()}\n")


# --- the lattice: an elegant file, read through cheetah's converters
LATTICE = """\
Q1: QUAD, L=0.1, K1=0.0
D1: DRIF, L=0.4
Q2: QUAD, L=0.1, K1=-6.0
D2: DRIF, L=1.0
YAG: WATCH, FILENAME="yag.sdds"
SCAN: LINE=(Q1, D1, Q2, D2, YAG)
"""
Path("line.lte").write_text(LATTICE)
diffaccel("lattice", "line.lte")
line = Beamline.from_lattice("line.lte")

# --- the known beam and what the screen shows of it (no camera noise yet)
p0c = 43.36e6  # [eV]
beam = sample_preset_beam("correlated", 20_000, torch.Generator().manual_seed(0))
beam[:, :4] *= 0.5  # x, px, y, py at half the preset's size: 0.75 mm, 0.3 mrad rms
k1 = torch.linspace(-10.0, 14.0, 11, dtype=torch.float64)[:, None]  # [1/m^2]
pixel = 2.0e-4  # [m]
screen = make_synthetic_quad_scan(
    particles=beam,
    beamline_spec=line.to_spec(),
    p0c=p0c,
    settings=k1,
    screen_shape=(96, 96),
    pixel_size=(pixel, pixel),
    image_method="kde",  # the screen's point spread: a Gaussian of one pixel rms
)
images = screen.mean_images().double().numpy()  # (K, H, W): rows y up, columns x


def write_daq(folder: Path, seed: int) -> Path:
    """What the DAQ writes: frames, background frames, a table, the lattice."""
    rng = np.random.default_rng(seed)
    folder.mkdir(exist_ok=True)

    def frame(electrons: np.ndarray) -> np.ndarray:
        counts = 400.0 + rng.poisson(electrons) + rng.normal(0, 8.0, electrons.shape)
        counts = np.clip(np.rint(counts), 0, 65535).astype(np.uint16)
        # camera row 0 is +y; the camera is turned clockwise by 90 degrees
        return np.rot90(counts[::-1, :], k=-1).copy()

    rows = []
    for k, image in enumerate(images):
        for shot in range(3):
            name = f"frame_{k:02d}_{shot}.tif"
            iio.imwrite(folder / name, frame(20_000.0 * image / images.max()))
            rows.append([name, f"{float(k1[k, 0]):g}"])
    for b in range(4):
        iio.imwrite(folder / f"background_{b}.png", frame(np.zeros_like(images[0])))
    with (folder / "frames.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["file", "Q1.k1 [1/m^2]"])
        writer.writerows(rows)
    (folder / "line.lte").write_text(LATTICE)
    experiment = {
        "p0c": p0c,
        "species": "electron",
        "description": "quadrupole scan, camera turned by 90 degrees",
        "scans": {
            "quad_scan": {
                "beamline": {"lattice": "line.lte"},
                "screen": {
                    "pixel_size": pixel,  # [m]
                    "rotate": 90,  # the camera is turned: turn its frames back
                    "row0": "top",
                    "col0": "left",
                    "resolution_pixels": 1.0,  # point-spread rms [pixels]
                },
                "images": "frames.csv",
                "background": "background_*.png",
            }
        },
    }
    path = folder / "experiment.yaml"
    path.write_text(yaml.safe_dump(experiment, sort_keys=False))
    return path


for seed in range(3):
    write_daq(Path(f"daq{seed}"), seed)
print("daq0/experiment.yaml:\n" + Path("daq0/experiment.yaml").read_text())
print("daq0/frames.csv (first rows):")
print("".join(Path("daq0/frames.csv").read_text().splitlines(True)[:4]))

# --- import: frames -> oriented, background-subtracted, normalised images
# (--force: replace the data.h5 of an earlier run; it replaces only diffaccel's files)
diffaccel("data", "import", "daq0/experiment.yaml", "--out", "data.h5", "--force")
scan = read_scans("data.h5")["quad_scan"]

# --- each way of importing against the known beam's rms size on the screen
at_screen = line.track(beam, p0c, settings=k1, names=["Q1.k1"])  # (K, N, 6)
# the beam's rms on the screen, widened by the point spread (one pixel rms)
true_rms = (at_screen[..., [0, 2]].var(dim=-2) + pixel**2).sqrt().numpy()  # (K, 2)


def rms_on_screen(ds) -> np.ndarray:
    """Rms x, y [m] of each setting's shot-averaged image (pixels as weights)."""
    xs, ys = (c.double().numpy() for c in ds.pixel_centers())
    img = ds.mean_images().double().numpy()  # (K, H, W), each summing to 1
    px, py = img.sum(axis=1), img.sum(axis=2)  # profiles along x and y
    mx, my = px @ xs, py @ ys
    return np.stack([np.sqrt(px @ xs**2 - mx**2), np.sqrt(py @ ys**2 - my**2)], axis=-1)


variants = {
    "default (signed)": {},
    "clip: true": {"preprocessing": {"background": {"clip": True}}},
    "clip + triangle threshold": {
        "preprocessing": {
            "background": {"clip": True},
            "threshold": {"method": "triangle"},
        }
    },
    "rotate left out": {"screen": {"rotate": 0}},
}
imported = {}
print("rms size on the screen against the known beam, mean over the 11 settings,")
print("for camera noise seeds 0 / 1 / 2:")
for label, change in variants.items():
    errors = []
    for seed in range(3):
        doc = yaml.safe_load(Path(f"daq{seed}/experiment.yaml").read_text())
        doc.update({k: v for k, v in change.items() if k != "screen"})
        doc["scans"]["quad_scan"]["screen"].update(change.get("screen", {}))
        path = Path(f"daq{seed}/variant.yaml")
        path.write_text(yaml.safe_dump(doc))
        ds = import_experiment(path)["quad_scan"]
        errors.append(100 * (rms_on_screen(ds) / true_rms - 1).mean(axis=0))
        if seed == 0:
            imported[label] = ds
    ex, ey = (" / ".join(f"{e[i]:+5.1f}" for e in errors) for i in (0, 1))
    print(f"  {label:26s} x {ex} %   y {ey} %")

# --- 4D reconstructions (seed 0); the even settings train, the odd are held out
results = {}
for label in ("default (signed)", "clip: true"):
    config = ReconstructionConfig(dims=4, seed=0)
    results[label] = reconstruct(imported[label], config, train_indices="even")
    moments = results[label].moments(n=20_000)
    for plane in ("x", "y"):
        est, truth = moments[f"emit_{plane}"], float(emittance(beam, plane=plane))
        print(
            f"{label:17s} emit_{plane}: {est['mean']:.3e} +- {est['std']:.1e} m rad "
            f"(truth {truth:.3e}, error {100 * (est['mean'] / truth - 1):+.1f} %)"
        )

# --- figures
k = 8
extent = [-48 * pixel * 1e3, 48 * pixel * 1e3] * 2
fig, axes = plt.subplots(1, 3, figsize=(9, 3.2))
axes[0].imshow(iio.imread(f"daq0/frame_{k:02d}_0.tif"))
axes[0].set_title("camera frame as read out", fontsize=9)
axes[0].set_xlabel("column")
axes[0].set_ylabel("row")
for ax, label in zip(axes[1:], ["default (signed)", "rotate left out"], strict=True):
    ax.imshow(imported[label].mean_images()[k], origin="lower", extent=extent)
    ax.set_title(f"imported: {label}", fontsize=9)
    ax.set_xlabel("x [mm]")
axes[1].set_ylabel("y [mm]")
fig.tight_layout()
fig.savefig("orientation.png", dpi=80)

fig, axes = plt.subplots(1, 2, figsize=(9, 3.4), sharey=True)
for i, plane in enumerate("xy"):
    axes[i].plot(k1[:, 0], 1e3 * true_rms[:, i], "k-", lw=3, label="known beam")
    for label, ds in imported.items():
        axes[i].plot(k1[:, 0], 1e3 * rms_on_screen(ds)[:, i], "o--", ms=3, label=label)
    axes[i].set_xlabel("Q1.k1 [1/m^2]")
    axes[i].set_title(f"rms {plane} on the screen (seed 0)", fontsize=9)
axes[0].set_ylabel("[mm]")
axes[1].legend(fontsize=7)
fig.tight_layout()
fig.savefig("rms_sizes.png", dpi=80)

result = results["default (signed)"]
plot_image_comparison(
    scan.mean_images(),
    result.predict_images(scan.settings),
    scan.settings,
    held_out=[i % 2 == 1 for i in range(len(scan.settings))],
    setting_name="Q1.k1",
    max_columns=11,
).savefig("images.png", dpi=80)
