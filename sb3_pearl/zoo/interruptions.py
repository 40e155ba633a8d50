"""Interruptions of ``train.py``: SIGTERM, Ctrl-C (SIGINT) and exceptions save the model (docs/cli.md).

:class:`InterruptibleExperimentManager` is rl_zoo3's ``ExperimentManager`` with:

- SIGTERM (``kill``, a batch scheduler's time limit) and SIGINT (Ctrl-C) handled alike: training stops at the next
  point where it can be resumed exactly (:class:`StopOnSignalCallback`; a second signal stops at once), the model and
  its replay buffer are saved, the run is marked cut (``interrupted.json`` in the run folder, what follows the save
  is skipped) and ``train.py`` exits with status 128 + the signal (143 for SIGTERM, 130 for SIGINT);
- a signal during the set-up (before training) stopping it at once, the run folder it reserved removed
  (:class:`SetupInterrupted`, exit status 128 + the signal);
- an exception during training saving the model reached so far into the run folder, saying where, re-raised;
- a final save that fails (no space left, ...) answered in one line naming the file (exit status 1);
- ``--resume`` (:attr:`resume`): training continues a checkpoint's run with its counters, up to ``n_timesteps``;
- ``--vec-env subproc`` workers that ignore SIGINT and SIGTERM (:class:`SignalShieldedSubprocVecEnv`): Ctrl-C reaches
  the terminal's whole process group, and a worker that died of it broke the env pipe under the stop; the main process
  stops training and closes them.
"""

from __future__ import annotations

import atexit
import errno
import glob
import json
import os
import shlex
import signal
import sys
import threading
import weakref
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

import gymnasium as gym
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.vec_env import SubprocVecEnv, VecEnv

from sb3_pearl.common.atomic import atomic_write
from sb3_pearl.common.callbacks import StopOnSignalCallback, StopRequested
from sb3_pearl.evaluation.callbacks import MetaTestCallback
from sb3_pearl.zoo.rl_zoo3_coupling import ExperimentManager
from sb3_pearl.zoo.usage import program_name

INTERRUPTED_FILE = "interrupted.json"  # in the run folder of a run cut by a signal
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


class SetupInterrupted(KeyboardInterrupt):
    """
    SIGTERM or SIGINT during the set-up, before training: nothing to save, so the set-up stops where it is and the run
    folder it reserved is removed (a half-made folder without a model was left before, and ``enjoy.py``'s "latest
    run" was then that empty folder).

    :param signal_name: ``"SIGTERM"`` or ``"SIGINT"``
    """

    def __init__(self, signal_name: str) -> None:
        super().__init__(signal_name)
        self.signal_name = signal_name

    @property
    def exit_status(self) -> int:
        """128 + the signal, as a process killed by it."""
        return 128 + int(signal.Signals[self.signal_name])


def _shielded(env_fn: Callable[[], gym.Env]) -> Callable[[], gym.Env]:
    """``env_fn`` that first makes the process it runs in (a worker) ignore SIGINT and SIGTERM."""

    def make() -> gym.Env:
        for signum in STOP_SIGNALS:
            signal.signal(signum, signal.SIG_IGN)
        return env_fn()

    return make


class SignalShieldedSubprocVecEnv(SubprocVecEnv):
    """
    SB3's ``SubprocVecEnv`` whose workers ignore SIGINT and SIGTERM: a stop is the main process's to make (it finishes
    the step, saves and closes the workers), where a worker killed by the terminal's Ctrl-C broke the pipe under it.

    :param env_fns: the env makers, as for ``SubprocVecEnv``
    :param start_method: as for ``SubprocVecEnv``
    """

    def __init__(self, env_fns: list[Callable[[], gym.Env]], start_method: str | None = None) -> None:
        super().__init__([_shielded(env_fn) for env_fn in env_fns], start_method=start_method)
        # multiprocessing ends daemon workers at exit with SIGTERM, which these ignore: close them first (an env left
        # open, e.g. the final meta-test's after a stop, would otherwise hang the exit)
        atexit.register(_close_at_exit, weakref.ref(self))


def _close_at_exit(ref: weakref.ref[SignalShieldedSubprocVecEnv]) -> None:
    """Close the VecEnv ``ref`` names, if it is still open."""
    vec_env = ref()
    if vec_env is not None and not vec_env.closed:
        try:
            vec_env.close()
        except (BrokenPipeError, EOFError, OSError):
            for process in vec_env.processes:
                process.kill()


