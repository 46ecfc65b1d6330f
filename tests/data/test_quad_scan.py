"""Quad-scan HDF5 reader/writer and the ``QuadScanDataset`` container."""

from __future__ import annotations

import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from diffaccel.data import FormatError, QuadScanDataset, read_quad_scan, write_quad_scan

ELECTRON_MC2 = 0.51099895069e6  # [eV], CODATA 2018


# ------------------------------------------------------------------ shared files
def test_read_gpsr_benchmark(reference_file) -> None:
    ds = read_quad_scan(reference_file("gpsr_4d_synthetic.h5"))
    assert ds.shape == (20, 1, 100, 100)
    assert ds.images.dtype == torch.float32
    assert ds.settings.dtype == torch.float64
    assert ds.setting_names == ["Q1.k1"]
    assert ds.setting_units == ["1/m^2"]
    # scan is k1 = -25 ... 15 in 20 steps (README of the shared data)
    torch.testing.assert_close(
        ds.settings[:, 0],
        torch.linspace(-25, 15, 20, dtype=torch.float64),
        rtol=0,
        atol=4e-6,  # float32-rounded values: 2 ulp of float32 at |k1| in [16, 32)
    )
    assert ds.p0c == pytest.approx(43.36e6, rel=1e-6)
    assert ds.pixel_size == pytest.approx((1e-3, 1e-3), rel=1e-7)
    assert ds.screen_name == "SCREEN"
    assert ds.ground_truth is not None and ds.ground_truth.shape == (10_000, 6)
    assert "GPSR" in ds.metadata["description"]


def test_gpsr_ground_truth_converted_from_cheetah(reference_file) -> None:
    """The file stores cheetah (tau, delta); we must return Bmad (z, pz)."""
    bmadx = pytest.importorskip("cheetah.utils.bmadx")
    path = reference_file("gpsr_4d_synthetic.h5")
    ds = read_quad_scan(path)
    with h5py.File(path, "r") as h5:
        raw = torch.from_numpy(h5["ground_truth/particles"][()])
    mc2 = torch.tensor(ELECTRON_MC2, dtype=torch.float64)
    ref_energy = torch.sqrt(torch.tensor(ds.p0c, dtype=torch.float64) ** 2 + mc2**2)
    expected, _ = bmadx.cheetah_to_bmad_coords(raw, ref_energy, mc2)
    # transverse coordinates are identical in both conventions
    torch.testing.assert_close(ds.ground_truth[:, :4], raw[:, :4], rtol=0, atol=0)
    # float64 round-off of an independent implementation of the same formulas
    torch.testing.assert_close(ds.ground_truth, expected, rtol=1e-10, atol=1e-15)


def test_read_awa_measured(reference_file) -> None:
    ds = read_quad_scan(reference_file("awa_quad_scan_train.h5"))
    assert ds.shape == (11, 3, 84, 84)
    assert ds.ground_truth is None
    assert ds.screen_name == "YAG"
    # the experimenters sum-normalised every shot; float32 sums over 7056 pixels
    torch.testing.assert_close(
        ds.images.sum(dim=(-2, -1)), torch.ones(11, 3), rtol=0, atol=1e-5
    )


@pytest.mark.parametrize(
    "name", ["gpsr_4d_synthetic.h5", "awa_quad_scan_train.h5"], ids=["gpsr", "awa"]
)
def test_reference_file_round_trip(reference_file, tmp_path: Path, name: str) -> None:
    ds = read_quad_scan(reference_file(name))
    out = write_quad_scan(ds, tmp_path / "copy.h5")
    _assert_same(read_quad_scan(out), ds)


# ------------------------------------------------------------------ round trips
def _assert_same(a: QuadScanDataset, b: QuadScanDataset) -> None:
    assert torch.equal(a.images, b.images)
    assert torch.equal(a.settings, b.settings)
    assert a.setting_names == b.setting_names
    assert a.setting_units == b.setting_units
    assert a.p0c == b.p0c
    assert a.species == b.species
    assert a.beamline_spec == b.beamline_spec
    assert a.pixel_size == b.pixel_size
    assert a.center == b.center
    assert a.metadata == b.metadata
    if b.ground_truth is None:
        assert a.ground_truth is None
    else:
        assert torch.equal(a.ground_truth, b.ground_truth)


@pytest.mark.parametrize("ground_truth", [True, False], ids=["with_gt", "no_gt"])
def test_round_trip(dataset_factory, tmp_path: Path, ground_truth: bool) -> None:
    ds = dataset_factory(ground_truth=ground_truth)
    path = write_quad_scan(ds, tmp_path / "scan.h5")
    back = read_quad_scan(path)
    _assert_same(back, ds)
    with h5py.File(path, "r") as h5:
        assert h5.attrs["format"] == "quad-scan"
        assert int(h5.attrs["format_version"]) == 1
        if ground_truth:
            coords = json.loads(h5["ground_truth/particles"].attrs["coordinates"])
            assert coords == ["x", "px", "y", "py", "z", "pz"]


