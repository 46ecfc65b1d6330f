"""Several scans of one beam: ``MultiScanDataset``, format version 2, selections."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from diffaccel.data import (
    SINGLE_SCAN_NAME,
    FormatError,
    MultiScanDataset,
    parse_selection,
    read_quad_scan,
    read_scans,
    write_quad_scan,
    write_scans,
)


def _two_scans(dataset_factory) -> MultiScanDataset:
    a = dataset_factory(k=5, s=2, h=16, w=20)
    b = dataset_factory(k=3, s=1, h=12, w=10)
    return MultiScanDataset({"straight": a, "bent": b})


def _assert_same_scans(got: MultiScanDataset, want: MultiScanDataset) -> None:
    assert got.names == want.names
    for name, scan in want:
        other = got[name]
        assert torch.equal(other.images, scan.images)
        assert torch.equal(other.settings, scan.settings)
        assert other.beamline_spec == scan.beamline_spec
        assert other.pixel_size == scan.pixel_size and other.center == scan.center
        assert other.setting_names == scan.setting_names
    assert torch.equal(got.ground_truth, want.ground_truth)
    assert got.p0c == want.p0c and got.species == want.species


def test_round_trip_v2(dataset_factory, tmp_path: Path) -> None:
    ms = _two_scans(dataset_factory)
    path = write_scans(ms, tmp_path / "scans.h5")
    with h5py.File(path, "r") as h5:
        assert int(h5.attrs["format_version"]) == 2
        assert list(h5["scans"]) == ["straight", "bent"]  # order kept
        assert h5["scans/bent/images"].shape == (3, 1, 12, 10)
        assert "beamline" in h5["scans/bent"].attrs
    back = read_scans(path)
    assert back.format_version == 2
    _assert_same_scans(back, ms)


def test_v1_reader_refuses_a_scans_group(dataset, tmp_path: Path) -> None:
    path = write_quad_scan(dataset, tmp_path / "v1.h5")
    with h5py.File(path, "r+") as h5:
        h5.create_group("scans")
    with pytest.raises(FormatError, match=r": /scans: a format_version 1 file"):
        read_scans(path)


def test_v1_file_reads_as_one_scan_and_writes_back_as_v1(
    dataset, tmp_path: Path
) -> None:
    path = write_quad_scan(dataset, tmp_path / "v1.h5")
    ms = read_scans(path)
    assert ms.names == [SINGLE_SCAN_NAME] and ms.format_version == 1
    out = write_scans(ms, tmp_path / "again.h5")
    with h5py.File(out, "r") as h5:
        assert int(h5.attrs["format_version"]) == 1 and "scans" not in h5
    again = read_quad_scan(out)
    assert torch.equal(again.images, dataset.images)


def test_read_quad_scan_reads_a_v2_file_with_one_scan(dataset, tmp_path) -> None:
    ms = MultiScanDataset({"only": dataset})
    path = write_scans(ms, tmp_path / "one.h5")
    assert torch.equal(read_quad_scan(path).images, dataset.images)


def test_read_quad_scan_refuses_several_scans(dataset_factory, tmp_path) -> None:
    path = write_scans(_two_scans(dataset_factory), tmp_path / "two.h5")
    with pytest.raises(FormatError, match=r"holds 2 scans .*read_scans"):
        read_quad_scan(path)


def test_write_v1_refuses_several_scans(dataset_factory, tmp_path) -> None:
    with pytest.raises(FormatError, match="format_version 1 holds one scan"):
        write_scans(_two_scans(dataset_factory), tmp_path / "x.h5", format_version=1)


def test_read_shared_6d_benchmark(reference_file) -> None:
    ms = read_scans(reference_file("sixd_synthetic_train.h5"))
    assert ms.names == ["dipole_off", "dipole_on"]
    for _, scan in ms:
        assert scan.shape == (10, 1, 96, 96)
        assert scan.setting_names == ["SCAN_QUAD.k1", "SCAN_TDC.voltage"]
    assert ms["dipole_on"].screen_name == "DYG2"
    assert ms.ground_truth is not None and ms.ground_truth.shape == (50_000, 6)
    assert ms.n_images == 20


def test_screen_resolution_round_trips_per_scan(dataset_factory, tmp_path) -> None:
    a = replace(dataset_factory(k=5, s=2, h=16, w=20), resolution_pixels=0.5)
    b = dataset_factory(k=3, s=1, h=12, w=10)  # unknown: no attribute written
    path = write_scans(MultiScanDataset({"straight": a, "bent": b}), tmp_path / "s.h5")
    with h5py.File(path, "r") as h5:
        assert float(h5["scans/straight/screen"].attrs["resolution_pixels"]) == 0.5
        assert "resolution_pixels" not in h5["scans/bent/screen"].attrs
    back = read_scans(path)
    assert back["straight"].resolution_pixels == 0.5
    assert back["bent"].resolution_pixels is None
    one = write_quad_scan(a, tmp_path / "one.h5")  # version 1: /screen
    assert read_quad_scan(one).resolution_pixels == 0.5


def _corrupt(path: Path, action: str) -> None:
    with h5py.File(path, "r+") as h5:
        if action == "no_scans":
            del h5["scans"]
        elif action == "empty_scans":
            for name in list(h5["scans"]):
                del h5["scans"][name]
        elif action == "scan_bad_name":
            h5["scans/bent/settings"].attrs["names"] = json.dumps(["Q9.k1"])
        elif action == "scan_no_images":
            del h5["scans/bent/images"]
        elif action == "scan_no_beamline":
            del h5["scans/bent"].attrs["beamline"]
        elif action == "scan_screen_pixel":
            h5["scans/straight/screen"].attrs["pixel_size_x"] = np.nan
        elif action == "scan_resolution_nan":
            h5["scans/straight/screen"].attrs["resolution_pixels"] = np.nan
        elif action == "scan_resolution_negative":
            h5["scans/bent/screen"].attrs["resolution_pixels"] = -1.0
        elif action == "scan_images_not_numbers":
            del h5["scans/bent/images"]
            h5["scans/bent/images"] = np.array([b"a", b"b"])
        elif action == "root_images":  # v1-looking data beside /scans
            h5["images"] = h5["scans/straight/images"][...]
        elif action == "root_beamline":
            h5.attrs["beamline"] = h5["scans/straight"].attrs["beamline"]
        else:  # pragma: no cover
            raise AssertionError(action)


CORRUPTIONS = [
    ("root_images", r"/images: a format_version 2 file keeps images under /scans"),
    ("root_beamline", r"/.beamline: a format_version 2 file keeps the beamline"),
    ("no_scans", r"/scans: missing group"),
    ("empty_scans", r"/scans: expected at least one scan group"),
    ("scan_bad_name", r"/scans/bent/settings.names: 'Q9.k1' names element 'Q9'"),
    ("scan_no_images", r"/scans/bent/images: missing dataset"),
    ("scan_no_beamline", r"/scans/bent: missing attribute 'beamline'"),
    ("scan_screen_pixel", r"/scans/straight/screen.pixel_size_x: expected a finite"),
    ("scan_images_not_numbers", r"/scans/bent/images: expected real numbers"),
    (
        "scan_resolution_nan",
        r"/scans/straight/screen.resolution_pixels: expected a finite",
    ),
    (
        "scan_resolution_negative",
        r"/scans/bent/screen.resolution_pixels: expected a number in \[0, 100\]",
    ),
]


@pytest.mark.parametrize(
    ("action", "message"), CORRUPTIONS, ids=[c[0] for c in CORRUPTIONS]
)
def test_v2_reader_names_file_scan_and_field(
    dataset_factory, tmp_path: Path, action: str, message: str
) -> None:
    path = write_scans(_two_scans(dataset_factory), tmp_path / "scans.h5")
    _corrupt(path, action)
    with pytest.raises(FormatError, match=message) as info:
        read_scans(path)
    assert str(info.value).startswith(f"{path}: ")
    assert "\n" not in str(info.value)


def test_container_refuses_scans_of_different_beams(dataset_factory) -> None:
    a = dataset_factory()
    b = dataset_factory(ground_truth=False)
    with pytest.raises(FormatError, match="scan 'b': ground_truth differs"):
        MultiScanDataset({"a": a, "b": b})


def test_container_refuses_bad_scan_name(dataset) -> None:
    with pytest.raises(FormatError, match="scan name 'a/b'"):
        MultiScanDataset({"a/b": dataset})


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("all", {"straight": [0, 1, 2, 3, 4], "bent": [0, 1, 2]}),
        ("even", {"straight": [0, 2, 4], "bent": [0, 2]}),
        ("odd", {"straight": [1, 3], "bent": [1]}),
        ("0,2", {"straight": [0, 2], "bent": [0, 2]}),
        ("straight:1,3;bent:even", {"straight": [1, 3], "bent": [0, 2]}),
        ("bent:all", {"straight": [], "bent": [0, 1, 2]}),
    ],
    ids=["all", "even", "odd", "list", "per_scan", "one_scan"],
)
def test_parse_selection(dataset_factory, text: str, expected: dict) -> None:
    assert parse_selection(text, _two_scans(dataset_factory)) == expected


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("4", r"scan 'bent': indices must be distinct and in \[0, 3\)"),
        ("nope:1", r"'nope:1' must be SCAN:RULE with SCAN one of"),
        ("straight:x", r"scan 'straight': expected all, even, odd, none"),
        ("straight:none;bent:none", r"select no setting"),
        ("", r"expected a rule"),
        # was exit 0 with the last rule silently winning
        ("straight:all;straight:0", r"scan 'straight' is named twice"),
    ],
    ids=["out_of_range", "unknown_scan", "bad_rule", "nothing", "empty", "twice"],
)
def test_parse_selection_errors(dataset_factory, text: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_selection(text, _two_scans(dataset_factory))


def test_subset_drops_unselected_scans(dataset_factory) -> None:
    ms = _two_scans(dataset_factory)
    sub = ms.subset({"straight": [], "bent": [2, 0]})
    assert sub.names == ["bent"]
    assert sub["bent"].settings[:, 0].tolist() == [
        ms["bent"].settings[2, 0].item(),
        ms["bent"].settings[0, 0].item(),
    ]
