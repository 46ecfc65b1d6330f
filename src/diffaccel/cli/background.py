"""Work of a command done in a forked child process while the command goes on.

A default ``reconstruct`` ends with work in two independent parts: evaluation
(torch kernels) and figures (matplotlib, single-threaded Python). Drawing the
figures in a thread would not help: both parts need the GIL between their
kernels and hand it over every few milliseconds. A child forked after training
has its own interpreter, a copy of the trained ensemble and of the imported
modules, and draws on the second core while the parent evaluates (issue 12
counts the whole command).
"""

from __future__ import annotations

import json
import os
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TypeVar

import torch

__all__ = ["can_fork", "in_child"]

_T = TypeVar("_T")

#: Longest error text a child sends back (characters).
_MAX_MESSAGE = 4000


def can_fork() -> bool:
    """True where :func:`in_child` forks.

    Linux only (macOS and Windows have no safe ``fork`` for a process with
    torch's libraries), from the main thread, with no CUDA context (the child
    could not use it) and no other non-daemon Python thread (one that may hold
    a lock the child would need; tqdm's daemon monitor only holds its own).
    """
    others = [
        t
        for t in threading.enumerate()
        if t is not threading.main_thread() and not t.daemon
    ]
    return (
        sys.platform.startswith("linux")
        and hasattr(os, "fork")
        and threading.current_thread() is threading.main_thread()
        and not torch.cuda.is_initialized()
        and not others
    )


@contextmanager
def in_child(
    work: Callable[[], _T], *, fork: bool = True
) -> Iterator[Callable[[], _T]]:
    """Run ``work()`` in a forked child; the block gets a function returning its result.

    The child runs torch on one thread (an OpenMP pool does not survive
    ``fork``) and ends with ``os._exit`` after sending ``work()``'s result
    (JSON-serialisable) or its error through a pipe; it runs none of the
    parent's clean-up. Leaving the block waits for the child, so that nothing
    it writes outlives an error of the parent. Without ``fork`` (or where
    :func:`can_fork` is False) ``work()`` runs in this process when the result
    is first asked for.

    Raises:
        RuntimeError: from the result function, with the child's error as one
            line (``TypeName: message``), if ``work()`` raised there.
    """
    if not (fork and can_fork()):
        done: list[_T] = []

        def run_here() -> _T:
            if not done:
                done.append(work())
            return done[0]

        yield run_here
        return
    read_end, write_end = os.pipe()
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:  # the child: never returns
        os.close(read_end)
        status = 1
        try:
            torch.set_num_threads(1)
            message = json.dumps({"result": work()})
            status = 0
        except BaseException as err:  # everything goes to the parent
            text = str(err).strip().splitlines()
            first = text[0] if text else ""
            message = json.dumps(
                {"error": f"{type(err).__name__}: {first}"[:_MAX_MESSAGE]}
            )
        try:
            with os.fdopen(write_end, "w") as pipe:
                pipe.write(message)
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(status)
    os.close(write_end)
    outcome: dict = {}

    def wait() -> _T:
        if not outcome:
            with os.fdopen(read_end, "r") as pipe:
                text = pipe.read()
            _, status = os.waitpid(pid, 0)
            try:
                outcome.update(json.loads(text))
            except ValueError:
                outcome["error"] = (
                    f"the child process ended with status {status} and no result"
                )
        if "error" in outcome:
            raise RuntimeError(outcome["error"])
        return outcome["result"]

    try:
        yield wait
    finally:
        if not outcome:
            try:
                wait()
            except RuntimeError:
                pass  # the block's own error (or none) is the one to report