def test_writer_refuses_to_overwrite(dataset, tmp_path: Path) -> None:
    path = tmp_path / "scan.h5"
    path.write_bytes(b"user data")
    with pytest.raises(FileExistsError, match="overwrite=True"):
        write_quad_scan(dataset, path)
    assert path.read_bytes() == b"user data"
    write_quad_scan(dataset, path, overwrite=True)
    _assert_same(read_quad_scan(path), dataset)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scan.h5"]  # no temp left


def test_writer_leaves_no_partial_file(dataset, tmp_path: Path) -> None:
    bad = QuadScanDataset(**{**_fields(dataset), "metadata": {"x": object()}})
    with pytest.raises(FormatError, match="metadata: not JSON"):
        write_quad_scan(bad, tmp_path / "scan.h5")
    assert list(tmp_path.iterdir()) == []


def _fields(ds: QuadScanDataset) -> dict:
    return {
        k: getattr(ds, k)
        for k in (
            "images settings setting_names setting_units p0c species beamline_spec "
            "pixel_size center ground_truth metadata"
        ).split()
    }


# ------------------------------------------------------------------ file errors
def _corrupt(path: Path, action: str) -> None:
    with h5py.File(path, "r+") as h5:
        if action == "no_format":
            del h5.attrs["format"]
        elif action == "wrong_format":
            h5.attrs["format"] = "image-stack"
        elif action == "version_3":
            h5.attrs["format_version"] = 3
        elif action == "version_1_7":
            h5.attrs["format_version"] = 1.7
        elif action == "species_not_utf8":
            h5.attrs["species"] = np.bytes_(b"electr\xffon")
        elif action == "species_number":
            h5.attrs["species"] = 3
        elif action == "screen_not_last":
            spec = json.loads(h5.attrs["beamline"])
            h5.attrs["beamline"] = json.dumps([spec[0], spec[2], spec[1]])
        elif action == "huge_drift":
            spec = json.loads(h5.attrs["beamline"])
            spec[1]["length"] = 1e30
            h5.attrs["beamline"] = json.dumps(spec)
        elif action == "huge_setting":
            h5["settings"][1, 0] = 1e12
        elif action == "one_pixel":
            attrs = dict(h5["images"].attrs)
            del h5["images"]
            h5["images"] = np.ones((5, 2, 1, 1), dtype=np.float32)
        elif action == "no_p0c":
            del h5.attrs["p0c"]
        elif action == "bad_json":
            h5.attrs["beamline"] = '[{"type": "Drift", "name": "D1"'
        elif action == "no_images":
            del h5["images"]
        elif action == "no_screen":
            del h5["screen"]
        elif action == "settings_rows":
            data = h5["settings"][()]
            attrs = dict(h5["settings"].attrs)
            del h5["settings"]
            h5["settings"] = data[:-1]
            h5["settings"].attrs.update(attrs)
        elif action == "nan_image":
            h5["images"][2, 1, 3, 3] = np.nan
        elif action == "inf_setting":
            h5["settings"][1, 0] = np.inf
        elif action == "zero_image":
            h5["images"][3, 0] = 0.0
        elif action == "negative_pixel":
            h5["screen"].attrs["pixel_size_y"] = -1e-3
        elif action == "unknown_element":
            h5["settings"].attrs["names"] = json.dumps(["Q9.k1"])
        elif action == "unknown_parameter":
            h5["settings"].attrs["names"] = json.dumps(["Q1.k2"])
        elif action == "wrong_unit":
            h5["settings"].attrs["units"] = json.dumps(["T"])
        elif action == "no_names":
            del h5["settings"].attrs["names"]
        elif action == "gt_coordinates":
            h5["ground_truth/particles"].attrs["coordinates"] = json.dumps(
                list("abcdef")
            )
        elif action == "no_screen_element":
            spec = json.loads(h5.attrs["beamline"])[:-1]
            h5.attrs["beamline"] = json.dumps(spec)
        else:  # pragma: no cover
            raise AssertionError(action)


