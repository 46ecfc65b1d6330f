"""Bad values in dataset and particle files: refused naming file and field."""

from __future__ import annotations

import json
import warnings
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from diffaccel.data import (
    FormatError,
    QuadScanDataset,
    read_openpmd_particles,
    read_quad_scan,
    write_openpmd_particles,
    write_quad_scan,
)


def _replace(h5: h5py.File, key: str, data: np.ndarray) -> None:
    attrs = dict(h5[key].attrs)
    del h5[key]
    h5[key] = data
    h5[key].attrs.update(attrs)


def _images(h5: h5py.File, fn: Callable[[np.ndarray], np.ndarray]) -> None:
    _replace(h5, "images", fn(h5["images"][()]))


def _someneg(x: np.ndarray) -> np.ndarray:
    x[1, 0, 0, 0] = -0.5
    return x


def _drift_length(value: float) -> Callable[[h5py.File], None]:
    def apply(h5: h5py.File) -> None:
        h5["settings"].attrs["names"] = '["D1.length"]'
        h5["settings"].attrs["units"] = '["m"]'
        _replace(h5, "settings", np.full((4, 1), value))

    return apply


def _beamline(value: object) -> Callable[[h5py.File], None]:
    def apply(h5: h5py.File) -> None:
        spec = json.loads(h5.attrs["beamline"])
        spec[1]["length"] = value
        h5.attrs["beamline"] = json.dumps(spec)

    return apply


def _cheetah_truth_p0c(value: float) -> Callable[[h5py.File], None]:
    """A ground truth in cheetah coordinates (converted with p0c on reading)."""

    def apply(h5: h5py.File) -> None:
        if "ground_truth" in h5:
            del h5["ground_truth"]
        h5["ground_truth/particles"] = np.zeros((3, 6))
        h5["ground_truth/particles"].attrs["coordinates"] = json.dumps(
            ["x", "px", "y", "py", "tau", "delta"]
        )
        h5.attrs["p0c"] = value

    return apply


def _link(key: str, make: Callable[[], object]) -> Callable[[h5py.File], None]:
    def apply(h5: h5py.File) -> None:
        del h5[key]
        h5[key] = make()

    return apply


def _linear_map(diagonal: float) -> Callable[[h5py.File], None]:
    def apply(h5: h5py.File) -> None:
        spec = json.loads(h5.attrs["beamline"])
        matrix = np.diag([diagonal] * 6).tolist()
        spec[1] = {"type": "LinearMap", "name": "D1", "matrix": matrix}
        h5.attrs["beamline"] = json.dumps(spec)

    return apply


