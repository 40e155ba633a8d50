"""A callback event SB3 does not have: between two gradient steps of a meta-algorithm's ``train()``.

SB3 calls its callbacks once per env step (``on_step``) and around rollouts; an iteration of PEARL trains thousands of
gradient steps after its collection (25 minutes at the paper's size on a CPU core) with no event at all. PEARL's
``train()`` calls :func:`gradient_step_event` between two gradient steps, where a saved model resumes exactly; a
callback that has an ``on_gradient_step() -> bool`` method is told, and one that returns False stops training there
(a signal's stop, :class:`StopOnSignalCallback`, in ``train.py`` and in the reproduction harness's runs), or saves a
checkpoint (:class:`~sb3_pearl.evaluation.callbacks.ResumableCheckpointCallback`).
"""

from __future__ import annotations

from stable_baselines3.common.callbacks import BaseCallback, CallbackList


def gradient_step_event(callback: BaseCallback) -> bool:
    """
    Tell ``callback`` (each callback of a ``CallbackList``, nested ones too) that a gradient step was taken.

    :param callback: the callback(s) of the running ``learn()``
    :return: False if one of them asks to stop training
    """
    if isinstance(callback, CallbackList):
        results = [gradient_step_event(inner) for inner in callback.callbacks]  # every callback hears the event
        return all(results)
    handler = getattr(callback, "on_gradient_step", None)
    return True if handler is None else bool(handler())


class StopRequested(KeyboardInterrupt):
    """Raised at an iteration start once a stop was asked for: ``learn`` stops as after Ctrl-C (rl_zoo3's catches it)."""


class StopOnSignalCallback(BaseCallback):
    """
    Stops training, once :attr:`requested`, where the state is one a checkpoint holds, so the saved model resumes
    exactly: at the next rollout start (PEARL and MAML call it at an iteration start, before the iteration's draws;
    Fine-Tune and SB3's algorithms before each collection), or, for PEARL / PEARL+, at the next env step (the
    iteration is kept open, ``model._open_iteration``, and finished by the resumed run) or the next gradient step (the
    iteration's steps still to train are saved with the model and trained first by the resumed run). A stop therefore
    lands within one gradient step or env step at any budget: seconds, within every scheduler's grace period.
    """

    def __init__(self) -> None:
        super().__init__()
        self.requested = False
        self.stopped = False  # training stopped here (False: it ended on its own or was stopped at once)
        self.training = False  # inside learn(): a request is heard (a signal handler stops at once otherwise)

    def _on_training_start(self) -> None:
        self.training = True

    def _on_training_end(self) -> None:
        self.training = False

    def _on_step(self) -> bool:
        if self.requested and hasattr(self.model, "_open_iteration"):
            self.stopped = True
            return False
        return True

    def on_gradient_step(self) -> bool:
        """Between two of PEARL's gradient steps (:func:`~sb3_pearl.common.callbacks.gradient_step_event`): stop there."""
        if self.requested:
            self.stopped = True
            return False
        return True

    def _on_rollout_start(self) -> None:
        if self.requested:
            self.stopped = True
            raise StopRequested
