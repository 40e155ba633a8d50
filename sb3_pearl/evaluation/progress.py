"""What a run costs, said before and measured during it; progress bars that count gradient steps and meta-test trajectories.

- :class:`TrainingPlan`: what ``learn()`` will do: env steps, gradient steps, and how many env steps only
  collect data before the first gradient step. Algorithms that know it offer ``training_plan(total_timesteps)``
  (PEARL / PEARL+, Fine-Tune).
- :class:`TrainingProgressCallback`: SB3's ``ProgressBarCallback`` made truthful for meta-RL. At the start it
  announces the plan (and the collection-only phase); once the first gradient steps are timed (20 of them, or 30 s of
  them: within the first minute of training at any budget) it prints the measured cost of an env step and of a
  gradient step and the ETA of the whole run, and says so when that is more than a day on a CPU; without the bar a
  line every 30 s of gradient steps keeps saying where the run is.
  Its progress bar (optional) weighs env steps and gradient steps by their measured cost, so it reaches 100 %
  after the last gradient step, and shows the ETA of the same cost model. PEARL's ``train()`` tells it about
  every gradient step (``gradient_step_callback``), so the bar also moves during the gradient steps.
- :class:`ProgressBar`: one rich progress bar; bars open at the same time share one live display (rich allows
  one), e.g. an in-training meta-test under the training bar. :func:`~sb3_pearl.evaluation.meta_test.meta_test`
  uses it with ``progress_bar=True``.
"""

from __future__ import annotations

import math
import time
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, Progress, TaskID, TaskProgressColumn, TextColumn, TimeElapsedColumn
from stable_baselines3.common.callbacks import ProgressBarCallback

from sb3_pearl.common.type_aliases import TrainingPlan

DAY_S = 86_400.0
COLLECTION_LINE_S = 5.0  # without -P: a progress line every 5 s of the collection before the first gradient step
TRAINING_LINE_S = 30.0  # without -P: a progress line every 30 s of gradient steps
FIRST_TIMED_UPDATES = 20  # the cost per gradient step (and the ETA) is reported once this many are timed ...
FIRST_TIMED_S = 30.0  # ... or once gradient steps have run this long, whichever comes first
NON_TERMINAL_WIDTH = 140


def format_duration(seconds: float) -> str:
    """``"42 s"``, ``"3.5 min"``, ``"2.1 h"``, ``"2 d 11 h"``."""
    if not math.isfinite(seconds):
        return "?"
    if seconds < 10:
        return f"{seconds:.1f} s"
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.1f} min"
    if seconds < DAY_S:
        return f"{seconds / 3600:.1f} h"
    days, hours = divmod(round(seconds / 3600), 24)
    return f"{days} d {hours} h" if hours else f"{days} d"


def _per_unit(seconds: float) -> str:
    return f"{seconds * 1000:.2f} ms" if seconds < 1 else f"{seconds:.2f} s"


class ProgressBar:
    """
    One rich progress bar: description, bar, percentage, elapsed time, ETA and a counts text.

    Bars open at the same time share one live display, the first one's (rich shows one at a time); the first bar
    closed stops it, later ones are removed from it. The ETA is set by the caller (:meth:`update`) or, with
    :meth:`advance`, extrapolated from the elapsed time (units of equal cost, e.g. meta-test trajectories).

    :param description: text before the bar (e.g. with a Ctrl-C hint)
    :param total: units to do (None: unknown)
    :param unit: name of the unit in the counts text (``advance`` only)
    """

    _shared: Progress | None = None

    def __init__(self, description: str, total: float | None, unit: str = "") -> None:
        self.unit = unit
        self.total = total
        self.completed = 0.0
        self.start = time.monotonic()
        self.owner = ProgressBar._shared is None
        if self.owner:
            console = Console()
            if not console.is_terminal:  # a log file: room for the whole line (rich assumes 80 columns)
                console.width = max(console.width, NON_TERMINAL_WIDTH)
            ProgressBar._shared = Progress(
                TextColumn("{task.description}"),
                BarColumn(bar_width=30),
                TaskProgressColumn(),
                TimeElapsedColumn(),
                TextColumn("ETA {task.fields[eta]}"),
                TextColumn("{task.fields[counts]}"),
                console=console,
            )
            ProgressBar._shared.start()
        assert ProgressBar._shared is not None
        self.progress: Progress = ProgressBar._shared
        self.task: TaskID = self.progress.add_task(description, total=total, eta="?", counts="")

    def update(self, **fields: Any) -> None:
        """
        Set ``completed``, ``total``, ``description``, ``eta`` (seconds or text) or ``counts`` (text).

        :param fields: the values to set
        """
        if isinstance(fields.get("eta"), (int, float)):
            fields["eta"] = format_duration(float(fields["eta"]))
        self.progress.update(self.task, **fields)

    def advance(self, units: float = 1.0) -> None:
        """
        ``units`` more done; the ETA is the elapsed time per unit times the units left.

        :param units: units just done
        """
        self.completed += units
        elapsed = time.monotonic() - self.start
        fields: dict[str, Any] = {"completed": self.completed}
        if self.total is not None:
            fields["counts"] = f"{self.completed:.0f}/{self.total:.0f} {self.unit}".rstrip()
            fields["eta"] = elapsed / self.completed * max(self.total - self.completed, 0.0)
        self.update(**fields)

    def close(self) -> None:
        """Stop the live display (the first bar: its last state stays on the screen) or leave it (the others)."""
        if self.owner:
            self.progress.stop()
            ProgressBar._shared = None
        else:
            self.progress.remove_task(self.task)

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


