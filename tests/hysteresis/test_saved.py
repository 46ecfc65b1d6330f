"""save_fit / load_fit: round trip and one-line errors for inconsistent files."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest
import torch

from diffaccel.hysteresis import fit_magnet, load_fit, save_fit, saved
from diffaccel.hysteresis.synthetic import bipolar_quadrupole_case


@pytest.fixture(scope="module")
def fitted():
    current, field, n, _ = bipolar_quadrupole_case(0)
    return current, fit_magnet(current[:n], field[:n], mesh_size=10, steps=30)


def test_round_trip_keeps_predictions_and_band(fitted, tmp_path: Path) -> None:
    current, fit = fitted
    save_fit(tmp_path, fit.model, fit.band, extra={"input_column": "I"})
    model, band, config = load_fit(tmp_path)
    assert config["symmetric"] is True and config["input_column"] == "I"
    with torch.no_grad():
        assert torch.equal(model(current), fit.model(current))
        assert torch.equal(band.std(model, current), fit.band.std(fit.model, current))


def _corrupt(tmp_path: Path, fitted, how: str) -> None:
    _, fit = fitted
    save_fit(tmp_path, fit.model, fit.band)
    if how == "count":
        config = json.loads((tmp_path / "model.json").read_text())
        config["n_hysterons"] += 1
        (tmp_path / "model.json").write_text(json.dumps(config))
    elif how == "pt-garbage":
        (tmp_path / "model.pt").write_bytes(b"not a torch file")
    elif how == "json-garbage":
        (tmp_path / "model.json").write_text("{")
    elif how == "missing":
        (tmp_path / "model.pt").unlink()
    elif how == "dtype":
        config = json.loads((tmp_path / "model.json").read_text())
        config["dtype"] = "banana"
        (tmp_path / "model.json").write_text(json.dumps(config))
    elif how == "band":
        tensors = torch.load(tmp_path / "model.pt", weights_only=True)
        tensors["band.directions"] = tensors["band.directions"][:, :-2]
        torch.save(tensors, tmp_path / "model.pt")


@pytest.mark.parametrize(
    ("how", "match"),
    [
        ("count", "hysterons but"),
        ("pt-garbage", "cannot read tensors"),
        ("json-garbage", "not valid JSON"),
        ("missing", "missing"),
        ("dtype", "dtype"),
        ("band", "band has"),
    ],
    ids=["count", "pt-garbage", "json-garbage", "missing", "dtype", "band"],
)
def test_inconsistent_files_raise_one_line(fitted, tmp_path, how, match) -> None:
    _corrupt(tmp_path, fitted, how)
    with pytest.raises(ValueError, match=match) as info:
        load_fit(tmp_path)
    assert "\n" not in str(info.value)


def test_load_fit_refuses_model_pt_of_another_fit(fitted, tmp_path: Path) -> None:
    # same mesh (so the hysteron counts agree), other numbers: stream.npz
    # records the SHA-256 of the model.pt it was made from
    _, fit = fitted
    mine, other = tmp_path / "mine", tmp_path / "other"
    save_fit(mine, fit.model, fit.band)
    changed = copy.deepcopy(fit.model)
    with torch.no_grad():
        changed.slope.add_(1.0)
    save_fit(other, changed, fit.band)
    (mine / "model.pt").write_bytes((other / "model.pt").read_bytes())
    with pytest.raises(ValueError, match=r"not the file .*stream\.npz was made from"):
        load_fit(mine)


def test_save_fit_refuses_a_non_empty_folder_unless_asked(
    fitted, tmp_path: Path
) -> None:
    current, fit = fitted
    save_fit(tmp_path, fit.model, fit.band)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    changed = copy.deepcopy(fit.model)
    with torch.no_grad():
        changed.slope.add_(1.0)
    with pytest.raises(FileExistsError, match="overwrite=True"):
        save_fit(tmp_path, changed, fit.band)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    save_fit(tmp_path, changed, fit.band, overwrite=True)
    model, _, _ = load_fit(tmp_path)
    with torch.no_grad():
        assert torch.equal(model(current), changed(current))


def test_interrupted_overwrite_leaves_no_loadable_mix(
    fitted, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # model.json goes first and comes back last: a folder caught between a new
    # model.pt and the old settings is refused, not loaded as one fit
    _, fit = fitted
    save_fit(tmp_path, fit.model, fit.band)

    def fail(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(saved, "write_stream_file", fail)
    with pytest.raises(OSError, match="disk full"):
        save_fit(tmp_path, fit.model, None, overwrite=True)
    with pytest.raises(ValueError, match=r"model\.json: missing"):
        load_fit(tmp_path)
