"""Checkpoints of a reproduction run, so that ``reproduce run`` resumes an interrupted run where it stopped.

A run folder holds, until its result.json is written, ``checkpoint/``:

- ``state.json``: where the run is (``phase``: ``train`` or ``evaluate``), its env steps, the CPU and wall seconds
  spent so far over all its processes, the evaluation phases already done (``phases``: their result.json entries);
- ``model_<steps>.zip`` and ``replay_<steps>.pkl``: the model (with every RNG state and, for a DummyVecEnv, the envs'
  open episodes: :mod:`sb3_pearl.common.persistence`) and its replay buffer, written at the start of the first
  iteration after every ``interval_s`` seconds of training (:class:`PeriodicCheckpoint`), and once more when
  training ends;
- ``progress_<steps>.csv``: the training log as it was at that checkpoint (the resumed run continues it).

A replay buffer over ``PART_BYTES`` (a cheetah-vel buffer from ~150k steps) is written as ``<name>.part0``,
``<name>.part1``, ... of at most ``PART_BYTES`` each, never whole, so that a part-way run's checkpoint can be
committed where a file over 100 MB cannot (git hosts' limit); loading joins them. No checkpoint is written at the
step of the one in force (a resumed run's first iteration start): parts rewritten under the same names could
otherwise pair with the old ones if a kill came between them.

Every file is written atomically (temporary file, then rename) under a name of its own, and ``state.json``, which
names the files of the checkpoint in force, is written last; the previous checkpoint's files are deleted only
after that. A kill at any moment therefore leaves one complete, consistent checkpoint (the model, the buffer and
the log of the same step), and loading checks that the model's step count is the state's.

Resuming from an iteration start is exact (docs/reliability.md, "Exact resume"): the resumed run trains the
same weights, bit for bit; an evaluation phase that was cut is run again from its start (the meta-tests are seeded
per trajectory with common random numbers, the measures and diagnostics by their own seeds), so the result.json
metrics are those of an uninterrupted run (tests/test_reproduce_resume.py). The folder is deleted once result.json
is written.
"""

from __future__ import annotations

import csv
import io
import json
import pickle
import shutil
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import CSVOutputFormat, Logger

from sb3_pearl.common.atomic import atomic_write
from sb3_pearl.common.env_state import EnvStateError
from sb3_pearl.common.persistence import DamagedModelError, compact_buffer, read_model_data

CHECKPOINT_DIR = "checkpoint"
STATE_FILE = "state.json"
FILE_NAMES = {"model": "model_{}.zip", "replay": "replay_{}.pkl", "progress": "progress_{}.csv"}
DEFAULT_INTERVAL_S = 600.0  # every 10 minutes of training
PART_BYTES = 50_000_000  # largest checkpoint file written: git hosts refuse files over 100 MB and warn over 50 MB

Interrupt = Callable[[str, int], None]  # (where, count): tests raise in it to simulate a kill


