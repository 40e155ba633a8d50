"""Interruptions of ``train.py``: SIGTERM and exceptions save the model, as Ctrl-C does in rl_zoo3 (docs/cli.md).

:class:`InterruptibleExperimentManager` is rl_zoo3's ``ExperimentManager`` with:

- SIGTERM (``kill``, a batch scheduler's time limit) stopping training like Ctrl-C: the model is saved, what follows
  the save is skipped and ``train.py`` exits with status 143 (128 + SIGTERM);
- an exception during training saving the model reached so far into the run folder, saying where, re-raised;
- ``--resume`` (:attr:`resume`): training continues a checkpoint's run with its counters, up to ``n_timesteps``.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from types import FrameType
from typing import Any

from rl_zoo3.exp_manager import ExperimentManager
from stable_baselines3.common.base_class import BaseAlgorithm


class InterruptibleExperimentManager(ExperimentManager):
    """rl_zoo3's ``ExperimentManager`` whose training survives SIGTERM and exceptions, model saved (module docstring)."""

    resume: bool = False  # --resume: continue the checkpoint's run (counters kept) up to n_timesteps in all

    def learn(self, model: BaseAlgorithm) -> None:
        """
        rl_zoo3's ``learn`` (Ctrl-C stops training and the model is saved), plus:

        - SIGTERM (``kill``, a batch scheduler's time limit) stops training the same way; the model is saved,
          the final meta-test is skipped and ``train.py`` exits with status 143 (128 + SIGTERM);
        - an exception during training saves the model reached so far into the run folder, says where, and is
          re-raised.

        :param model: the model to train
        """
        self._stop_signal: str | None = None
        self._sigterm_raises = True
        self._previous_sigterm_handler = self._install_sigterm_handler()
        try:
            if self.resume and self.continue_training:
                self._learn_resumed(model)
            else:
                super().learn(model)
        except Exception as error:
            self._restore_sigterm_handler()
            self._save_after_failure(model, error)
            raise
        self._sigterm_raises = False  # from here on, a SIGTERM no longer interrupts the save

    def _learn_resumed(self, model: BaseAlgorithm) -> None:
        """
        ``train.py --resume``: continue the checkpoint's run up to ``n_timesteps`` in all (its counters kept,
        ``reset_num_timesteps=False``), as rl_zoo3's ``learn`` otherwise (Ctrl-C stops and saves).
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
        try:
            if remaining > 0:
                model.learn(remaining, reset_num_timesteps=False, **kwargs)
        except KeyboardInterrupt:
            pass  # as rl_zoo3: the model is saved by save_trained_model
        finally:
            if self.callbacks:
                self.callbacks[0].on_training_end()
            try:
                assert model.env is not None
                model.env.close()
            except EOFError:
                pass

    def _install_sigterm_handler(self) -> Any:
        if threading.current_thread() is not threading.main_thread():
            return None  # signal handlers can only be installed by the main thread
        return signal.signal(signal.SIGTERM, self._on_sigterm)

    def _restore_sigterm_handler(self) -> None:
        previous = getattr(self, "_previous_sigterm_handler", None)
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
            self._previous_sigterm_handler = None

    def _on_sigterm(self, signum: int, frame: FrameType | None) -> None:
        first = self._stop_signal is None
        self._stop_signal = "SIGTERM"
        if first and self._sigterm_raises:
            print("Received SIGTERM: stopping training and saving the model (SIGKILL stops without saving)", flush=True)
            raise KeyboardInterrupt  # rl_zoo3's learn() / the meta-test stop as after Ctrl-C
        print("Received SIGTERM: finishing the save first", flush=True)

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
        """rl_zoo3's save (model, replay buffer), then :meth:`after_save` unless training was stopped by SIGTERM."""
        self._sigterm_raises = False
        if getattr(self, "_previous_sigterm_handler", None) is None:
            self._stop_signal = getattr(self, "_stop_signal", None)
            self._previous_sigterm_handler = self._install_sigterm_handler()
        try:
            super().save_trained_model(model)
            if self._stop_signal is None:
                self._sigterm_raises = True  # a SIGTERM now stops what follows the save, as Ctrl-C does
                try:
                    self.after_save(model)
                except KeyboardInterrupt:
                    print("Meta-test interrupted: the model is saved, meta_test.* not written")
        finally:
            self._restore_sigterm_handler()
        if self._stop_signal is not None:
            print(
                f"Stopped by {self._stop_signal} at {model.num_timesteps} timesteps: the model is saved to "
                f"{self._model_path()} (final meta-test skipped; continue with train.py -i {self._model_path()})",
                flush=True,
            )
            raise SystemExit(128 + signal.SIGTERM)

    def after_save(self, model: BaseAlgorithm) -> None:
        """What runs once the trained model is saved (the meta-test manager's final meta-test); Ctrl-C / SIGTERM stop it."""


__all__ = ["InterruptibleExperimentManager"]
