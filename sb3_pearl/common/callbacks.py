"""A callback event SB3 does not have: between two gradient steps of a meta-algorithm's ``train()``.

SB3 calls its callbacks once per env step (``on_step``) and around rollouts; an iteration of PEARL trains thousands of
gradient steps after its collection (25 minutes at the paper's size on a CPU core) with no event at all. PEARL's
``train()`` calls :func:`gradient_step_event` between two gradient steps, where a saved model resumes exactly; a
callback that has an ``on_gradient_step() -> bool`` method is told, and one that returns False stops training there
(a signal's stop, :class:`~sb3_pearl.zoo.interruptions.StopOnSignalCallback`), or saves a checkpoint
(:class:`~sb3_pearl.evaluation.callbacks.ResumableCheckpointCallback`).
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