class RunCheckpoint:
    """
    The ``checkpoint/`` folder of one run folder.

    :param run_folder: the run folder
    """

    def __init__(self, run_folder: str | Path) -> None:
        self.run_folder = Path(run_folder)
        self.folder = self.run_folder / CHECKPOINT_DIR

    def read_state(self) -> dict[str, Any] | None:
        """
        The saved state, None when no checkpoint was written. A state whose files are missing or damaged is returned:
        :meth:`damage` says what is wrong, and the resume refuses it rather than restarting the run over it.
        """
        path = self.folder / STATE_FILE
        if not path.is_file():
            return None
        try:
            state = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as error:
            raise ValueError(f"{path} is unreadable ({error}): delete {self.folder} to restart the run from zero") from error
        if not isinstance(state, dict):
            raise ValueError(f"{path} holds no checkpoint state: delete {self.folder} to restart the run from zero")
        return state

    def write_state(self, state: dict[str, Any]) -> None:
        """Write the state (atomically); then delete the files of earlier checkpoints it no longer names."""
        with atomic_write(self.folder / STATE_FILE, "w") as file:
            json.dump(state, file, indent=1, allow_nan=False)
        keep = set((state.get("files") or {}).values()) | {STATE_FILE}
        for path in self.folder.iterdir():
            if path.name not in keep and not path.name.startswith("."):
                path.unlink(missing_ok=True)

    def save_model(self, model: Any, progress: Path | None, tag: str | None = None) -> dict[str, str]:
        """
        Save the model, its replay buffer (off-policy models) and a snapshot of the training log, under names of their own.

        :param tag: what the names hold (default: the env steps); a stop between two gradient steps saves at the env
            steps of an earlier checkpoint, under a tag with the gradient steps
        :return: the files written (``model``, ``replay``, ``progress``), for the state that will name them
        """
        self.folder.mkdir(parents=True, exist_ok=True)
        steps = tag or str(int(model.num_timesteps))
        files = {"model": FILE_NAMES["model"].format(steps)}
        model.save(self.folder / files["model"])
        if getattr(model, "replay_buffer", None) is not None and hasattr(model, "save_replay_buffer"):
            pickled = _Unclosed()  # in memory first: a kill never leaves a whole buffer over the part size on disk
            model.save_replay_buffer(pickled)
            files.update(self._write_parts(FILE_NAMES["replay"].format(steps), pickled.getvalue(), "replay"))
        if progress is not None and progress.is_file():
            files["progress"] = FILE_NAMES["progress"].format(steps)
            with atomic_write(self.folder / files["progress"], "wb") as file:
                file.write(progress.read_bytes())
        return files

    def load_model(self, state: dict[str, Any], algo_cls: Any, env: Any, device: str = "auto") -> Any:
        """
        The checkpoint's model on ``env`` (envs' episodes and RNG streams restored), with its replay buffer.

        Strict about the envs' saved episodes: a snapshot this MuJoCo cannot read (another release wrote it) stops the
        resume with the versions to install, rather than continuing a run that would differ from an unsplit one.
        """
        files = state["files"]
        damage = self.damage(state)
        if damage is not None:
            raise ValueError(f"{damage}: delete {self.folder}, or rerun with --force, to restart the run from zero")
        try:
            model = algo_cls.load(self.folder / files["model"], env=env, device=device, strict_env=True)
        except EnvStateError as error:
            raise EnvStateError(f"{error}, or restart the run from zero with --force") from error
        if hasattr(model, "load_replay_buffer"):
            if "replay" in files:  # read from the file: its errors name it, and no second copy is held in memory
                model.load_replay_buffer(self.folder / files["replay"])
            elif "replay.part0" in files:
                model.load_replay_buffer(io.BytesIO(self._joined(files, "replay")))
        if int(model.num_timesteps) != int(state["num_timesteps"]):
            raise ValueError(
                f"{self.folder}: the model is at {model.num_timesteps} steps, the state says {state['num_timesteps']}: "
                f"delete {self.folder} to restart the run from zero"
            )
        return model

    def damage(self, state: dict[str, Any]) -> str | None:
        """
        Why the checkpoint cannot be resumed although its state names it, or None: its model zip is missing, cut or corrupt
        (:func:`~sb3_pearl.common.persistence.read_model_data`: the zip's directory, every entry's CRC, the ``data``
        entry), or a replay-buffer file it names is missing or empty.

        :param state: :meth:`read_state`'s state
        :return: ``"checkpoint damaged: <what>"``, or None
        """
        files = state.get("files") or {}
        if not files.get("model"):
            return f"checkpoint damaged: {self.folder / STATE_FILE} names no model"
        if not (self.folder / files["model"]).is_file():
            return f"checkpoint damaged: {self.folder / files['model']} is missing"
        try:
            read_model_data(self.folder / files["model"])
        except (DamagedModelError, OSError) as error:
            return f"checkpoint damaged: {error.problem if isinstance(error, DamagedModelError) else error}"
        for key, name in files.items():
            path = self.folder / name
            if key.startswith("replay") and (not path.is_file() or path.stat().st_size == 0):
                return f"checkpoint damaged: {path} is {'empty' if path.is_file() else 'missing'}"
        return None

    def _write_parts(self, name: str, data: bytes, key: str) -> dict[str, str]:
        """
        Write ``data`` as the file ``name``, or over ``PART_BYTES`` as ``name.part0``, ``name.part1``, ... (each atomically).

        :return: ``{key: name}`` for a whole file, else ``{f"{key}.part{i}": part name}``
        """
        chunks = [data[i : i + PART_BYTES] for i in range(0, len(data), PART_BYTES)] or [data]
        written = {key: name} if len(chunks) == 1 else {f"{key}.part{i}": f"{name}.part{i}" for i in range(len(chunks))}
        for part, chunk in zip(written.values(), chunks):
            with atomic_write(self.folder / part, "wb") as file:
                file.write(chunk)
        return written

    def replay_bytes(self, files: dict[str, str]) -> bytes | None:
        """
        The replay buffer's pickled bytes, whole or joined from its parts (``compact`` and ``reward-profile``).

        :param files: the ``files`` of :meth:`read_state`'s state
        :return: the bytes, or None when the checkpoint holds no replay buffer
        """
        if "replay" in files:
            return (self.folder / files["replay"]).read_bytes()
        if "replay.part0" in files:
            return self._joined(files, "replay")
        return None

    def _joined(self, files: dict[str, str], key: str) -> bytes:
        """The bytes of a file saved in parts (``key.part0``, ``key.part1``, ...), joined in order."""
        chunks, i = [], 0
        while f"{key}.part{i}" in files:
            chunks.append((self.folder / files[f"{key}.part{i}"]).read_bytes())
            i += 1
        return b"".join(chunks)

    def compact_replay(self) -> tuple[int, int]:
        """
        Rewrite the replay buffer of the checkpoint in force with only its filled rows
        (:func:`~sb3_pearl.common.persistence.compact_buffer`; what ``save_replay_buffer`` writes since it does so), so
        that an older part-way checkpoint can be committed. The new parts are written, then the state naming them,
        then the old parts are deleted: a kill at any moment leaves one complete checkpoint.

        :return: the buffer's bytes before and after (equal when there was nothing to compact)
        """
        state = self.read_state()
        files = dict((state or {}).get("files") or {})
        if state is None:
            return 0, 0
        data = self.replay_bytes(files)
        if data is None:
            return 0, 0
        buffer = pickle.loads(data)
        compact = compact_buffer(buffer)
        if compact is buffer:
            return len(data), len(data)
        packed = pickle.dumps(compact, protocol=pickle.HIGHEST_PROTOCOL)
        old = {key: name for key, name in files.items() if key == "replay" or key.startswith("replay.part")}
        name = FILE_NAMES["replay"].format(f"{int(state['num_timesteps'])}_compact")
        kept = {key: value for key, value in files.items() if key not in old}
        state["files"] = {**kept, **self._write_parts(name, packed, "replay")}
        self.write_state(state)
        for stale in old.values():
            if stale not in state["files"].values():
                (self.folder / stale).unlink(missing_ok=True)
        return len(data), len(packed)

    def size_bytes(self, state: dict[str, Any]) -> int:
        """The bytes on disk of the files the state names, with the state itself: what committing the checkpoint adds."""
        names = [*(state.get("files") or {}).values(), STATE_FILE]
        return sum((self.folder / name).stat().st_size for name in names if (self.folder / name).is_file())

    def progress_snapshot(self, state: dict[str, Any]) -> Path | None:
        """The training log saved with the checkpoint, if any."""
        name = (state.get("files") or {}).get("progress")
        return self.folder / name if name and (self.folder / name).is_file() else None

    def remove(self) -> None:
        """Delete the checkpoint (the run is complete)."""
        shutil.rmtree(self.folder, ignore_errors=True)