class InterruptibleExperimentManager(ExperimentManager):
    """rl_zoo3's ``ExperimentManager`` whose training survives signals and exceptions, model saved (module docstring)."""

    resume: bool = False  # --resume: continue the checkpoint's run (counters kept) up to n_timesteps in all
    command: list[str] = []  # noqa: RUF012  (train.py's command line, set per instance)
    _stop_signal: str | None = None
    _stopped_at_once: bool = False  # a second signal stopped training where it was: the resume is not exact
    _phase: str = "setup"  # "training", "saving", "after save": what a signal does (_on_signal)
    _previous_handlers: dict[int, Any]  # the signal handlers to restore

    def learn(self, model: BaseAlgorithm) -> None:
        """
        rl_zoo3's ``learn``, plus:

        - SIGTERM and SIGINT (Ctrl-C) stop training at the next point where the run resumes exactly (a second signal
          stops at once); the model and its replay buffer are saved, the run is marked cut and ``train.py`` exits with
          status 128 + the signal (:meth:`save_trained_model`);
        - an exception during training saves the model reached so far into the run folder, says where, and is
          re-raised.

        :param model: the model to train
        """
        self._stop_signal = None
        self._stop_callback = StopOnSignalCallback()
        self.callbacks.append(self._stop_callback)
        self._phase = "training"
        self._previous_handlers = self._install_signal_handlers()
        try:
            if self.resume and self.continue_training:
                self._learn_resumed(model)
            else:
                super().learn(model)
        except Exception as error:
            self._restore_signal_handlers()
            self._save_after_failure(model, error)
            raise
        self._phase = "saving"  # from here on, a signal no longer interrupts the save

    def create_envs(self, n_envs: int, eval_env: bool = False, no_log: bool = False) -> VecEnv:
        """rl_zoo3's ``create_envs``; ``--vec-env subproc`` makes :class:`SignalShieldedSubprocVecEnv` workers."""
        if self.vec_env_class is SubprocVecEnv:
            self.vec_env_class = SignalShieldedSubprocVecEnv
        return super().create_envs(n_envs, eval_env=eval_env, no_log=no_log)

    def _learn_resumed(self, model: BaseAlgorithm) -> None:
        """
        ``train.py --resume``: continue the checkpoint's run up to ``n_timesteps`` in all (its counters kept,
        ``reset_num_timesteps=False``), as rl_zoo3's ``learn`` otherwise (a stop saves the model).
        """
        remaining = self.n_timesteps - model.num_timesteps
        print(f"Resuming at {model.num_timesteps} timesteps: {max(remaining, 0)} to go (n_timesteps {self.n_timesteps})")
        kwargs: dict[str, Any] = {}
        if self.log_interval > -1:
            kwargs["log_interval"] = self.log_interval
        elif self.log_interval < -1:
            kwargs["log_interval"] = None
        if self.callbacks:
            kwargs["callback"] = self.callbacks
        pending = int(getattr(model, "_pending_gradient_steps", 0))
        if pending > 0:
            print(f"First the {pending:,} gradient steps of the iteration the stop interrupted", flush=True)
        learning = remaining > 0 or pending > 0
        try:
            if learning:
                model.learn(max(remaining, 0), reset_num_timesteps=False, **kwargs)
            else:  # nothing to train: the cut run's evaluations still continue in this run's folder
                for callback in self.callbacks:
                    if isinstance(callback, MetaTestCallback):
                        callback.init_callback(model)
        except KeyboardInterrupt:
            pass  # as rl_zoo3: the model is saved by save_trained_model
        finally:
            if self.callbacks and learning:  # (callbacks that learn() never started have nothing to end)
                self.callbacks[0].on_training_end()
            try:
                assert model.env is not None
                model.env.close()
            except EOFError:
                pass

    @contextmanager
    def stop_signals_abort_setup(self) -> Iterator[None]:
        """
        Within the block (the set-up), SIGTERM and SIGINT raise :class:`SetupInterrupted`: the caller removes what it
        made; the previous handlers are back after the block.
        """
        if threading.current_thread() is not threading.main_thread():
            yield
            return

        def abort(signum: int, frame: FrameType | None) -> None:
            name = signal.Signals(signum).name
            print(f"Received {name} during the set-up, before training: stopping (nothing to save)", flush=True)
            raise SetupInterrupted(name)

        previous = {signum: signal.signal(signum, abort) for signum in STOP_SIGNALS}
        try:
            yield
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)

    def _install_signal_handlers(self) -> dict[int, Any]:
        if threading.current_thread() is not threading.main_thread():
            return {}  # signal handlers can only be installed by the main thread
        return {signum: signal.signal(signum, self._on_signal) for signum in STOP_SIGNALS}

    def _restore_signal_handlers(self) -> None:
        for signum, previous in (getattr(self, "_previous_handlers", None) or {}).items():
            signal.signal(signum, previous)
        self._previous_handlers = {}

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        name = signal.Signals(signum).name
        first = self._stop_signal is None
        self._stop_signal = self._stop_signal or name
        if self._phase == "training" and first:
            self._stop_callback.requested = True
            print(
                f"Received {name}: stopping training where it resumes exactly (the next gradient step, env step or "
                "iteration start), "
                f"then saving the model and its replay buffer; {name} again stops at once (the resume is then not "
                "exact), SIGKILL stops without saving",
                flush=True,
            )
        elif self._phase == "training":
            print(f"Received {name} again: stopping training now", flush=True)
            self._stopped_at_once = True
            raise KeyboardInterrupt
        elif self._phase == "after save":
            print(f"Received {name}: stopping the final meta-test (the model is saved)", flush=True)
            raise KeyboardInterrupt
        else:
            print(f"Received {name}: finishing the save first", flush=True)

    def _model_path(self) -> str:
        return os.path.join(self.save_path, f"{self.env_name}.zip")

    def _save_after_failure(self, model: BaseAlgorithm, error: BaseException) -> None:
        """Save the model reached when training raised ``error`` (and its replay buffer if asked), and say where."""
        try:
            model.save(self._model_path())
            if self.save_replay_buffer and hasattr(model, "save_replay_buffer"):
                model.save_replay_buffer(os.path.join(self.save_path, "replay_buffer.pkl"))
        except Exception as save_error:  # report both; the training error is re-raised by the caller
            print(f"Training failed ({type(error).__name__}) and saving the model failed too: {save_error}", file=sys.stderr)
            return
        print(
            f"Training stopped by {type(error).__name__} at {model.num_timesteps} timesteps: the model reached so far is "
            f"saved to {self._model_path()} (continue with train.py -i {self._model_path()}); the error follows",
            file=sys.stderr,
            flush=True,
        )

    def save_trained_model(self, model: BaseAlgorithm) -> None:
        """
        rl_zoo3's save (model, replay buffer, normalisation), then :meth:`after_save` unless a signal stopped training.
        A run stopped by a signal also gets its replay buffer saved (what an exact resume needs), ``interrupted.json``
        and the exit status 128 + the signal; so does a run whose :meth:`after_save` a signal stopped.
        """
        self._phase = "saving"
        if not getattr(self, "_previous_handlers", None):
            self._previous_handlers = self._install_signal_handlers()
        stopped_in_training = self._stop_signal is not None
        stopped_in_save = False
        try:
            try:
                super().save_trained_model(model)
                buffer_path = None
                if stopped_in_training and getattr(model, "replay_buffer", None) is not None:
                    buffer_path = os.path.join(self.save_path, "replay_buffer.pkl")
                    if not self.save_replay_buffer:
                        print("Saving replay buffer (for the resume)")
                        model.save_replay_buffer(buffer_path)  # type: ignore[attr-defined]
            except OSError as error:  # e.g. no space left: one line, not the writer's chained tracebacks
                raise SystemExit(self._save_failed_message(error)) from None
            stopped_in_save = not stopped_in_training and self._stop_signal is not None
            if stopped_in_save:
                print(f"{self._stop_signal} came during the save: the final meta-test is skipped", flush=True)
            elif not stopped_in_training:
                self._phase = "after save"  # a signal now stops what follows the save
                try:
                    self.after_save(model)
                except KeyboardInterrupt:
                    print("Final meta-test interrupted: the model is saved, meta_test.* not written")
        finally:
            self._phase = "done"
            self._restore_signal_handlers()
        if self._stop_signal is not None:
            during = "training" if stopped_in_training else "final save" if stopped_in_save else "final meta-test"
            self._mark_interrupted(model, during, buffer_path if stopped_in_training else None)

    def _save_failed_message(self, error: OSError) -> str:
        """
        The one line for a final save that failed (no space left on the device, a file too large, ...): the file (the
        writers name it, :func:`~sb3_pearl.common.atomic.atomic_path`), that nothing older was overwritten, and the
        checkpoint to resume from if the run wrote one.
        """
        problem = str(error.strerror or error)
        if error.errno is not None and error.errno in errno.errorcode:
            problem += f" ({errno.errorcode[error.errno]})"
        checkpoints = glob.glob(os.path.join(self.save_path, "*_steps*.zip"))
        resume = "free space (or choose another -f) and train again"
        if checkpoints:
            latest = max(checkpoints, key=os.path.getmtime)
            resume = f"free space, then resume the run's last checkpoint: {self._resume_command(latest)}"
        return (
            f"{program_name()}: error: saving the trained model failed: {problem}; nothing older was overwritten (every "
            f"save writes a temporary file and renames it into place, and the temporary file was removed): {resume}"
        )

    def _resume_command(self, model_path: str) -> str:
        """``train.py``'s command line with ``--resume model_path`` instead of ``-i`` / ``--resume``."""
        args = [arg for arg in self.command if arg != "--resume-without-buffer"]
        for flag in ("--resume", "--trained-agent", "-i"):
            while flag in args:
                index = args.index(flag)
                del args[index : index + 2]
        return " ".join([program_name(), *map(shlex.quote, args), "--resume", shlex.quote(model_path)])

    def _mark_interrupted(self, model: BaseAlgorithm, during: str, buffer_path: str | None) -> None:
        """
        Write ``interrupted.json``, say what was saved and how to go on, and exit with status 128 + the signal.

        :param model: the saved model
        :param during: where the signal came: ``training``, ``final save`` (training complete, the final meta-test
            skipped) or ``final meta-test``
        :param buffer_path: the replay buffer saved for the resume, if any
        """
        assert self._stop_signal is not None
        in_training = during == "training"
        signum = int(signal.Signals[self._stop_signal])
        finished = model.num_timesteps >= self.n_timesteps and int(getattr(model, "_pending_gradient_steps", 0)) == 0
        exact = in_training and not self._stopped_at_once and (self._stop_callback.stopped or finished)
        resume = self._resume_command(self._model_path())
        record = {
            "signal": self._stop_signal,
            "during": during,
            "num_timesteps": int(model.num_timesteps),
            "n_timesteps": int(self.n_timesteps),
            "model": self._model_path(),
            "replay_buffer": buffer_path,
            "exact_resume": bool(exact),
            "resume": resume if in_training else None,
        }
        with atomic_write(os.path.join(self.save_path, INTERRUPTED_FILE), "w") as file:
            json.dump(record, file, indent=1)
        if in_training:
            how = "exactly" if exact else "approximately (stopped at once: not where an exact resume is possible)"
            pending = int(getattr(model, "_pending_gradient_steps", 0))
            trained = f", {int(getattr(model, '_n_updates', 0)):,} gradient steps trained"
            if pending > 0:
                trained += f" ({pending:,} of the current iteration's still to train, first thing on resume)"
            print(
                f"Stopped by {self._stop_signal} at {model.num_timesteps} of {self.n_timesteps} timesteps{trained}: the run "
                "is cut "
                f"(final meta-test skipped, {INTERRUPTED_FILE} written); the model is saved to {self._model_path()}"
                + (f" with its replay buffer {buffer_path}" if buffer_path else "")
                + f". It resumes {how} with: {resume}",
                flush=True,
            )
        else:
            print(
                f"Stopped by {self._stop_signal} during the {during}: training is complete and the model saved to "
                f"{self._model_path()}; meta_test.* not written ({INTERRUPTED_FILE} written)",
                flush=True,
            )
        raise SystemExit(128 + signum)

    def after_save(self, model: BaseAlgorithm) -> None:
        """What runs once the trained model is saved (the meta-test manager's final meta-test); a signal stops it."""


__all__ = [
    "INTERRUPTED_FILE",
    "InterruptibleExperimentManager",
    "SetupInterrupted",
    "SignalShieldedSubprocVecEnv",
    "StopOnSignalCallback",
    "StopRequested",
]