class TrainingProgressCallback(ProgressBarCallback):
    """
    The cost of a training run, announced and measured; optionally a progress bar that counts the gradient steps.

    Time spent between ``on_rollout_start`` and ``on_rollout_end`` is collection, time between ``on_rollout_end``
    and the next ``on_rollout_start`` (or the end) is gradient steps, counted with the model's ``_n_updates``.
    With the model's :class:`TrainingPlan` (``model.training_plan(total_timesteps)``) the ETA is
    ``env steps left x seconds per env step + gradient steps left x seconds per gradient step``; without one it
    extrapolates the elapsed time per env step. Printed (``verbose >= 1``): the plan at the start, then once the
    first gradient steps are timed (PEARL's ``train()`` reports each one; other algorithms at the next rollout start
    after the first iteration), the measured costs and the ETA, and ``slow_hint`` when the model runs on a CPU and
    the ETA exceeds ``slow_after_s``; without the bar, a line every ``TRAINING_LINE_S`` seconds of gradient steps.

    :param progress_bar: show the progress bar
    :param slow_hint: what to do instead of a run longer than ``slow_after_s`` on a CPU (e.g. a smaller budget)
    :param slow_after_s: the ETA (seconds) above which ``slow_hint`` is printed
    :param verbose: 0 silent, 1 the plan and the cost lines
    """

    def __init__(
        self, progress_bar: bool = True, slow_hint: str | None = None, slow_after_s: float = DAY_S, verbose: int = 1
    ) -> None:
        super().__init__()
        self.verbose = verbose
        self.progress_bar = progress_bar
        self.slow_hint = slow_hint
        self.slow_after_s = slow_after_s
        self.plan: TrainingPlan | None = None
        self.bar: ProgressBar | None = None
        self.reported = self.ended = False

    # -- measurements --------------------------------------------------------------------------------------------
    def _on_training_start(self) -> None:
        total = int(self.locals["total_timesteps"])
        planner = getattr(self.model, "training_plan", None)
        self.plan = planner(total) if callable(planner) else None
        self.total_env_steps = max(total - self.model.num_timesteps, 0)
        self.env_start = self.model.num_timesteps
        self.updates_start = int(getattr(self.model, "_n_updates", 0))
        self.t_collect = self.t_update = 0.0
        self.n_rollouts = 0
        now = time.monotonic()
        self.t_start = self.phase_start = self.last_draw = self.last_line = self.last_training_line = now
        self.collecting = self.ended = False
        if hasattr(self.model, "gradient_step_callback"):
            self.model.gradient_step_callback = self._on_gradient_step
        if self.verbose >= 1:
            self._announce()
        if self.progress_bar:
            self.bar = ProgressBar(f"{type(self.model).__name__}: collecting", None)
            self._draw(force=True)

    def _on_rollout_start(self) -> None:
        now = time.monotonic()
        if not self.collecting:
            self.t_update += now - self.phase_start
        self.phase_start, self.collecting = now, True
        self.n_rollouts += 1
        if not self.reported and self._first_iteration_done():
            self.reported = True
            if self.verbose >= 1:
                self._report()

    def _on_rollout_end(self) -> None:
        now = time.monotonic()
        if self.collecting:
            self.t_collect += now - self.phase_start
        self.phase_start, self.collecting = now, False

    def _on_step(self) -> bool:
        self._draw()
        if self.bar is None and self.verbose >= 1 and self.collecting:
            self._collection_line()
        return True

    def _collection_line(self) -> None:
        """Without the bar: a line every ``COLLECTION_LINE_S`` seconds of collection before the first gradient step."""
        now = time.monotonic()
        if now - self.last_line < COLLECTION_LINE_S or self.updates_done() > 0:
            return
        self.last_line = now
        env = self.env_steps_done()
        initial = self.plan.initial_steps if self.plan is not None and self.plan.initial_steps > 0 else self.total_env_steps
        share = f" ({100 * env / initial:.0f}%)" if initial > 0 else ""
        print(
            f"Collecting: {env:,}/{initial:,} env steps{share} before the first gradient step, "
            f"{format_duration(now - self.t_start)} so far",
            flush=True,
        )

    def _on_gradient_step(self) -> None:
        """Called by PEARL's ``train()`` after every gradient step (``_n_updates`` counts it already)."""
        self._draw()
        if not self.reported and self._first_updates_timed():
            self.reported = True
            if self.verbose >= 1:
                self._report()
        if self.bar is None and self.verbose >= 1 and time.monotonic() - self.last_training_line >= TRAINING_LINE_S:
            self._training_line()

    def _first_updates_timed(self) -> bool:
        """Enough gradient steps timed for the cost per step: FIRST_TIMED_UPDATES of them, or FIRST_TIMED_S seconds."""
        updates = self.updates_done()
        return updates >= FIRST_TIMED_UPDATES or (updates > 0 and self._times()[1] >= FIRST_TIMED_S)

    def _training_line(self) -> None:
        """Without the bar: where the run is during gradient steps (a line every ``TRAINING_LINE_S`` seconds)."""
        self.last_training_line = time.monotonic()
        updates, eta = self.updates_done(), self.eta()
        total = f"/{self.plan.gradient_steps:,}" if self.plan is not None else ""
        _, per_update = self.costs()
        cost = f" ({_per_unit(per_update)} per update)" if per_update is not None else ""
        print(
            f"Training: {updates:,}{total} gradient steps{cost}, {self.env_steps_done():,}/{self.total_env_steps:,} env "
            f"steps, ETA {format_duration(eta) if eta is not None else '?'}; Ctrl-C saves the model",
            flush=True,
        )

    def _on_training_end(self) -> None:
        if self.ended:  # rl_zoo3's learn() ends callback 0 a second time
            return
        self.ended = True
        if hasattr(self.model, "gradient_step_callback"):
            self.model.gradient_step_callback = None
        pending = int(getattr(self.model, "_pending_gradient_steps", 0))  # an iteration's gradient steps cut short
        stopped = self.env_steps_done() < self.total_env_steps or pending > 0
        if (
            self.verbose >= 1
            and stopped
            and self.plan is not None
            and self.plan.gradient_steps > 0
            and self.updates_done() == 0
        ):
            print(f"Stopped at {self.model.num_timesteps:,} env steps, before the first gradient step: the model is untrained")
        if self.bar is not None:
            self._draw(force=True, phase="stopped" if stopped else "done")
            self.bar.close()
            self.bar = None

    def env_steps_done(self) -> int:
        """Env steps collected since the start of this ``learn()``."""
        return self.model.num_timesteps - self.env_start

    def updates_done(self) -> int:
        """Gradient steps taken since the start of this ``learn()``."""
        return int(getattr(self.model, "_n_updates", 0)) - self.updates_start

    def _first_iteration_done(self) -> bool:
        if self.plan is None:
            return self.n_rollouts >= 2  # one whole iteration (collection and update) is behind
        return self.plan.gradient_steps > 0 and self.updates_done() >= min(self.plan.first_updates, self.plan.gradient_steps)

    def _times(self) -> tuple[float, float]:
        """Seconds of collection and of gradient steps so far, the current phase included."""
        running = time.monotonic() - self.phase_start
        return self.t_collect + (running if self.collecting else 0.0), self.t_update + (0.0 if self.collecting else running)

    def costs(self) -> tuple[float | None, float | None]:
        """Measured seconds per env step and per gradient step (None: not measured yet)."""
        t_collect, t_update = self._times()
        env, updates = self.env_steps_done(), self.updates_done()
        return (t_collect / env if env > 0 else None), (t_update / updates if updates > 0 else None)

    def eta(self) -> float | None:
        """Seconds left (None: not known yet)."""
        env_left = max(self.total_env_steps - self.env_steps_done(), 0)
        if self.plan is None:
            done = self.env_steps_done()
            return (time.monotonic() - self.t_start) / done * env_left if done > 0 and self.n_rollouts >= 2 else None
        per_step, per_update = self.costs()
        updates_left = max(self.plan.gradient_steps - self.updates_done(), 0)
        if per_step is None or (per_update is None and updates_left > 0):
            return None
        return env_left * per_step + updates_left * (per_update or 0.0)

    # -- output --------------------------------------------------------------------------------------------------
    def _announce(self) -> None:
        name = type(self.model).__name__
        if self.plan is None:
            print(f"{name}: {self.total_env_steps:,} env steps; the ETA follows the first iteration", flush=True)
            return
        line = f"{name}: {self.plan.env_steps:,} env steps and {self.plan.gradient_steps:,} gradient steps."
        if self.plan.initial_steps > 0:
            line += (
                f" Initial collection: the first {self.plan.initial_steps:,} env steps only collect data"
                f"{f' ({self.plan.note})' if self.plan.note else ''}, a model saved before then is untrained."
            )
        if self.plan.gradient_steps == 0:
            line += " The run ends before the first gradient step: the model stays untrained."
        print(line + " Cost per gradient step and ETA after the first gradient steps; Ctrl-C saves the model.", flush=True)

    def _report(self) -> None:
        t_collect, t_update = self._times()
        env, updates = self.env_steps_done(), self.updates_done()
        eta = self.eta()
        device = getattr(getattr(self.model, "device", None), "type", "cpu")
        whole = self.plan is not None and updates >= self.plan.first_updates
        line = f"{'First iteration' if whole else 'So far'}: {env:,} env steps in {format_duration(t_collect)}"
        if env > 0:
            line += f" ({_per_unit(t_collect / env)} per step)"
        if self.plan is not None and updates > 0:
            line += f", {updates:,} gradient steps in {format_duration(t_update)} ({_per_unit(t_update / updates)} per update)"
        print(line + ".", flush=True)
        if eta is None:
            return
        env_left = max(self.total_env_steps - env, 0)
        left = f"{env_left:,} env steps"
        if self.plan is not None:
            left += f" and {max(self.plan.gradient_steps - updates, 0):,} gradient steps"
        print(f"ETA of the whole run: {format_duration(eta)} on {device} ({left} to go).", flush=True)
        if device == "cpu" and eta > self.slow_after_s:
            hint = f" {self.slow_hint}" if self.slow_hint else ""
            limit = "a day" if self.slow_after_s == DAY_S else format_duration(self.slow_after_s)
            print(f"This run takes more than {limit} on a CPU.{hint}", flush=True)

    def _draw(self, force: bool = False, phase: str | None = None) -> None:
        if self.bar is None:
            return
        now = time.monotonic()
        if not force and now - self.last_draw < 0.2:
            return
        self.last_draw = now
        env, updates = self.env_steps_done(), self.updates_done()
        per_step, per_update = self.costs()
        eta = self.eta()
        counts = f"{env:,}/{self.total_env_steps:,} env steps"
        if self.plan is not None:
            counts += f", {updates:,}/{self.plan.gradient_steps:,} gradient steps"
        if self.plan is not None and per_step is not None and eta is not None:
            done = env * per_step + updates * (per_update or 0.0)  # seconds of work, by the measured costs
            completed, total = done, done + eta
        else:  # env steps only, until a gradient step has been timed
            completed, total = float(env), float(max(self.total_env_steps, 1))
        if phase is None:
            phase = "collecting" if self.collecting else "gradient steps"
            if self.plan is not None and updates == 0 and self.plan.initial_steps > 0:
                phase = "initial collection"
        self.bar.update(
            completed=completed,
            total=total,
            eta="after the first gradient steps" if eta is None else eta,
            counts=counts,
            description=f"{type(self.model).__name__}: {phase}",
        )


__all__ = ["COLLECTION_LINE_S", "DAY_S", "ProgressBar", "TrainingPlan", "TrainingProgressCallback", "format_duration"]