def resume_promise(folder: Path) -> str:
    """What the same ``reproduce run`` command does with an interrupted run: resume its checkpoint, or start anew."""
    checkpoint = RunCheckpoint(folder)
    try:
        state = checkpoint.read_state()
        damage = checkpoint.damage(state) if state is not None else None
    except (OSError, ValueError):
        state = damage = None
    if damage is not None:
        return f"{damage}: delete {checkpoint.folder} (or add --force), and the same `reproduce run` command starts it anew"
    if state is None:
        return (
            "no checkpoint was written yet (one is written every 10 minutes of training): the same `reproduce run` "
            "command starts this run anew"
        )
    return (
        f"the same `reproduce run` command resumes this run from its checkpoint at {int(state.get('num_timesteps', 0)):,} "
        "env steps"
    )


class _Unclosed(io.BytesIO):
    """An in-memory file that SB3's ``save_to_pkl`` cannot close (it closes the file it was given)."""

    def close(self) -> None:
        pass


def csv_log_problem(text: str) -> str | None:
    """
    Why ``text`` is not a training log SB3's csv logger can continue (a header of column names, then rows of as many
    fields), or None when it is.

    :param text: the log's content
    :return: the problem, or None
    """
    if not text.strip():
        return "it is empty"
    if "\x00" in text:
        return "it holds NUL bytes (a file cut by a crash)"
    rows = list(csv.reader(io.StringIO(text)))
    header = rows[0] if rows else []
    if not header or not all(name.strip() for name in header):
        return "its first line is not a header of column names"
    bad = next((index for index, row in enumerate(rows[1:], start=2) if row and len(row) != len(header)), None)
    if bad is not None:
        return f"line {bad} has {len(rows[bad - 1])} fields, the header {len(header)}"
    return None


