"""Corrupted files, CSVs and arguments into every reader and command.

Each case must end in a clear error: a non-zero exit code, exactly one
``Error:`` line (the message on one line), no traceback, and not the CLI's
net for unforeseen exceptions ("unexpected ..."). Readers raise ``ValueError``
(``FormatError``) or ``OSError`` naming the file, never ``KeyError``,
``TypeError``, ``AttributeError`` or ``IndexError``. Small inputs only.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner, Result

from diffaccel.cli import main
from diffaccel.data import (
    make_synthetic_quad_scan,
    read_magnet_csv,
    read_openpmd_particles,
    read_scans,
    write_quad_scan,
    write_scans,
)
from diffaccel.hysteresis import load_fit
from diffaccel.reconstruction import load, load_checkpoint

TINY = ["--particles", "16", "--steps", "1", "--snapshots", "1", "--no-figures"]
CSV = "current,field\n" + "".join(
    f"{(i % 7) - 3},{0.1 * ((i % 7) - 3) + 0.002 * i}\n" for i in range(24)
)
FIT = ["--input", "current", "--output", "field", "--steps", "3", "--mesh-size", "4"]


def assert_clear_error(r: Result) -> None:
    assert r.exit_code not in (0, None), r.output
    assert r.exception is None or isinstance(r.exception, SystemExit), repr(r.exception)
    assert "Traceback" not in r.output
    errors = [line for line in r.output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1, r.output
    assert r.output.rstrip().endswith(errors[0]), r.output  # one line, last
    assert "unexpected" not in errors[0], errors[0]


# ---------------------------------------------------------------- inputs
@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("fuzz")
    ds = make_synthetic_quad_scan(
        "gaussian",
        n_particles=300,
        n_settings=3,
        k1_range=(-4.0, 4.0),
        screen_shape=(8, 8),
        pixel_size=(2e-3, 2e-3),
        seed=0,
    )
    good = write_quad_scan(ds, d / "good.h5")
    (d / "m.csv").write_text(CSV)
    f = {"dir": d, "good": good, "csv": d / "m.csv"}
    f["empty"] = d / "empty.h5"
    f["empty"].write_bytes(b"")
    f["text"] = d / "text.h5"
    f["text"].write_text("not hdf5")
    f["truncated"] = d / "truncated.h5"
    f["truncated"].write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    f["folder"] = d / "folder.h5"
    f["folder"].mkdir()
    f["other_h5"] = d / "other.h5"
    with h5py.File(f["other_h5"], "w") as h5:
        h5["x"] = np.zeros(3)
    for name, edit in H5_EDITS.items():
        p = d / f"{name}.h5"
        p.write_bytes(good.read_bytes())
        with h5py.File(p, "r+") as h5:
            edit(h5)
        f[name] = p
    f["csv_constant_input"] = d / "const.csv"  # one current, varying field
    f["csv_constant_input"].write_text(
        "current,field\n" + "".join(f"1.0,{i}\n" for i in range(20))
    )
    for name, text in CSV_CASES.items():
        p = d / f"{name}.csv"
        p.write_bytes(text if isinstance(text, bytes) else text.encode())
        f[name] = p
    return f


def _replace(h5: h5py.File, name: str, value) -> None:
    attrs = dict(h5[name].attrs)
    del h5[name]
    h5[name] = value
    h5[name].attrs.update(attrs)


H5_EDITS: dict[str, Callable[[h5py.File], None]] = {
    "no_images": lambda h5: h5.__delitem__("images"),
    "images_1d": lambda h5: _replace(h5, "images", np.ones(5)),
    "images_text": lambda h5: _replace(h5, "images", np.array([b"a", b"b"])),
    "settings_text": lambda h5: _replace(h5, "settings", np.array([[b"x"]] * 3)),
    "names_not_json": lambda h5: h5["settings"].attrs.__setitem__("names", "[Q1"),
    "names_bytes": lambda h5: h5["settings"].attrs.__setitem__(
        "names", np.bytes_(b"\xff\xfe")
    ),
    "version_string": lambda h5: h5.attrs.__setitem__("format_version", "one"),
    "version_future": lambda h5: h5.attrs.__setitem__("format_version", 99),
    "beamline_garbage": lambda h5: _set_beamline(h5, "{]"),
    "beamline_list_of_ints": lambda h5: _set_beamline(h5, "[1, 2]"),
    "negative_images": lambda h5: _replace(h5, "images", -h5["images"][...]),
}


def _set_beamline(h5: h5py.File, text: str) -> None:
    for key in ("beamline",):
        if key in h5.attrs:
            h5.attrs[key] = text
            return
        if key in h5:
            if isinstance(h5[key], h5py.Dataset):
                _replace(h5, key, np.bytes_(text.encode()))
            else:
                h5[key].attrs["spec"] = text
            return
    h5.attrs["beamline"] = text


CSV_CASES: dict[str, str | bytes] = {
    "csv_empty": "",
    "csv_header_only": "current,field\n",
    "csv_text_cell": "current,field\n1,abc\n2,3\n",
    "csv_ragged": "current,field\n1\n2,3,4\n",
    "csv_binary": b"\x00\xff\xfe\x00garbage",
    "csv_nan": "current,field\n1,nan\n2,3\n3,4\n",
    "csv_inf": "current,field\n1,inf\n2,3\n3,4\n",
    "csv_huge": "current,field\n1,1e300\n2,3\n3,4\n",
    "csv_no_header_names": ",\n1,2\n2,3\n",
    "csv_latin1": "current,feld\u00e4\n1,2\n".encode("latin-1"),
}

QUAD_SCAN_CASES = [
    "empty",
    "text",
    "truncated",
    "folder",
    "other_h5",
    *H5_EDITS,
]


# --------------------------------------------------------------- readers
@pytest.mark.parametrize("case", QUAD_SCAN_CASES)
def test_quad_scan_reader(files, case: str) -> None:
    try:
        ds = read_scans(files[case])
    except (ValueError, OSError) as err:
        assert "\n" not in str(err).strip(), str(err)
        return
    # accepted: then it must be a valid dataset (e.g. negative pixels allowed)
    assert ds.n_images > 0


@pytest.mark.parametrize("case", ["empty", "text", "truncated", "folder", "other_h5"])
def test_particle_reader(files, case: str) -> None:
    with pytest.raises((ValueError, OSError)):
        read_openpmd_particles(files[case])


@pytest.mark.parametrize("case", [*CSV_CASES.keys() - {"csv_huge"}, "folder"])
def test_magnet_csv_reader(files, case: str) -> None:
    with pytest.raises((ValueError, OSError)) as info:
        read_magnet_csv(files[case], "current", "field")
    assert "\n" not in str(info.value).strip()


def _pt(path: Path, obj) -> Path:
    torch.save(obj, path)
    return path


PT_CASES: dict[str, object] = {
    "not_a_dict": [1, 2, 3],
    "empty_dict": {},
    "no_snapshots": {"ensemble_version": 2, "config": {}},
    "bad_config": {
        "ensemble_version": 2,
        "config": {"dims": "four"},
        "snapshots": [{}],
        "forwards": "{}",
        "history": "{}",
        "info": "{}",
    },
    "bad_forwards": {
        "ensemble_version": 2,
        "config": {"steps": 2, "snapshots": 1, "longitudinal_scale": [1, 1]},
        "snapshots": [{"w": torch.zeros(2)}],
        "forwards": "[1]",
        "history": "{}",
        "info": "{}",
    },
}


@pytest.mark.parametrize("case", [*PT_CASES, "garbage"])
def test_ensemble_loader(tmp_path: Path, case: str) -> None:
    path = tmp_path / "ensemble.pt"
    if case == "garbage":
        path.write_bytes(b"\x80\x02garbage")
    else:
        _pt(path, PT_CASES[case])
    with pytest.raises(ValueError, match=str(tmp_path)):
        load(tmp_path)


@pytest.mark.parametrize("case", [*PT_CASES, "garbage"])
def test_checkpoint_loader(tmp_path: Path, case: str) -> None:
    path = tmp_path / "checkpoint.pt"
    if case == "garbage":
        path.write_bytes(b"garbage")
    else:
        obj = PT_CASES[case]
        if isinstance(obj, dict) and obj:
            obj = {**obj, "checkpoint_version": 1}
        _pt(path, obj)
    with pytest.raises(ValueError, match=str(tmp_path)):
        load_checkpoint(path)


# ------------------------------------------------------------- commands
@pytest.fixture(scope="module")
def result_dir(files) -> Path:
    out = files["dir"] / "result"
    r = CliRunner().invoke(
        main, ["reconstruct", str(files["good"]), "--out", str(out), *TINY]
    )
    assert r.exit_code == 0, r.output
    return out


@pytest.fixture(scope="module")
def fit_dir(files) -> Path:
    out = files["dir"] / "fit"
    args = ["hysteresis", "fit", str(files["csv"]), "--train-rows", "16"]
    r = CliRunner().invoke(main, [*args, "--out", str(out), *FIT, "--no-figures"])
    assert r.exit_code == 0, r.output
    return out


@pytest.mark.parametrize("case", QUAD_SCAN_CASES)
def test_reconstruct_bad_file(files, tmp_path: Path, case: str) -> None:
    r = CliRunner().invoke(
        main, ["reconstruct", str(files[case]), "--out", str(tmp_path / "o"), *TINY]
    )
    assert_clear_error(r)
    assert not (tmp_path / "o").exists()


def test_reconstruct_refuses_v1_data_beside_scans(files, tmp_path: Path) -> None:
    path = write_scans(read_scans(files["good"]), tmp_path / "v2.h5", format_version=2)
    with h5py.File(path, "r+") as h5:  # a stray root-level images dataset
        h5["images"] = np.zeros((3, 1, 8, 8), np.float32)
    r = CliRunner().invoke(
        main, ["reconstruct", str(path), "--out", str(tmp_path / "o"), *TINY]
    )
    assert_clear_error(r)
    assert str(path) in r.output and "/images" in r.output
    assert not (tmp_path / "o").exists()


RECONSTRUCT_ARGS = {
    "cuda7": ["--device", "cuda:7"],
    "device_junk": ["--device", "banana"],
    "cpu1": ["--device", "cpu:1"],  # torch accepts it and ignores the index
    "zero_particles": ["--particles", "0"],
    "particles_beyond_memory": ["--particles", str(10**13)],  # ~15 PB to train
    "negative_steps": ["--steps", "-3"],
    "snapshots_over_steps": ["--steps", "2", "--snapshots", "5"],
    "blur_huge": ["--blur", "1e30"],
    "blur_nan": ["--blur", "nan"],
    "train_none": ["--train-indices", "none"],
    "train_junk": ["--train-indices", "a,b"],
    "train_semicolon": ["--train-indices", ";"],
    "train_out_of_range": ["--train-indices", "7"],
}


@pytest.mark.parametrize("case", RECONSTRUCT_ARGS)
def test_reconstruct_bad_options(files, tmp_path: Path, case: str) -> None:
    args = ["reconstruct", str(files["good"]), "--out", str(tmp_path / "o"), *TINY]
    r = CliRunner().invoke(main, [*args, *RECONSTRUCT_ARGS[case]])
    if case == "cuda7" and torch.cuda.device_count() > 7:
        pytest.skip("this machine has a cuda:7")
    assert_clear_error(r)
    assert not (tmp_path / "o").exists()


def test_reconstruct_out_is_a_file_or_below_one(files) -> None:
    for out in (files["good"], files["good"] / "sub"):
        r = CliRunner().invoke(
            main, ["reconstruct", str(files["good"]), "--out", str(out), *TINY]
        )
        assert_clear_error(r)
    assert read_scans(files["good"]).n_images == 3  # the input is untouched


def test_reconstruct_refuses_a_folder_of_other_files(files, tmp_path: Path) -> None:
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("precious")
    args = ["reconstruct", str(files["good"]), "--out", str(out), *TINY, "--force"]
    assert_clear_error(CliRunner().invoke(main, args))
    assert (out / "notes.txt").read_text() == "precious"


def test_reconstruct_refuses_an_input_inside_out(files, tmp_path: Path) -> None:
    out = tmp_path / "o"
    out.mkdir()
    data = out / "scan.h5"
    data.write_bytes(files["good"].read_bytes())
    args = ["reconstruct", str(data), "--out", str(out), *TINY, "--force"]
    assert_clear_error(CliRunner().invoke(main, args))
    assert data.is_file()


PREDICT_SETTINGS = {
    "semicolon": ";",
    "trailing_semicolon": "1;2;",  # an empty setting group, not ignored
    "double_comma": "1,,2",
    "empty": "",
    "comma": ",",
    "letters": "a,b",
    "two_values_one_parameter": "1:2",
    "nan": "nan",
    "absurd": "1e300",
    "huge_focusing": "1e4",  # k1 = 1e4 1/m^2 (f = 1 mm): positions overflow
}


@pytest.mark.parametrize("case", PREDICT_SETTINGS)
def test_predict_bad_settings(result_dir: Path, tmp_path: Path, case: str) -> None:
    out = tmp_path / "p.npy"
    r = CliRunner().invoke(
        main,
        [
            "predict",
            str(result_dir),
            "--settings",
            PREDICT_SETTINGS[case],
            "--out",
            str(out),
            "--particles",
            "100",
        ],
    )
    assert_clear_error(r)
    assert not out.exists()
    if case == "huge_focusing":  # the error says what may have caused the NaN
        assert "too strong" in r.output


@pytest.mark.parametrize("case", ["text", "other_h5", "truncated", "no_images"])
def test_predict_bad_dataset(files, result_dir: Path, tmp_path: Path, case) -> None:
    r = CliRunner().invoke(
        main,
        [
            "predict",
            str(result_dir),
            "--dataset",
            str(files[case]),
            "--out",
            str(tmp_path / "p.h5"),
        ],
    )
    assert_clear_error(r)


ENSEMBLE_DAMAGE = {
    "garbage": lambda p: p.write_bytes(b"garbage"),
    "empty": lambda p: p.write_bytes(b""),
    "no_snapshots": lambda p: _pt(p, PT_CASES["no_snapshots"]),
    "bad_forwards": lambda p: _pt(p, PT_CASES["bad_forwards"]),
}


@pytest.mark.parametrize("case", [*ENSEMBLE_DAMAGE, "missing"])
def test_predict_damaged_result(tmp_path: Path, case: str) -> None:
    run = tmp_path / "run"
    run.mkdir()
    if case != "missing":
        ENSEMBLE_DAMAGE[case](run / "ensemble.pt")
    r = CliRunner().invoke(
        main, ["predict", str(run), "--settings", "1", "--out", str(tmp_path / "p.npy")]
    )
    assert_clear_error(r)


@pytest.mark.parametrize("case", [*CSV_CASES, "good_h5"])
def test_hysteresis_fit_bad_csv(files, tmp_path: Path, case: str) -> None:
    path = files["good"] if case == "good_h5" else files[case]
    r = CliRunner().invoke(
        main,
        [
            "hysteresis",
            "fit",
            str(path),
            "--train-rows",
            "2",
            "--out",
            str(tmp_path / "f"),
            *FIT,
        ],
    )
    assert_clear_error(r)
    assert not (tmp_path / "f").exists()


FIT_ARGS = {
    "range_reversed": ["--input-range", "5", "-5"],
    "range_nan": ["--input-range", "nan", "1"],
    "same_column": ["--output", "current"],
    "missing_column": ["--input", "nope"],
    "too_many_rows": ["--train-rows", "999"],
    "mesh_huge": ["--mesh-size", "100000"],  # 5e9 hysterons: ran out of memory
}


@pytest.mark.parametrize("case", FIT_ARGS)
def test_hysteresis_fit_bad_options(files, tmp_path: Path, case: str) -> None:
    r = CliRunner().invoke(
        main,
        [
            "hysteresis",
            "fit",
            str(files["csv"]),
            "--train-rows",
            "16",
            "--out",
            str(tmp_path / "f"),
            *FIT,
            *FIT_ARGS[case],
        ],
    )
    assert_clear_error(r)


def test_hysteresis_fit_refuses_a_constant_input(files, tmp_path: Path) -> None:
    # one current, varying field: nothing to learn (was exit 0, 32 % rmse and
    # a RankWarning from the plot's straight line)
    data = files["csv_constant_input"]
    args = ["hysteresis", "fit", str(data), "--train-rows", "16"]
    r = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "f"), *FIT])
    assert_clear_error(r)
    assert "input is constant" in r.output
    assert not (tmp_path / "f").exists()


@pytest.mark.parametrize("case", [*CSV_CASES])
def test_hysteresis_predict_bad_csv(files, fit_dir, tmp_path: Path, case) -> None:
    out = tmp_path / "p.csv"
    r = CliRunner().invoke(
        main,
        [
            "hysteresis",
            "predict",
            str(fit_dir),
            "--input",
            str(files[case]),
            "--out",
            str(out),
        ],
    )
    if case in ("csv_text_cell", "csv_nan", "csv_inf", "csv_huge"):
        pytest.skip("the input column is fine: predicted")
    assert_clear_error(r)
    assert not out.exists()


FIT_DAMAGE = {
    "json_garbage": ("model.json", lambda p: p.write_text("{")),
    "json_list": ("model.json", lambda p: p.write_text("[]")),
    "json_dtype": (
        "model.json",
        lambda p: p.write_text(
            json.dumps({**json.loads(p.read_text()), "dtype": "Tensor"})
        ),
    ),
    "json_no_range": (
        "model.json",
        lambda p: p.write_text(
            json.dumps(
                {
                    k: v
                    for k, v in json.loads(p.read_text()).items()
                    if k != "input_range"
                }
            )
        ),
    ),
    "pt_garbage": ("model.pt", lambda p: p.write_bytes(b"garbage")),
    "pt_list": ("model.pt", lambda p: _pt(p, [1])),
    "pt_missing": ("model.pt", lambda p: p.unlink()),
}


@pytest.mark.parametrize("case", FIT_DAMAGE)
def test_hysteresis_predict_damaged_fit(files, fit_dir, tmp_path, case) -> None:
    damaged = tmp_path / "fit"
    damaged.mkdir()
    for p in fit_dir.iterdir():
        (damaged / p.name).write_bytes(p.read_bytes())
    name, damage = FIT_DAMAGE[case]
    damage(damaged / name)
    with pytest.raises(ValueError, match=str(damaged)):
        load_fit(damaged)
    r = CliRunner().invoke(
        main,
        [
            "hysteresis",
            "predict",
            str(damaged),
            "--input",
            str(files["csv"]),
            "--out",
            str(tmp_path / "p.csv"),
        ],
    )
    assert_clear_error(r)


GP_CASES = {
    "empty": ("csv_empty", []),
    "text_cell": ("csv_text_cell", []),
    "binary": ("csv_binary", []),
    "plain_missing": ("csv", ["--plain", "zz"]),
    "range_reversed": ("csv", ["--input-range", "5", "-5"]),
    "plain_twice": ("csv", ["--plain", "current", "--plain", "current"]),
    "mesh_huge": ("csv", ["--mesh-size", "100000"]),
    "constant_input": ("csv_constant_input", []),
}


@pytest.mark.parametrize("case", GP_CASES)
def test_gp_fit_bad_input(files, tmp_path: Path, case: str) -> None:
    name, extra = GP_CASES[case]
    r = CliRunner().invoke(
        main,
        [
            "hysteresis",
            "gp-fit",
            str(files[name]),
            "--x",
            "current",
            "--y",
            "field",
            "--out",
            str(tmp_path / "g"),
            "--restarts",
            "1",
            "--max-iter",
            "2",
            *extra,
        ],
    )
    assert_clear_error(r)
    assert not (tmp_path / "g").exists()


SYNTHETIC_ARGS = {
    "shape_1x1": ["--shape", "1", "1"],
    "k1_inf": ["--k1-max", "inf"],
    "k1_nan": ["--k1-min", "nan"],
    "k1_absurd": ["--k1-max", "1e30"],
    "pixel_absurd": ["--pixel-size", "1e30"],
    "pixel_nan": ["--pixel-size", "nan"],
    "p0c_nan": ["--p0c", "nan"],
    "noise_nan": ["--noise", "nan"],
    "noise_huge": ["--noise", "1e9"],
    "zero_settings": ["--settings", "0"],
}


@pytest.mark.parametrize("case", SYNTHETIC_ARGS)
def test_synthetic_bad_options(tmp_path: Path, case: str) -> None:
    out = tmp_path / "s.h5"
    r = CliRunner().invoke(
        main,
        [
            "synthetic",
            str(out),
            "--particles",
            "50",
            "--settings",
            "2",
            "--shape",
            "8",
            "8",
            *SYNTHETIC_ARGS[case],
        ],
    )
    assert_clear_error(r)
    assert not out.exists()


@pytest.mark.parametrize("case", ["text", "other_h5", "folder"])
def test_synthetic_bad_particle_file(files, tmp_path: Path, case: str) -> None:
    r = CliRunner().invoke(
        main,
        ["synthetic", str(tmp_path / "s.h5"), "--particle-file", str(files[case])],
    )
    assert_clear_error(r)


def test_predict_never_overwrites_its_dataset(files, result_dir: Path) -> None:
    before = files["good"].read_bytes()
    r = CliRunner().invoke(
        main,
        [
            "predict",
            str(result_dir),
            "--dataset",
            str(files["good"]),
            "--out",
            str(files["good"]),
            "--force",
        ],
    )
    assert_clear_error(r)
    assert files["good"].read_bytes() == before


def test_synthetic_never_overwrites_its_particle_file(tmp_path: Path) -> None:
    from diffaccel.data import sample_preset_beam, write_openpmd_particles

    beam = sample_preset_beam("gaussian", 100, torch.Generator().manual_seed(0))
    path = write_openpmd_particles(tmp_path / "beam.h5", beam, 43e6, "electron")
    before = path.read_bytes()
    r = CliRunner().invoke(
        main, ["synthetic", str(path), "--particle-file", str(path), "--force"]
    )
    assert_clear_error(r)
    assert path.read_bytes() == before


def test_predict_never_overwrites_a_file_of_its_result(
    files, result_dir: Path, fit_dir: Path, tmp_path: Path
) -> None:
    # --force allows replacing an earlier output, never the result being read
    # (hysteresis predict --out FIT/model.json --force destroyed the fit)
    model = (fit_dir / "model.json").read_bytes()
    data = tmp_path / "in.csv"
    data.write_text("current\n1\n2\n")
    args = ["hysteresis", "predict", str(fit_dir), "--input", str(data), "--force"]
    r = CliRunner().invoke(main, [*args, "--out", str(fit_dir / "model.json")])
    assert_clear_error(r)
    assert "result folder" in r.output
    assert (fit_dir / "model.json").read_bytes() == model
    parts = (result_dir / "particles.h5").read_bytes()
    args = ["predict", str(result_dir), "--dataset", str(files["good"]), "--force"]
    r = CliRunner().invoke(main, [*args, "--out", str(result_dir / "particles.h5")])
    assert_clear_error(r)
    assert (result_dir / "particles.h5").read_bytes() == parts


def test_check_device_accepts_the_cpu_by_either_name() -> None:
    from diffaccel.cli.reconstruct import check_device

    assert check_device("cpu").type == check_device("cpu:0").type == "cpu"
