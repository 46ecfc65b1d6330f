"""Work of a command done in a forked child process while the command goes on.

A default ``reconstruct`` ends with work in two independent parts: evaluation
(torch kernels) and figures (matplotlib, single-threaded Python). Drawing the
figures in a thread would not help: both parts need the GIL between their
kernels and hand it over every few milliseconds. A child forked after training
has its own interpreter, a copy of the trained ensemble and of the imported
modules, and draws on the second core while the parent evaluates. The child
is a standard :mod:`multiprocessing` process (``fork`` context); nothing but
its result is pickled.
"""

from __future__ import annotations

import multiprocessing
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from multiprocessing.connection import Connection
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
        and "fork" in multiprocessing.get_all_start_methods()
        and threading.current_thread() is threading.main_thread()
        and not torch.cuda.is_initialized()
        and not others
    )


def _child(work: Callable[[], object], conn: Connection) -> None:
    """Body of the child process: ``work()``'s result or its error, through ``conn``."""
    try:
        torch.set_num_threads(1)
        message = {"result": work()}
    except BaseException as err:  # everything goes to the parent
        text = str(err).strip().splitlines()
        first = text[0] if text else ""
        message = {"error": f"{type(err).__name__}: {first}"[:_MAX_MESSAGE]}
    try:
        conn.send(message)
    finally:
        conn.close()


@contextmanager
def in_child(
    work: Callable[[], _T], *, fork: bool = True
) -> Iterator[Callable[[], _T]]:
    """Run ``work()`` in a forked child; the block gets a function returning its result.

    The child is a :mod:`multiprocessing` process of the ``fork`` context (a
    copy of this process: nothing is pickled but the result), runs torch on one
    thread (an OpenMP pool does not survive ``fork``) and sends ``work()``'s
    result (picklable) or its error back through a pipe. Leaving the block
    waits for the child, so that nothing it writes outlives an error of the
    parent. Without ``fork`` (or where :func:`can_fork` is False) ``work()``
    runs in this process when the result is first asked for.

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
    context = multiprocessing.get_context("fork")
    receive, send = context.Pipe(duplex=False)
    child = context.Process(target=_child, args=(work, send), daemon=True)
    child.start()
    send.close()  # the child holds the sending end now
    outcome: dict = {}

    def wait() -> _T:
        if not outcome:
            try:
                outcome.update(receive.recv())
            except EOFError:
                child.join()
                outcome["error"] = (
                    f"the child process ended with exit code {child.exitcode} "
                    "and no result"
                )
            finally:
                receive.close()
                child.join()
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