BAD_FILES = {
    "p0c_bool": (
        lambda h: h.attrs.__setitem__("p0c", True),
        r"/\.p0c: expected a number",
    ),
    "p0c_str": (
        lambda h: h.attrs.__setitem__("p0c", "43e6"),
        r"/\.p0c: expected a number",
    ),
    "p0c_tiny": (
        lambda h: h.attrs.__setitem__("p0c", 1e-3),
        r"/\.p0c: expected >= 510\.999 eV for electrons",
    ),
    # the cheetah -> Bmad conversion of the truth ran before p0c was checked
    # ("unexpected ValueError ... this is a bug" at the CLI)
    "p0c_negative_cheetah_truth": (
        _cheetah_truth_p0c(-43.36e6),
        r"/\.p0c: expected a finite value > 0 \[eV\]; found -4\.336e\+07",
    ),
    "p0c_zero_cheetah_truth": (
        _cheetah_truth_p0c(0.0),
        r"/\.p0c: expected a finite value > 0 \[eV\]; found 0",
    ),
    "p0c_huge": (
        lambda h: h.attrs.__setitem__("p0c", 1e300),
        r"/\.p0c: expected <= 1e\+15 eV",
    ),
    # read, then "AttributeError: 'str' object has no attribute 'append'" at
    # the first preprocessing step (subset, pool, normalize, predict)
    "metadata_preprocessing_str": (
        lambda h: h.attrs.__setitem__("metadata", '{"preprocessing": "bg"}'),
        r"/\.metadata\.preprocessing: expected a list of step objects.*str 'bg'",
    ),
    "metadata_preprocessing_strings": (
        lambda h: h.attrs.__setitem__("metadata", '{"preprocessing": ["bg"]}'),
        r"/\.metadata\.preprocessing: expected a list of step objects",
    ),
    # a dangling link escaped as KeyError "Unable to synchronously open object"
    "images_dangling_external_link": (
        _link("images", lambda: h5py.ExternalLink("/nonexistent.h5", "/images")),
        r"/images: cannot be opened \(external link to /nonexistent\.h5:/images\)",
    ),
    "screen_dangling_soft_link": (
        _link("screen", lambda: h5py.SoftLink("/nowhere")),
        r"/screen: cannot be opened \(soft link to /nowhere\)",
    ),
    # accepted, then "least squares: the system holds NaN or infinite values"
    "linear_map_huge": (
        _linear_map(1e300),
        r"\(LinearMap 'D1'\)\.matrix: expected \|value\| <= 1e\+06 .*entry 1e\+300",
    ),
    "pixel_str": (
        lambda h: h["screen"].attrs.__setitem__("pixel_size_x", "1e-3"),
        r"/screen\.pixel_size_x: expected a number",
    ),
    # a denormal pixel passed as > 0, then its image moments underflowed to 0
    # ("scale must be finite and > 0" at reconstruct, no field named)
    "pixel_denormal": (
        lambda h: h["screen"].attrs.__setitem__("pixel_size_x", 1e-300),
        r"screen\.pixel_size: .*at least 1e-09 m.*\(pixel_size_x = 1e-300\)",
    ),
    "version_str": (
        lambda h: h.attrs.__setitem__("format_version", "1"),
        r"/\.format_version: expected an integer",
    ),
    "images_complex": (
        lambda h: _images(h, lambda x: x.astype(np.complex64)),
        r"/images: expected real numbers .* complex64",
    ),
    "images_bool": (
        lambda h: _images(h, lambda x: x > 0),
        r"/images: expected real numbers .* bool",
    ),
    "images_negative": (
        lambda h: _images(h, _someneg),
        r"/images: image of setting 1 \(shot 0\) has a pixel of -0\.5",
    ),
    "length_str": (_beamline("1.0"), r"\(Drift 'D1'\)\.length: expected a real number"),
    "length_null": (_beamline(None), r"\(Drift 'D1'\)\.length: expected a real number"),
    "length_bool": (_beamline(True), r"\(Drift 'D1'\)\.length: expected a real number"),
    "length_list": (
        _beamline([1.0]),
        r"\(Drift 'D1'\)\.length: expected a real number",
    ),
    "negative_length_setting": (
        _drift_length(-1.0),
        r"/settings: 'D1\.length' = -1 at setting 0; expected >= 0 m",
    ),
}


@pytest.fixture
def scan_file(tmp_path: Path, dataset_factory) -> Path:
    """4 settings of one shot of 8 x 8 pixels."""
    return write_quad_scan(dataset_factory(4, 1, 8, 8), tmp_path / "scan.h5")


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_dataset_file_is_refused(scan_file: Path, case: str) -> None:
    change, message = BAD_FILES[case]
    with h5py.File(scan_file, "r+") as h5:
        change(h5)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no ComplexWarning on the way
        with pytest.raises(FormatError, match=message) as info:
            read_quad_scan(scan_file)
    assert str(info.value).startswith(f"{scan_file}: /")


def test_tdc_needs_a_frequency(scan_file: Path) -> None:
    with h5py.File(scan_file, "r+") as h5:
        spec = json.loads(h5.attrs["beamline"])
        tdc = {"type": "TransverseDeflectingCavity", "name": "T", "length": 0.1}
        h5.attrs["beamline"] = json.dumps(
            [spec[0], {**tdc, "frequency": 0.0}, *spec[1:]]
        )
    with pytest.raises(FormatError, match=r"'T'\): frequency must be > 0 Hz"):
        read_quad_scan(scan_file)


