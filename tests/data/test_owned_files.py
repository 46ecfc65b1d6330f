from __future__ import annotations

import errno
from pathlib import Path

import h5py
import numpy as np
import pytest

from diffaccel.data import make_synthetic_quad_scan, write_quad_scan
from diffaccel.data.atomic import os_condition
from diffaccel.data.owned_files import (
    OutputFileError,
    check_out_file,
    mark_npz,
    save_arrays,
    save_npy,
    written_by_diffaccel,
)


def test_npy_and_npz_records_are_read_back(tmp_path: Path) -> None:
    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    ours, theirs = tmp_path / "ours.npy", tmp_path / "theirs.npy"
    with ours.open("wb") as f:
        save_npy(f, a)
    np.save(theirs, a)
    assert np.array_equal(np.load(ours), a) and np.load(ours).dtype == np.float32
    assert np.load(ours, mmap_mode="r").shape == (3, 4)
    assert (len(ours.read_bytes()) - len(a.tobytes())) % 64 == 0  # aligned header
    assert written_by_diffaccel(ours) and not written_by_diffaccel(theirs)
    npz = tmp_path / "s.npz"
    np.savez(npz, scan=a)
    assert not written_by_diffaccel(npz)
    mark_npz(npz)
    assert written_by_diffaccel(npz)
    with np.load(npz) as z:
        assert z.files == ["scan"] and np.array_equal(z["scan"], a)


def test_hdf5_and_csv_records(tmp_path: Path) -> None:
    h5 = tmp_path / "scan.h5"
    write_quad_scan(make_synthetic_quad_scan("gaussian", n_particles=200), h5)
    assert written_by_diffaccel(h5)
    with h5py.File(h5, "r+") as f:
        assert str(f.attrs["written_by"]).startswith("diffaccel ")
        del f.attrs["written_by"]
    assert not written_by_diffaccel(h5)
    csv = tmp_path / "p.csv"
    csv.write_text("current_A,prediction,prediction_std\n1,2,3\n")
    cols = ("prediction", "prediction_std")
    assert written_by_diffaccel(csv, csv_columns=cols)
    assert not written_by_diffaccel(csv, csv_columns=("other",))
    assert not written_by_diffaccel(tmp_path / "missing.h5")
    (tmp_path / "x.txt").write_text("mine")
    assert not written_by_diffaccel(tmp_path / "x.txt")


def test_os_conditions_are_named() -> None:
    assert os_condition(OSError(errno.ENOSPC, "x")).startswith("no space left")
    assert os_condition(OSError(errno.EROFS, "x")) == "read-only file system"
    assert os_condition(PermissionError(errno.EACCES, "x")) == "permission denied"
    locked = OSError("Unable to open file (unable to lock file, errno = 11)")
    assert os_condition(locked).startswith("locked by another program")
    wrapped = ValueError("writing failed")
    wrapped.__cause__ = OSError(errno.ENOSPC, "x")
    assert os_condition(wrapped).startswith("no space left")
    assert os_condition(OSError(errno.ENOENT, "x")) is None


def test_a_locked_file_is_not_taken_for_a_foreign_one(
    tmp_path: Path, monkeypatch
) -> None:
    h5 = tmp_path / "scan.h5"
    write_quad_scan(make_synthetic_quad_scan("gaussian", n_particles=200), h5)

    def locked(*a, **kw):
        raise OSError(errno.EAGAIN, "Unable to open file (unable to lock file)")

    monkeypatch.setattr(h5py, "File", locked)
    with pytest.raises(OSError, match="unable to lock"):
        written_by_diffaccel(h5)


def test_save_arrays_writes_marked_npy_or_npz(tmp_path) -> None:
    one = np.arange(6, dtype=np.float32).reshape(2, 3)
    npy = save_arrays(tmp_path / "new" / "a.NPY", {"x": one})
    assert npy == tmp_path / "new" / "a.NPY"  # the folder made
    np.testing.assert_array_equal(np.load(npy), one)
    assert written_by_diffaccel(npy)
    npz = save_arrays(tmp_path / "b.npz", {"a": one, "b": 2 * one})
    with np.load(npz) as z:
        assert sorted(z.files) == ["a", "b"]
        np.testing.assert_array_equal(z["b"], 2 * one)
    assert written_by_diffaccel(npz)
    with pytest.raises(ValueError, match=r"2 arrays; write them to an \.npz"):
        save_arrays(tmp_path / "c.npy", {"a": one, "b": one})
    assert not (tmp_path / "c.npy").exists()


def test_check_out_file_refuses_inputs_result_folders_and_foreign_files(
    tmp_path: Path,
) -> None:
    data = tmp_path / "data.csv"
    data.write_text("a\n1\n")
    with pytest.raises(OutputFileError, match=r"--out .*data.csv is the --input file"):
        check_out_file(data, True, {"--input": data, "--other": None})
    folder = tmp_path / "fit"
    folder.mkdir()
    (folder / ".diffaccel-result").write_text("{}")
    with pytest.raises(OutputFileError, match="inside the result folder"):
        check_out_file(folder / "p.npy", True, {}, option="--std-out")
    theirs = tmp_path / "theirs.npy"
    np.save(theirs, np.zeros(2))
    with pytest.raises(OutputFileError, match="pass --force to overwrite it"):
        check_out_file(theirs, False, {})
    with pytest.raises(OutputFileError, match="not written by diffaccel"):
        check_out_file(theirs, True, {})
    ours = save_arrays(tmp_path / "ours.npy", {"x": np.zeros(2)})
    check_out_file(ours, True, {})  # diffaccel's own: --force replaces it
    check_out_file(tmp_path / "new.npy", False, {})