def csv_logger_continuing(folder: Path, snapshot: Path | None) -> Logger:
    """
    SB3's csv logger on ``folder/progress.csv`` that continues the rows of ``snapshot`` (a resumed run) or starts empty.

    A snapshot that is empty or cannot be parsed (:func:`csv_log_problem`) is not restored: the run's progress.csv is
    kept as it is and continued, with a warning naming the snapshot (its rows after the checkpoint's step, if any,
    then appear twice), rather than emptied.

    :param folder: the run folder
    :param snapshot: the training log saved with the checkpoint (None: a new log)
    :return: the logger
    """
    path = folder / "progress.csv"
    text = ""
    if snapshot is not None:
        text = snapshot.read_text(errors="replace")
        problem = csv_log_problem(text)
        if problem is not None:
            current = path.read_text(errors="replace") if path.is_file() else ""
            kept = csv_log_problem(current) is None
            warnings.warn(
                f"{snapshot} is not restored: {problem}; "
                + (f"{path} kept as it is and continued" if kept else f"{path} holds no log either: a new log starts"),
                stacklevel=2,
            )
            text = current if kept else ""
    output = CSVOutputFormat(str(path))  # truncates: the log is written back below
    if text:
        output.file.write(text if text.endswith("\n") else text + "\n")
        output.file.flush()
        output.keys = next(csv.reader(io.StringIO(text)))  # SB3 extends the header (and rewrites the file) for new keys
    return Logger(str(folder), [output])


class PeriodicCheckpoint(BaseCallback):
    """
    Save a resumable checkpoint at the first iteration start after every ``interval_s`` seconds (0: every iteration).

    PEARL / PEARL+ and MAML call ``on_rollout_start`` before they draw an iteration's tasks, so a checkpoint there
    resumes bit for bit; Fine-Tune's rollouts are single env steps, its checkpoints hold the envs' open episodes.

    :param checkpoint: the run's checkpoint folder
    :param progress: the run's training log (snapshotted with each checkpoint)
    :param interval_s: seconds of training between checkpoints
    :param on_save: called with the files of each save (the runner writes the state naming them)
    :param interrupt: test hook, called as ``interrupt("step", n)`` after every env step and
        ``interrupt("iteration", n)`` after every iteration-start checkpoint
    :param in_force_steps: env steps of the checkpoint the run resumed from (-1: none); none is written again there
    """

    def __init__(
        self,
        checkpoint: RunCheckpoint,
        progress: Path,
        interval_s: float,
        on_save: Callable[[dict[str, str]], None],
        interrupt: Interrupt | None = None,
        in_force_steps: int = -1,
    ) -> None:
        super().__init__()
        self.checkpoint = checkpoint
        self.progress = progress
        self.interval_s = interval_s
        self.on_save = on_save
        self.interrupt = interrupt
        self._last = time.monotonic()
        self._iterations = 0
        self._saved_steps = in_force_steps

    def _on_step(self) -> bool:
        if self.interrupt is not None:
            self.interrupt("step", self.num_timesteps)
        return True

    def _on_rollout_start(self) -> None:
        if time.monotonic() - self._last < self.interval_s or self.model.num_timesteps in (0, self._saved_steps):
            return
        self.on_save(self.checkpoint.save_model(self.model, self.progress))
        self._saved_steps = int(self.model.num_timesteps)
        self._last = time.monotonic()
        self._iterations += 1
        if self.interrupt is not None:
            self.interrupt("iteration", self._iterations)
