"""One run, one owner: an exclusive lock per run folder, and children that die with the parent.

:func:`run_lock` is held by the process that trains a run (``run-one``) for as long as it runs: an ``flock`` on
``<run folder>/run.lock``, which holds the owner's pid. The kernel releases it when the process exits, however it
exits, so a lock left by a dead process is never mistaken for a live one; the owner removes the file when its run
ends (finished or failed), still holding the lock, and a process that locked a file since removed tries again on the
new one, so the lock stays exclusive. Two ``reproduce run`` commands on the
same results folder therefore share the work: a run another process owns is skipped (:func:`lock_holder`), and a
child that loses the race exits with :data:`LOCKED_EXIT` without touching the run's files.

:func:`die_with_parent`, called first thing by ``run-one``, makes a child receive SIGTERM when its parent dies, even by
SIGKILL (Linux; elsewhere the parent's own SIGINT / SIGTERM handling still stops its children,
``scheduler.run_experiment``).
"""

from __future__ import annotations

import contextlib
import ctypes
import fcntl
import os
import signal
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO

LOCK_FILE = "run.lock"
PARENT_PID_ENV = "SB3_PEARL_PARENT_PID"  # set by `reproduce run` for its children
LOCKED_EXIT = 75  # EX_TEMPFAIL: the run is owned by another process; nothing was done


class RunLockedError(RuntimeError):
    """The run is being trained by another process."""


def lock_holder(folder: str | Path) -> int | None:
    """
    The pid of the live process that owns the run in ``folder``, None if nobody does.

    :param folder: the run folder
    :return: the owner's pid (0 if it could not be read), or None
    """
    path = Path(folder) / LOCK_FILE
    try:
        file = open(path)  # noqa: SIM115  (never creates the file: a finished run leaves none)
    except FileNotFoundError:
        return None
    with file:
        try:
            fcntl.flock(file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            file.seek(0)
            text = file.read().strip()
            return int(text) if text.isdigit() else 0
        fcntl.flock(file.fileno(), fcntl.LOCK_UN)
    return None


@contextlib.contextmanager
def run_lock(folder: str | Path, wait_s: float = 2.0) -> Iterator[None]:
    """
    Own the run in ``folder`` for the duration of the block, or raise :class:`RunLockedError` after ``wait_s``.

    The short wait covers another command's :func:`lock_holder` probe, which holds the lock for an instant.

    :param folder: the run folder (created if missing)
    :param wait_s: seconds to keep trying
    """
    path = Path(folder) / LOCK_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    deadline = time.monotonic() + wait_s
    while True:
        file = open(path, "a+")  # noqa: SIM115  (held open: the lock lives as long as the file descriptor)
        try:
            fcntl.flock(file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if time.monotonic() >= deadline:
                file.seek(0)
                owner = file.read().strip() or "?"
                file.close()
                raise RunLockedError(f"{folder} is being run by another process (pid {owner})") from None
            file.close()
            time.sleep(0.1)
            continue
        if _same_file(file, path):
            break
        file.close()  # locked a file its owner removed when its run ended: lock the one at the path now
    try:
        file.seek(0)
        file.truncate()
        file.write(f"{os.getpid()}\n")
        file.flush()
        yield
    finally:
        with contextlib.suppress(OSError):
            path.unlink()  # still holding the lock: whoever opened this file finds it removed and tries again
        file.close()  # releases the lock


def _same_file(file: IO[str], path: Path) -> bool:
    """Whether the open ``file`` is still the one at ``path`` (not removed, nor replaced)."""
    try:
        on_disk = path.stat()
    except FileNotFoundError:
        return False
    opened = os.fstat(file.fileno())
    return (opened.st_dev, opened.st_ino) == (on_disk.st_dev, on_disk.st_ino)


def die_with_parent() -> None:
    """
    In a child of ``reproduce run``: receive SIGTERM when the parent process dies (Linux ``prctl(PR_SET_PDEATHSIG)``),
    and stop at once if it died before this call (the parent's pid, :data:`PARENT_PID_ENV`, is no longer ours).
    """
    expected = os.environ.get(PARENT_PID_ENV)
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM))  # 1 = PR_SET_PDEATHSIG
    if expected is not None and expected.isdigit() and os.getppid() != int(expected):
        raise KeyboardInterrupt  # the parent is gone: nothing was started
