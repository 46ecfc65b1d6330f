"""cli.background: work done in a forked child while the command goes on."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from diffaccel.cli.background import can_fork, in_child

needs_fork = pytest.mark.skipif(not can_fork(), reason="no fork here")


@needs_fork
def test_work_runs_in_another_process_and_returns_its_result() -> None:
    with in_child(lambda: {"pid": os.getpid(), "x": [1, 2]}) as result:
        got = result()
    assert got["x"] == [1, 2]
    assert got["pid"] != os.getpid()


def test_without_fork_the_work_runs_here_once() -> None:
    calls = []

    def work() -> int:
        calls.append(1)
        return os.getpid()

    with in_child(work, fork=False) as result:
        assert not calls  # not before it is asked for
        assert result() == os.getpid() and result() == os.getpid()
    assert calls == [1]


@needs_fork
def test_an_error_in_the_child_is_raised_as_one_line() -> None:
    def work() -> None:
        raise ValueError("no such figure\nsecond line")

    with in_child(work) as result, pytest.raises(RuntimeError) as err:
        result()
    assert str(err.value) == "ValueError: no such figure"


@needs_fork
def test_leaving_the_block_waits_for_the_child(tmp_path: Path) -> None:
    done = tmp_path / "done"

    def work() -> None:
        time.sleep(0.2)
        done.write_text("x")

    with pytest.raises(KeyError), in_child(work):
        raise KeyError("the parent fails first")
    assert done.exists()  # the child finished before the error went on


@needs_fork
def test_the_child_runs_torch_on_one_thread() -> None:
    import torch

    with in_child(torch.get_num_threads) as result:
        assert result() == 1


@needs_fork
def test_a_child_that_dies_without_a_result_is_a_clear_error() -> None:
    # e.g. killed by the out-of-memory killer: no traceback from the pipe
    with in_child(lambda: os._exit(3)) as result, pytest.raises(RuntimeError) as err:
        result()
    assert str(err.value) == "the child process ended with exit code 3 and no result"
