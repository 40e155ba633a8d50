"""Atomic file writes: a file that a later step reads is either the old one or the complete new one.

Every writer of the project (model zips, replay buffers, checkpoints, ``best_model.zip``, meta-test
CSV / JSON) goes through :func:`atomic_write` or :func:`atomic_path`: the content is written to a
temporary file in the destination's folder, flushed to disk (``fsync``) and renamed over the
destination with :func:`os.replace`, which is atomic on POSIX and Windows within one file system. A
process killed mid-write (SIGKILL, out of memory, power loss after the rename) leaves the previous
file intact; at worst a stale ``.<stem>.<random>.tmp<suffix>`` file stays behind in the folder.
"""

from __future__ import annotations

import contextlib
import os
import pathlib
import tempfile
from collections.abc import Iterator
from typing import IO, Any

TMP_SUFFIX = ".tmp"


def sb3_file_path(path: str | os.PathLike[str], suffix: str) -> pathlib.Path:
    """
    The file SB3 writes for ``path``: ``path`` itself, or ``path.<suffix>`` when ``path`` has no suffix.

    This is the rule of ``stable_baselines3.common.save_util.open_path`` (``save("model")`` writes
    ``model.zip``, ``save_replay_buffer("buffer")`` writes ``buffer.pkl``).

    :param path: the path given to ``save`` / ``save_replay_buffer``
    :param suffix: the default suffix without the dot (``"zip"``, ``"pkl"``)
    :return: the path of the file that will be written
    """
    path = pathlib.Path(path)
    if path.suffix == "" and suffix:
        return pathlib.Path(f"{path}.{suffix}")
    return path


def _fsync_folder(folder: pathlib.Path) -> None:
    """Make the rename itself durable (POSIX); a no-op where folders cannot be opened (Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _default_file_mode() -> int:
    """The permissions ``open(path, "w")`` would give a new file (0o666 minus the umask)."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[pathlib.Path]:
    """
    A temporary path next to ``path``; on a clean exit of the ``with`` block it replaces ``path`` atomically.

    For writers that take a path (``matplotlib``'s ``savefig``, a library's ``save(path)``). The
    temporary path keeps the destination's extension (writers that pick the format from it work);
    the writer must write exactly that path. On an exception the temporary file is removed and
    ``path`` is untouched; a write error (an ``OSError`` about the temporary file, e.g. no space left on the device)
    is raised again as the same ``OSError`` type whose message names ``path``.

    :param path: the destination file (its folder is created if missing)
    :return: the temporary path to write
    """
    destination = pathlib.Path(path)
    if destination.is_dir():
        raise IsADirectoryError(f"cannot write {destination}: it is a folder")
    folder = destination.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
        # ".model.<random>.tmp.zip": hidden, marked as temporary, and keeping the extension that writers
        # such as matplotlib read the format from.
        fd, tmp_name = tempfile.mkstemp(dir=folder, prefix=f".{destination.stem}.", suffix=f"{TMP_SUFFIX}{destination.suffix}")
    except (FileExistsError, NotADirectoryError) as error:  # a file where a folder of the path should be
        raise type(error)(error.errno, f"cannot write {destination}: {error.filename} is a file, not a folder") from None
    except OSError as error:  # e.g. a folder without write permission: name the destination, not the temporary file
        raise type(error)(error.errno, f"cannot write {destination}: {error.strerror} in {folder}") from None
    os.close(fd)
    tmp = pathlib.Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb+") as file:
            os.fsync(file.fileno())
        os.chmod(tmp, _default_file_mode() if not destination.exists() else destination.stat().st_mode & 0o777)
        os.replace(tmp, destination)
    except OSError as error:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if error.filename not in (None, str(tmp)):
            raise  # about another file than the one written
        # a write error (no space left, file too large, ...): name the destination, which keeps its previous content
        raise type(error)(error.errno, f"cannot write {destination}: {error.strerror or error}") from None
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    _fsync_folder(folder)


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike[str], mode: str = "wb", **open_kwargs: Any) -> Iterator[IO[Any]]:
    """
    Open a temporary file next to ``path`` for writing; on a clean exit it replaces ``path`` atomically.

    ``with atomic_write("meta_test.json", "w") as file: json.dump(data, file)``. On an exception
    (or a kill) ``path`` keeps its previous content.

    :param path: the destination file (its folder is created if missing)
    :param mode: ``"wb"`` (binary) or ``"w"`` (text)
    :param open_kwargs: passed to :func:`open` (``newline``, ``encoding``)
    :return: the open temporary file
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write: mode must be 'w' or 'wb', got {mode!r}")
    with atomic_path(path) as tmp, open(tmp, mode, **open_kwargs) as file:
        yield file
        file.flush()


__all__ = ["atomic_path", "atomic_write", "sb3_file_path"]
