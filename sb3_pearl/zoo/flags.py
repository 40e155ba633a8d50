"""``train.py``'s own flags, on top of rl_zoo3's: ``--budget PRESET``, ``--resume CHECKPOINT`` and
``--checkpoint-minutes M``, plus the checks of
``--env`` and ``-n`` before rl_zoo3 parses anything (docs/cli.md)."""

from __future__ import annotations

import argparse
import importlib
import math
import os
from typing import NamedTuple

from huggingface_sb3 import EnvironmentName

from sb3_pearl.evaluation.callbacks import checkpoint_replay_buffer_path
from sb3_pearl.zoo import usage
from sb3_pearl.zoo.budget import budget_hyperparams
from sb3_pearl.zoo.usage import UsageError, check_env_id

PROJECT_FLAGS_HELP = """
sb3-pearl flags (docs/cli.md):
  --budget PRESET       train with the env's entry of a budget preset instead of zoo_hyperparams/<algo>.yml:
                        cpu (PEARL / PEARL+ runs of 5-44 min on one core), smoke or paper
                        (sb3_pearl/config/presets/; -n and -params still override it)
  --resume CHECKPOINT   continue a --save-freq checkpoint (or a run's model) up to n_timesteps in all, with its
                        replay buffer and RNG states
  --resume-without-buffer
                        let --resume go on when the checkpoint has no replay buffer beside it, or an empty or
                        truncated one (the run then restarts from an empty buffer and differs from an
                        uninterrupted one)
  --checkpoint-minutes M
                        save a resumable checkpoint (checkpoint_<steps>_steps*.zip and its replay buffer, atomic,
                        the previous one deleted) every M minutes of training, at the next gradient step or
                        iteration start (default 10; 0: off): a kill loses at most M minutes"""

DEFAULT_CHECKPOINT_MINUTES = 10.0
OWN_VALUE_FLAGS = ("--resume", "--budget", "--checkpoint-minutes")  # the project's flags that take a value


def split_own_flags(args: list[str]) -> list[str]:
    """
    The command line with the project's own ``--flag=value`` written ``--flag value``, as rl_zoo3's argparse takes
    both forms of its flags.

    :param args: the command line
    :return: a new list
    """
    split: list[str] = []
    for arg in args:
        name, equals, value = arg.partition("=")
        split += [name, value] if equals and name in OWN_VALUE_FLAGS else [arg]
    return split


class ProjectFlags(NamedTuple):
    """The command line split: what rl_zoo3 parses, and the project's settings for the experiment manager."""

    zoo_args: list[str]  # rl_zoo3's arguments (``--resume X`` became ``--trained-agent X``, ``--budget P`` removed)
    command: list[str]  # the command line as given (the resume command of a cut run is made from it)
    resume: bool  # --resume: -i continues the checkpoint's run (counters kept) up to n_timesteps in all
    budget: str | None  # --budget PRESET: the family's entry of that budget preset replaces the YAML entry
    checkpoint_minutes: float = DEFAULT_CHECKPOINT_MINUTES  # --checkpoint-minutes M: periodic checkpoints (0: off)
    resume_without_buffer: bool = False  # --resume-without-buffer: a missing or unreadable buffer leaves it empty