CORRUPTIONS = [
    ("no_format", r"/: missing attribute 'format'"),
    ("wrong_format", r"format: expected 'quad-scan'; found 'image-stack'"),
    ("version_3", r"/.format_version: this reader reads versions 1, 2; found 3"),
    ("version_1_7", r"/.format_version: expected an integer \(1 or 2\); found 1.7"),
    ("species_not_utf8", r"/.species: expected UTF-8 text; found bytes"),
    ("species_number", r"/.species: expected a text attribute; found int"),
    ("screen_not_last", r"/beamline: the Screen 'SCREEN' must be the last element"),
    ("huge_drift", r"beamline\[1\] \(Drift 'D1'\).length: expected \|value\| <= 1000"),
    ("huge_setting", r"'Q1.k1' = 1e\+12 at setting 1; expected \|value\| <= 10000"),
    ("one_pixel", r"/images: expected a screen of at least 2 x 2 pixels"),
    ("no_p0c", r"missing attribute 'p0c'"),
    ("bad_json", r"/.beamline: invalid JSON"),
    ("no_images", r"/images: missing dataset"),
    ("no_screen", r"/screen: missing group"),
    ("settings_rows", r"settings: expected 5 rows .* found shape \(4, 1\)"),
    ("nan_image", r"images: expected finite values.*setting 2, shot 1"),
    ("inf_setting", r"settings: expected finite values; found NaN/inf at setting 1"),
    ("zero_image", r"image of setting 3 \(shot 0\) is all zero"),
    ("negative_pixel", r"pixel_size.*> 0"),
    ("unknown_element", r"'Q9.k1' names element 'Q9', which is not in the beamline"),
    ("unknown_parameter", r"'Q1.k2' names parameter 'k2'"),
    ("wrong_unit", r"'Q1.k1' must be in '1/m\^2'; found 'T'"),
    ("no_names", r"/settings: missing attribute 'names'"),
    ("gt_coordinates", r"ground_truth/particles.coordinates: expected"),
    ("no_screen_element", r"exactly one element of type 'Screen'"),
]


@pytest.mark.parametrize(
    ("action", "message"), CORRUPTIONS, ids=[c[0] for c in CORRUPTIONS]
)
def test_reader_names_the_problem(
    dataset, tmp_path: Path, action: str, message: str
) -> None:
    path = write_quad_scan(dataset, tmp_path / "scan.h5")
    _corrupt(path, action)
    with pytest.raises(FormatError, match=message) as info:
        read_quad_scan(path)
    # one line that names the file
    assert str(info.value).startswith(f"{path}: ")
    assert "\n" not in str(info.value)


def test_reader_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="not found"):
        read_quad_scan(tmp_path / "nope.h5")


def test_reader_not_hdf5(tmp_path: Path) -> None:
    path = tmp_path / "scan.h5"
    path.write_text("not hdf5")
    with pytest.raises(FormatError, match="not a readable HDF5 file"):
        read_quad_scan(path)


# ------------------------------------------------------------------ constructor errors
BAD_FIELDS = [
    ("images_3d", {"images": torch.ones(5, 16, 20)}, r"expected 4 dimensions"),
    ("settings_1d", {"settings": torch.zeros(5)}, r"settings: expected 2 dimensions"),
    ("names_count", {"setting_names": ["Q1.k1", "Q1.length"]}, r"expected 1 names"),
    ("name_syntax", {"setting_names": ["k1"]}, r"expected 'ELEMENT.parameter'"),
    ("p0c_negative", {"p0c": -1.0}, r"p0c: expected a finite value > 0 \[eV\]"),
    (
        "pixel_zero",
        {"pixel_size": (0.0, 1e-3)},
        r"pixel_size: expected \(x, y\) > 0 and <= 10 m",
    ),
    ("center_nan", {"center": (math.nan, 0.0)}, r"center: expected finite"),
    (
        "preprocessing_str",
        {"metadata": {"preprocessing": "bg"}},
        r"metadata\.preprocessing: expected a list of step objects",
    ),
    ("species", {"species": "muon"}, r"species: expected one of"),
    ("gt_shape", {"ground_truth": torch.zeros(10, 4)}, r"ground_truth: expected shape"),
    ("gt_nan", {"ground_truth": torch.full((3, 6), math.nan)}, r"ground_truth: .*NaN"),
    ("spec_empty", {"beamline_spec": []}, r"beamline: expected a non-empty list"),
]


@pytest.mark.parametrize(
    ("changes", "message"),
    [b[1:] for b in BAD_FIELDS],
    ids=[b[0] for b in BAD_FIELDS],
)
def test_constructor_names_the_field(dataset, changes: dict, message: str) -> None:
    with pytest.raises(FormatError, match=message):
        QuadScanDataset(**{**_fields(dataset), **changes})


def test_format_error_is_value_error() -> None:
    assert issubclass(FormatError, ValueError)


# ------------------------------------------------------------------ container
def test_dataset_is_frozen_and_copies_inputs(dataset) -> None:
    with pytest.raises(AttributeError):
        dataset.p0c = 1.0  # type: ignore[misc]
    spec = [dict(e) for e in dataset.beamline_spec]
    ds = QuadScanDataset(**{**_fields(dataset), "beamline_spec": spec})
    spec[0]["length"] = 99.0
    assert ds.beamline_spec[0]["length"] == 0.1


