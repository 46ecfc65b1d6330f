from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from diffaccel.data import ResultFolderError, result_folder
from diffaccel.data.result_folder import MARKER


class _Late(Exception):
    pass


def _write(out: Path, files: dict[str, str], **kw) -> None:
    with result_folder(out, command="test", **kw) as folder:
        for name, text in files.items():
            (folder.path / name).write_text(text)


def _names(out: Path) -> set[str]:
    return {p.name for p in out.iterdir()} - {MARKER}


def test_new_folder_gets_every_file_and_a_marker(tmp_path: Path) -> None:
    out = tmp_path / "a" / "run"
    _write(out, {"x.txt": "1", "y.txt": "2"})
    assert _names(out) == {"x.txt", "y.txt"}
    assert json.loads((out / MARKER).read_text())["command"] == "test"
    # nothing left beside it: no lock, no staging folder
    assert sorted(p.name for p in out.parent.iterdir()) == ["run"]


def test_late_failure_with_force_leaves_the_old_result(tmp_path: Path) -> None:
    out = tmp_path / "run"
    _write(out, {"x.txt": "old", "fig.png": "old"})
    with pytest.raises(_Late), result_folder(out, command="test", force=True) as f:
        (f.path / "x.txt").write_text("new")
        raise _Late
    assert (out / "x.txt").read_text() == "old" and _names(out) == {"x.txt", "fig.png"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_force_replaces_the_whole_folder(tmp_path: Path) -> None:
    """--force --no-figures must not keep the old figures."""
    out = tmp_path / "run"
    _write(out, {"x.txt": "old", "fig.png": "old"})
    _write(out, {"x.txt": "new"}, force=True)
    assert _names(out) == {"x.txt"} and (out / "x.txt").read_text() == "new"


def test_refuses_a_result_without_force(tmp_path: Path) -> None:
    out = tmp_path / "run"
    _write(out, {"x.txt": "old"})
    with pytest.raises(ResultFolderError, match="not empty; pass --force"):
        _write(out, {"x.txt": "new"})
    assert (out / "x.txt").read_text() == "old"


def test_refuses_to_replace_a_folder_of_other_files(tmp_path: Path) -> None:
    out = tmp_path / "mine"
    out.mkdir()
    (out / "thesis.tex").write_text("precious")
    with pytest.raises(ResultFolderError, match=r"not a diffaccel result \(thesis"):
        _write(out, {"x.txt": "new"}, force=True)
    assert (out / "thesis.tex").read_text() == "precious"


def test_unmarked_folder_of_owned_names_is_an_earlier_result(tmp_path: Path) -> None:
    out = tmp_path / "run"
    out.mkdir()
    (out / "summary.json").write_text("{}")
    _write(out, {"summary.json": "[]"}, force=True, owned=["summary.json", "*.png"])
    assert (out / "summary.json").read_text() == "[]"


def test_refuses_an_input_inside_the_folder(tmp_path: Path) -> None:
    out = tmp_path / "run"
    _write(out, {"data.h5": "measured"})
    with pytest.raises(ResultFolderError, match="lies inside --out"):
        _write(out, {"x": "1"}, force=True, inputs=[out / "data.h5"])
    assert (out / "data.h5").read_text() == "measured"


def test_out_is_a_file(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("")
    with pytest.raises(ResultFolderError, match="not a folder"):
        _write(tmp_path / "f", {"x": "1"})


def test_a_second_run_is_refused_while_one_runs(tmp_path: Path) -> None:
    out = tmp_path / "run"
    with result_folder(out, command="test") as folder:
        (folder.path / "x.txt").write_text("first")
        with pytest.raises(ResultFolderError, match="being written by another run"):
            _write(out, {"x.txt": "second"}, force=True)
    assert (out / "x.txt").read_text() == "first"


def test_lock_of_a_live_process_refuses(tmp_path: Path) -> None:
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        lock = tmp_path / ".run.lock"
        import socket

        lock.write_text(json.dumps({"pid": proc.pid, "host": socket.gethostname()}))
        with pytest.raises(ResultFolderError, match=f"pid {proc.pid}"):
            _write(out, {"x": "1"})
    finally:
        proc.kill()
        proc.wait()
    # the process is gone: its lock is stale and taken over
    _write(out, {"x": "1"})
    assert (out / "x").read_text() == "1"
    assert not (tmp_path / ".run.lock").exists()


def test_garbled_old_lock_is_taken_over(tmp_path: Path) -> None:
    lock = tmp_path / ".run.lock"
    lock.write_text("{not json")
    os.utime(lock, (0, 0))
    _write(tmp_path / "run", {"x": "1"})
    assert not lock.exists()


def test_keep_partial_then_resume(tmp_path: Path) -> None:
    out = tmp_path / "run"
    with (
        pytest.raises(_Late),
        result_folder(out, command="test", keep_partial=True) as f,
    ):
        (f.path / "checkpoint").write_text("step 5")
        raise _Late
    assert not out.exists()
    with result_folder(out, command="test", resume=True, keep_partial=True) as f:
        assert (f.path / "checkpoint").read_text() == "step 5"
        (f.path / "result").write_text("done")
    assert _names(out) == {"checkpoint", "result"}


def test_keep_partial_leaves_no_empty_staging_folder(tmp_path: Path) -> None:
    # a run that fails before writing anything (e.g. bad settings found at the
    # first step) has nothing to resume: no ".run.partial" clutter is left
    out = tmp_path / "run"
    with (
        pytest.raises(_Late),
        result_folder(out, command="test", keep_partial=True),
    ):
        raise _Late
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_resume_of_a_completed_result_starts_from_its_files(tmp_path: Path) -> None:
    out = tmp_path / "run"
    _write(out, {"checkpoint": "step 10"})
    with result_folder(out, command="test", resume=True) as f:
        assert (f.path / "checkpoint").read_text() == "step 10"


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores file permissions")
def test_read_only_parent_is_reported_before_the_run(tmp_path: Path) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(ResultFolderError, match="cannot write"):
            with result_folder(ro / "run", command="test"):
                pytest.fail("the body must not run")
    finally:
        ro.chmod(0o700)


def test_refusal_names_resume_only_for_commands_that_can_resume(
    tmp_path: Path,
) -> None:
    out = tmp_path / "run"
    _write(out, {"x": "1"})
    for keep, says in ((False, False), (True, True)):
        with (
            pytest.raises(ResultFolderError, match="pass --force") as err,
            result_folder(out, command="test", keep_partial=keep),
        ):
            pass
        assert ("--resume" in str(err.value)) is says


def test_force_refuses_a_result_holding_files_the_user_added(tmp_path: Path) -> None:
    out = tmp_path / "run"
    _write(out, {"x.txt": "old"})
    (out / "notes.txt").write_text("mine")
    (out / "mysub").mkdir()
    with pytest.raises(ResultFolderError, match=r"did not write \(mysub, notes.txt\)"):
        _write(out, {"x.txt": "new"}, force=True)
    assert (out / "notes.txt").read_text() == "mine" and (out / "mysub").is_dir()
    assert (out / "x.txt").read_text() == "old"


def test_marker_lists_the_files_the_result_wrote(tmp_path: Path) -> None:
    out = tmp_path / "run"
    _write(out, {"x.txt": "1", "y.txt": "2"})
    assert json.loads((out / MARKER).read_text())["files"] == ["x.txt", "y.txt"]


@pytest.mark.parametrize("force", [False, True], ids=["plain", "force"])
def test_refuses_a_result_of_another_command(tmp_path: Path, force: bool) -> None:
    out = tmp_path / "run"
    _write(out, {"ensemble.pt": "reconstruction"})
    with pytest.raises(ResultFolderError, match="result of 'test', not of 'other'"):
        with result_folder(out, command="other", force=force) as f:
            (f.path / "fit.json").write_text("fit")
    assert _names(out) == {"ensemble.pt"}


def test_marker_without_a_file_list_falls_back_to_owned_names(
    tmp_path: Path,
) -> None:
    """A result of an earlier version: its marker names the command, no files."""
    out = tmp_path / "run"
    out.mkdir()
    (out / MARKER).write_text(json.dumps({"command": "test", "written": 0.0}))
    (out / "summary.json").write_text("{}")
    (out / "notes.txt").write_text("mine")
    with pytest.raises(ResultFolderError, match=r"did not write \(notes.txt\)"):
        _write(out, {"summary.json": "[]"}, force=True, owned=["summary.json"])
    (out / "notes.txt").unlink()
    _write(out, {"summary.json": "[]"}, force=True, owned=["summary.json"])
    assert (out / "summary.json").read_text() == "[]"


def _interrupted(out: Path) -> None:
    with (
        pytest.raises(_Late),
        result_folder(out, command="test", keep_partial=True) as f,
    ):
        (f.path / "checkpoint").write_text("step 5")
        raise _Late


def test_a_fresh_run_refuses_a_kept_staging_folder(tmp_path: Path) -> None:
    out = tmp_path / "run"
    _interrupted(out)
    staging = tmp_path / ".run.partial"
    with pytest.raises(ResultFolderError, match="--resume to continue it or --force"):
        _write(out, {"x": "1"}, keep_partial=True)
    assert (staging / "checkpoint").read_text() == "step 5"
    # --force discards it
    _write(out, {"x": "1"}, keep_partial=True, force=True)
    assert _names(out) == {"x"} and not staging.exists()


def test_a_killed_runs_kept_staging_folder_resumes(tmp_path: Path) -> None:
    """SIGKILL leaves the lock of a dead process and the staging folder."""
    out = tmp_path / "run"
    _interrupted(out)
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    lock = tmp_path / ".run.lock"
    lock.write_text(json.dumps({"pid": proc.pid, "host": socket.gethostname()}))
    with pytest.raises(ResultFolderError, match="--resume to continue it"):
        _write(out, {"x": "1"}, keep_partial=True)
    with result_folder(out, command="test", resume=True, keep_partial=True) as f:
        assert (f.path / "checkpoint").read_text() == "step 5"
    assert not lock.exists()


def test_a_killed_runs_staging_folder_without_checkpoints_is_removed(
    tmp_path: Path,
) -> None:
    # a command that keeps nothing for --resume: its leftovers are half a result
    staging = tmp_path / ".run.partial"
    staging.mkdir()
    (staging / "summary.json").write_text("half")
    _write(tmp_path / "run", {"x": "1"})
    assert not staging.exists() and _names(tmp_path / "run") == {"x"}


def test_a_failed_resume_of_a_completed_result_keeps_no_copy(tmp_path: Path) -> None:
    # the checkpoint is still in out, where the next resume finds it
    out = tmp_path / "run"
    _write(out, {"checkpoint": "step 10"})
    with (
        pytest.raises(_Late),
        result_folder(out, command="test", resume=True, keep_partial=True),
    ):
        raise _Late
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    assert _names(out) == {"checkpoint"}