def parse_project_flags(args: list[str]) -> ProjectFlags:
    """
    Handle the project's own flags (``--resume``, ``--budget``) and check ``--env`` and ``-n``.

    :param args: the command line (not changed)
    :return: rl_zoo3's arguments and the project's settings
    """
    command = split_own_flags(args)
    args = list(command)
    resume, budget = False, None
    args = usage.check_n_timesteps(args)
    usage.check_seed(args)
    usage.check_log_folder(args)
    without_buffer = "--resume-without-buffer" in args
    if without_buffer:
        args.remove("--resume-without-buffer")
    if "--resume" in args:
        index = args.index("--resume")
        if index + 1 >= len(args) or not os.path.isfile(args[index + 1]) or not args[index + 1].endswith(".zip"):
            raise UsageError(
                "--resume takes the checkpoint's model zip, e.g. --resume logs/pearl/Env_1/rl_model_5000_steps.zip"
            )
        if any(arg.partition("=")[0] in ("-i", "--trained-agent") for arg in args):
            raise UsageError("--resume and -i/--trained-agent exclude each other (--resume is -i that keeps the counters)")
        args[index] = "--trained-agent"
        resume = True
    elif without_buffer:
        raise UsageError("--resume-without-buffer goes with --resume CHECKPOINT")
    peek = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    peek.add_argument("--env", default=None)
    peek.add_argument("--algo", default=None)
    peek.add_argument("--gym-packages", nargs="+", default=[])
    peek.add_argument("--budget", default=None)
    known, _ = peek.parse_known_args(args)
    for module in known.gym_packages:
        importlib.import_module(module)
    if known.env is not None:
        check_env_id(known.env)
    if "--budget" in args:
        index = args.index("--budget")
        if known.budget is None or known.budget.startswith("-"):
            raise UsageError("--budget takes a budget preset name: smoke, cpu or paper")
        del args[index : index + 2]
        if known.algo is not None and known.env is not None:
            budget_hyperparams(known.budget, known.env, known.algo)  # an unknown preset or entry: the error now
        budget = known.budget
    if resume and not without_buffer:
        check_resume_buffer(args[args.index("--trained-agent") + 1], known.algo, known.env)
    checkpoint_minutes = DEFAULT_CHECKPOINT_MINUTES
    if "--checkpoint-minutes" in args:
        index = args.index("--checkpoint-minutes")
        value = args[index + 1] if index + 1 < len(args) else ""
        try:
            checkpoint_minutes = float(value)
        except ValueError:
            checkpoint_minutes = math.nan
        if not (math.isfinite(checkpoint_minutes) and checkpoint_minutes >= 0):
            raise UsageError(f"--checkpoint-minutes takes minutes >= 0 (0: no periodic checkpoint), got {value!r}")
        del args[index : index + 2]
    return ProjectFlags(args, command, resume, budget, checkpoint_minutes, without_buffer)


def resume_buffer_path(checkpoint: str, env_id: str | None) -> str | None:
    """
    The replay buffer that belongs to a model zip ``--resume`` is given: a periodic checkpoint's own
    (:func:`~sb3_pearl.evaluation.callbacks.checkpoint_replay_buffer_path`), or for the run's model ``<env_id>.zip``
    (saved at the end or at a stop) the run folder's ``replay_buffer.pkl``. Any other zip (``best_model.zip``) has none:
    the folder's buffer is of another step.

    :param checkpoint: the model zip
    :param env_id: the ``--env`` value
    :return: the buffer's path (which may not exist), or None
    """
    own = checkpoint_replay_buffer_path(checkpoint)
    if own is not None:
        return own
    if env_id is not None and os.path.basename(checkpoint) == f"{EnvironmentName(env_id)}.zip":  # the run's file name
        return os.path.join(os.path.dirname(checkpoint), "replay_buffer.pkl")
    return None


def check_resume_buffer(checkpoint: str, algo: str | None, env_id: str | None = None) -> None:
    """
    Refuse ``--resume`` of an off-policy model without its replay buffer (:func:`resume_buffer_path`: the run would
    restart from an empty buffer, or another step's, and no longer continue the interrupted one), unless
    ``--resume-without-buffer`` is given.

    :param checkpoint: the model zip
    :param algo: the ``--algo`` value
    :param env_id: the ``--env`` value
    """
    from sb3_pearl.zoo.rl_zoo3_coupling import ALGOS

    algo_class = ALGOS.get(algo or "")
    if algo_class is None or not hasattr(algo_class, "load_replay_buffer"):
        return  # on-policy (MAML): nothing to resume but the model
    path = resume_buffer_path(checkpoint, env_id)
    if path is None:
        raise UsageError(
            f"--resume {checkpoint}: no replay buffer belongs to this model (a checkpoint's is "
            "<prefix>_replay_buffer_<steps>_steps.pkl, the run's <EnvId>.zip has replay_buffer.pkl; the folder's "
            "replay_buffer.pkl is of another step), so the run would differ from the uninterrupted one: resume a "
            "checkpoint or the run's model, or add --resume-without-buffer to go on from an empty buffer"
        )
    if not os.path.isfile(path):
        raise UsageError(
            f"--resume {checkpoint}: no replay buffer beside it ({path}), so the run would restart from an empty buffer "
            "and differ from the uninterrupted one; add --resume-without-buffer to go on anyway"
        )


__all__ = [
    "DEFAULT_CHECKPOINT_MINUTES",
    "PROJECT_FLAGS_HELP",
    "ProjectFlags",
    "check_resume_buffer",
    "parse_project_flags",
    "resume_buffer_path",
    "split_own_flags",
]