def test_mean_images_sum_normalised(dataset) -> None:
    mean = dataset.mean_images()
    assert mean.shape == (5, 16, 20)
    # float32 sums over 320 pixels
    torch.testing.assert_close(mean.sum(dim=(-2, -1)), torch.ones(5), rtol=0, atol=1e-6)
    raw = dataset.images.mean(1)
    torch.testing.assert_close(
        mean, raw / raw.sum(dim=(-2, -1), keepdim=True), rtol=1e-6, atol=0
    )


def test_pixel_centers_follow_format_convention(dataset) -> None:
    xs, ys = dataset.pixel_centers()
    assert ys.shape == (16,) and xs.shape == (20,)
    # y_i = cy + (i - (H-1)/2) * py ; x_j = cx + (j - (W-1)/2) * px
    assert ys[0].item() == pytest.approx(-2e-4 - 7.5 * 2e-3, rel=1e-12)
    assert xs[-1].item() == pytest.approx(1e-4 + 9.5 * 1e-3, rel=1e-12)
    assert ((ys[0] + ys[-1]) / 2).item() == pytest.approx(-2e-4, rel=1e-12)
    torch.testing.assert_close(
        torch.diff(xs), torch.full((19,), 1e-3, dtype=torch.float64)
    )


@pytest.mark.parametrize(
    ("indices", "expected"),
    [([0, 2, 4], [0, 2, 4]), (slice(1, None, 2), [1, 3]), ([-1], [4])],
    ids=["list", "slice", "negative"],
)
def test_subset(dataset, indices, expected: list[int]) -> None:
    sub = dataset.subset(indices)
    assert torch.equal(sub.images, dataset.images[expected])
    assert torch.equal(sub.settings, dataset.settings[expected])
    assert sub.metadata["preprocessing"][-1] == {"step": "subset", "indices": expected}
    assert dataset.metadata["preprocessing"] == []  # original untouched
    assert sub.ground_truth is dataset.ground_truth or torch.equal(
        sub.ground_truth, dataset.ground_truth
    )


def test_subset_bool_mask(dataset) -> None:
    mask = torch.tensor([True, False, True, False, False])
    assert dataset.subset(mask).settings[:, 0].tolist() == [-10.0, 0.0]


@pytest.mark.parametrize(
    ("indices", "error"), [([5], IndexError), ([], ValueError)], ids=["range", "empty"]
)
def test_subset_errors(dataset, indices, error) -> None:
    with pytest.raises(error):
        dataset.subset(indices)


def test_beamline_has_screen_geometry(dataset) -> None:
    bl = dataset.beamline()
    assert bl.element_names == ["Q1", "D1", "SCREEN"]
    screen = bl["SCREEN"]
    assert screen.shape == (16, 20)
    assert screen.pixel_size == pytest.approx((1e-3, 2e-3))
    assert screen.center == pytest.approx((1e-4, -2e-4))
    assert "shape" not in dataset.beamline_spec[-1]  # dataset unchanged


def test_beamline_pixel_convention_matches_screen(dataset) -> None:
    """A particle at a pixel centre lights that pixel in the dynamics screen."""
    xs, ys = dataset.pixel_centers()
    particle = torch.zeros(1, 6, dtype=torch.float64)
    particle[0, 0], particle[0, 2] = xs[7], ys[3]
    img = dataset.beamline()["SCREEN"].image(particle, method="cic")
    assert img.shape == (16, 20)
    assert torch.nonzero(img > 0.5).tolist() == [[3, 7]]


def test_setting_may_name_parameter_absent_from_spec(dataset) -> None:
    ds = QuadScanDataset(
        **{
            **_fields(dataset),
            "settings": torch.zeros(5, 2, dtype=torch.float64),
            "setting_names": ["Q1.k1", "Q1.tilt"],
            "setting_units": ["1/m^2", "rad"],
        }
    )
    assert ds.setting_names == ["Q1.k1", "Q1.tilt"]


def test_unknown_element_type(dataset) -> None:
    spec = [{"type": "Wiggler", "name": "W1"}, *dataset.beamline_spec]
    with pytest.raises(FormatError, match=r"beamline: .*unknown element type"):
        QuadScanDataset(**{**_fields(dataset), "beamline_spec": spec})


def test_pixel_centers_are_the_screens(dataset) -> None:
    # one helper, one (x, y) order: the dataset's centres are its screen's
    xs, ys = dataset.pixel_centers()
    sx, sy = dataset.beamline().elements[-1].pixel_centers(dtype=torch.float64)
    assert torch.equal(xs, sx) and torch.equal(ys, sy)
    assert xs.shape == (dataset.screen_shape[1],)
    assert ys.shape == (dataset.screen_shape[0],)