def test_small_negative_pixels_are_accepted(scan_file: Path) -> None:
    """Background-subtracted images may dip below zero by their noise."""
    with h5py.File(scan_file, "r+") as h5:
        x = h5["images"][()]
        x[:, :, 0, 0] = -0.1 * x.max()
        _replace(h5, "images", x)
    assert float(read_quad_scan(scan_file).images.min()) < 0


def test_repeated_setting_rows_warn(scan_file: Path) -> None:
    with h5py.File(scan_file, "r+") as h5:
        _replace(h5, "settings", np.array([[-1.0], [0.0], [-1.0], [2.0]]))
    with pytest.warns(UserWarning, match=r"/settings: rows \[\[0, 2\]\] hold the same"):
        read_quad_scan(scan_file)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with h5py.File(scan_file, "r+") as h5:
            _replace(h5, "settings", np.array([[-1.0], [0.0], [1.0], [2.0]]))
        read_quad_scan(scan_file)


def test_container_refuses_tiny_p0c(dataset: QuadScanDataset) -> None:
    ds = dataset
    with pytest.raises(FormatError, match=r"p0c: expected >= 938272 eV for protons"):
        QuadScanDataset(**{**ds.__dict__, "p0c": 43.0, "species": "proton"})


# ------------------------------------------------------------------ particles
P = "data/0/particles/"
RECORDS = [f"position/{c}" for c in "xyz"] + [f"momentum/{c}" for c in "xyz"]
RECORDS += ["time", "weight", "particleStatus"]


def _first(n: int) -> Callable[[h5py.File], None]:
    def apply(h5: h5py.File) -> None:
        for key in RECORDS:
            _replace(h5, P + key, h5[P + key][:n])

    return apply


BAD_PARTICLES = {
    "unitSI_str": (
        lambda h: h[P + "position/x"].attrs.__setitem__("unitSI", "m"),
        r"position/x\.unitSI: expected a number; found 'm'",
    ),
    "record_str": (
        lambda h: _replace(h, P + "position/x", np.array([b"a"] * 300)),
        r"position/x: expected real numbers; found dtype",
    ),
    "far_positions": (
        lambda h: _replace(h, P + "position/z", np.linspace(-1e3, 1e3, 300)),
        r"/position: expected \|x\|, \|y\| <= 1 m",
    ),
    "weight_negative": (
        lambda h: _replace(h, P + "weight", -h[P + "weight"][()]),
        r"/weight: expected macro-particle charges > 0",
    ),
    "weight_zero": (
        lambda h: _replace(h, P + "weight", np.zeros(300)),
        r"/weight: expected macro-particle charges > 0",
    ),
    "unit_dimension": (
        lambda h: h[P + "position/x"].attrs.__setitem__(
            "unitDimension", np.array([0.0, 0, 1, 0, 0, 0, 0])
        ),
        r"position/x\.unitDimension: expected \[1\.0, 0\.0",
    ),
    "one_particle": (_first(1), "expected at least 2 live particles"),
    "p0c_str": (
        lambda h: h[P].attrs.__setitem__("p0c", "43e6"),
        r"particles\.p0c: expected a number",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_PARTICLES))
def test_bad_particle_file_is_refused(tmp_path: Path, case: str) -> None:
    beam = torch.randn(300, 6, generator=torch.Generator().manual_seed(0)) * 1e-3
    path = write_openpmd_particles(tmp_path / "beam.h5", beam.double(), 43e6)
    change, message = BAD_PARTICLES[case]
    with h5py.File(path, "r+") as h5:
        change(h5)
    with pytest.raises(FormatError, match=message) as info:
        read_openpmd_particles(path)
    assert str(info.value).startswith(str(path))


@pytest.mark.parametrize("n", [0, 1])
def test_write_refuses_empty_beam(tmp_path: Path, n: int) -> None:
    with pytest.raises(ValueError, match=r"N >= 2 particles; got \(" + str(n)):
        write_openpmd_particles(tmp_path / "x.h5", torch.zeros(n, 6).double(), 1e6)


def test_a_plausible_linear_map_is_accepted(scan_file: Path) -> None:
    with h5py.File(scan_file, "r+") as h5:
        _linear_map(1.0)(h5)
    read_quad_scan(scan_file)  # does not raise
