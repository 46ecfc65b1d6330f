"""Predicted screen images for new settings, with their warnings."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from diffaccel.data import read_scans, write_quad_scan
from diffaccel.reconstruction import (
    ReconstructionConfig,
    as_scans,
    predict_dataset,
    reconstruct,
)
from diffaccel.reconstruction.prediction import (
    check_prediction_files,
    parse_settings,
    predict_files,
    predict_scans,
    predict_settings,
)


@pytest.fixture(scope="module")
def result(small_scan):
    config = ReconstructionConfig(n_particles=256, steps=4, snapshots=2)
    return reconstruct(small_scan, config, uncertainty=False)


def test_predict_scans_equals_predict_dataset(result, small_scan) -> None:
    scans = as_scans(small_scan)
    pred = predict_scans(result, scans, n_particles=300, seed=3)
    images, on_screen = predict_dataset(
        result, scans, n_particles=300, seed=3, return_on_screen=True
    )
    assert list(pred.images) == list(images) == scans.names
    for name in scans.names:
        torch.testing.assert_close(pred.images[name], images[name])
        torch.testing.assert_close(pred.on_screen[name], on_screen[name])
        assert pred.images[name].sum(dim=(-2, -1)) == pytest.approx(1.0, rel=1e-5)
    assert pred.spread is None and pred.warnings == []
    spread = predict_scans(result, scans, n_particles=300, return_std=True).spread
    assert spread is not None
    assert spread[scans.names[0]].shape == pred.images[scans.names[0]].shape


def test_predict_settings_images_the_first_training_beamline(result) -> None:
    settings = torch.tensor([[-5.0], [0.0], [5.0]], dtype=torch.float64)
    pred = predict_settings(result, settings, n_particles=300, return_std=True)
    (name,) = pred.images
    assert name == result.scan_names[0]
    assert pred.images[name].shape == (3, 32, 32)
    assert pred.spread is not None and pred.spread[name].shape == (3, 32, 32)
    assert pred.on_screen[name].shape == (3,)
    assert bool((pred.on_screen[name] > 0.5).all()) and pred.warnings == []


def test_predict_settings_warns_where_the_beam_leaves_the_screen(result) -> None:
    # a strong quadrupole spreads the beam far beyond the 32 mm screen
    settings = torch.tensor([[0.0], [300.0]], dtype=torch.float64)
    pred = predict_settings(result, settings, n_particles=300)
    name = result.scan_names[0]
    assert float(pred.on_screen[name][1]) < 0.5
    assert len(pred.warnings) == 1 and "screen" in pred.warnings[0]


def test_parse_settings_reads_values_and_rows() -> None:
    assert parse_settings("-3, 0,2.5", ["k1"]).tolist() == [[-3.0], [0.0], [2.5]]
    assert parse_settings("1;2", ["k1"]).tolist() == [[1.0], [2.0]]
    two = parse_settings("1:2;3:4", ["k1", "angle"])
    assert two.dtype == torch.float64 and two.tolist() == [[1.0, 2.0], [3.0, 4.0]]
    with pytest.raises(ValueError, match="holds no value"):
        parse_settings(" ;, ", ["k1"])
    with pytest.raises(ValueError, match=r"value 2 is empty \(a stray ','\?\)"):
        parse_settings("1,,2", ["k1"])
    with pytest.raises(ValueError, match=r"row 2 '3' has 1 value\(s\); expected 2"):
        parse_settings("1:2;3", ["k1", "angle"])
    with pytest.raises(ValueError, match="row 1 'x': not a number"):
        parse_settings("x", ["k1"])


def test_check_prediction_files_refuses_before_any_work(tmp_path: Path) -> None:
    data = tmp_path / "scan.h5"
    data.write_bytes(b"")
    out = tmp_path / "pred.h5"
    check_prediction_files(out, tmp_path / "s.npz", data, False, force=False)
    check_prediction_files(tmp_path / "p.npy", None, None, True, force=False)
    with pytest.raises(ValueError, match="is the --dataset file"):
        check_prediction_files(data, None, data, False, force=True)
    with pytest.raises(ValueError, match=r"--std-out .*s.txt: expected a .npy"):
        check_prediction_files(out, tmp_path / "s.txt", data, False, force=False)
    with pytest.raises(ValueError, match="exactly one of --dataset or --settings"):
        check_prediction_files(out, None, data, True, force=False)
    with pytest.raises(ValueError, match=r"expected a .h5 \(quad-scan file\)"):
        check_prediction_files(tmp_path / "p.png", None, data, False, force=False)
    with pytest.raises(ValueError, match=r"--out \.h5 needs --dataset"):
        check_prediction_files(out, None, None, True, force=False)


def test_predict_files_writes_images_and_spread(
    result, small_scan, tmp_path: Path
) -> None:
    folder = result.save(tmp_path / "rec")
    data = tmp_path / "scan.h5"
    write_quad_scan(small_scan, data)
    lines: list[str] = []
    out, std = tmp_path / "pred.h5", tmp_path / "spread.npz"
    warnings = predict_files(
        folder, out, dataset=data, std_out=std, n_particles=300, echo=lines.append
    )
    assert warnings == []
    assert lines[0].startswith(f"wrote {out}: 6 predicted images in 1 scan(s)")
    assert lines[1] == f"wrote {std}: per-pixel spread of 1 scan(s)"
    pred = read_scans(out)
    assert pred[pred.names[0]].shape[0] == 6
    with np.load(std) as z:
        assert z[z.files[0]].shape == (6, 32, 32)
    npy = tmp_path / "pred.npy"
    predict_files(folder, npy, settings="-5,0", n_particles=300, echo=lines.append)
    assert lines[2] == f"wrote {npy}: 2 images of 32 x 32 pixels"
    assert np.load(npy).shape == (2, 32, 32)
