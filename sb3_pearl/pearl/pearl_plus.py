"""PEARL+ : PEARL with the paper's prior-regularisation term and prior critic.

The paper: L. Wen, S. Zhang, H. E. Tseng, B. Singh, D. Filev, H. Peng, "Improved Robustness and Safety for
Pre-Adaptation of Meta Reinforcement Learning with Prior Regularization", arXiv:2108.08448.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar, TypeVar

import torch as th
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback

from sb3_pearl.common.checks import check_arch, check_int, check_real
from sb3_pearl.common.meta_algorithm import forwards_arguments_to
from sb3_pearl.common.networks import LatentCritic
from sb3_pearl.common.persistence import saved_arguments
from sb3_pearl.common.type_aliases import PEARLLosses
from sb3_pearl.pearl.losses import LossSettings
from sb3_pearl.pearl.pearl import PEARL
from sb3_pearl.pearl.policies import PRIOR_CRITIC_MODES, PEARLPolicy, check_prior_critic

SelfPEARLPlus = TypeVar("SelfPEARLPlus", bound="PEARLPlus")

PRIOR_DATA_MODES = ("all", "prior")
PRIOR_TARGETS = ("prior", "main", "mc")


def check_pearl_plus_arguments(arguments: Mapping[str, Any]) -> None:
    """
    Raise a ValueError for the first prior-term argument of :class:`PEARLPlus` out of its range (see its docstring).

    Called at the top of ``PEARLPlus.__init__`` with its bound arguments (``locals()``), and by ``load`` on a loaded
    model's settings.

    :param arguments: ``PEARLPlus.__init__``'s arguments by name, defaults included
    """
    prior_coef, prior_critic = arguments["prior_coef"], arguments["prior_critic"]
    prior_data, prior_critic_input = arguments["prior_data"], arguments["prior_critic_input"]
    prior_target, prior_conservative_weight = arguments["prior_target"], arguments["prior_conservative_weight"]
    prior_return_steps = arguments["prior_return_steps"]
    check_real("prior_coef", prior_coef, 0.0, hint="the paper's alpha, default 0.1; 0 gives PEARL")
    check_arch("prior_critic_arch", arguments["prior_critic_arch"])
    check_int("prior_n_critics", arguments["prior_n_critics"], 1, hint="Q networks of the prior critic")
    # The policy's checks, before anything is built; a PEARL+ model has a prior term ("none" is PEARL's).
    check_prior_critic(prior_critic, prior_critic_input, modes=tuple(mode for mode in PRIOR_CRITIC_MODES if mode != "none"))
    if prior_data not in PRIOR_DATA_MODES:
        raise ValueError(
            f"unknown prior_data {prior_data!r}: expected one of {PRIOR_DATA_MODES} (the replay rows the prior terms "
            "use: all of them, as in the paper, or only those collected with z from the prior)"
        )
    if prior_target not in PRIOR_TARGETS:
        raise ValueError(
            f"unknown prior_target {prior_target!r}: expected one of {PRIOR_TARGETS} (the prior critic's own target "
            "network, as in the paper, or the critic's target network at z0)"
        )
    check_real("prior_conservative_weight", prior_conservative_weight, 0.0, hint="0 turns the CQL penalty off")
    check_int("prior_return_steps", prior_return_steps, 0, hint="n-step returns with prior_target='mc'; 0: to the end")
    if prior_return_steps > 0 and prior_target != "mc":
        raise ValueError(
            f"prior_return_steps={prior_return_steps} sets the horizon of Monte-Carlo targets: use it with "
            f"prior_target='mc' (got prior_target={prior_target!r})"
        )
    if prior_critic == "shared" and (
        prior_critic_input != "state_z0" or prior_target != "prior" or prior_conservative_weight > 0
    ):
        raise ValueError(
            "prior_critic_input, prior_target and prior_conservative_weight configure the separate prior critic: "
            "prior_critic='shared' has none (use prior_critic='separate')"
        )


def _with_prior_terms(values: dict[str, th.Tensor], losses: PEARLLosses, kl_key: str) -> dict[str, th.Tensor]:
    """
    PEARL's losses of a step by name, with PEARL+'s two prior terms in the order of the total loss: the prior critic's
    after the KL (named ``kl_key``), the actor's after the actor's.
    """
    items = list(values.items())
    for after, name in ((kl_key, "prior_critic_loss"), ("actor_loss", "prior_actor_loss")):
        at = [key for key, _ in items].index(after) + 1
        items.insert(at, (name, getattr(losses, name)))
    return dict(items)


@forwards_arguments_to(PEARL)
class PEARLPlus(PEARL):
    """
    PEARL+ : PEARL with a prior-regularisation term (Algorithm 1 of the paper).

    The actor minimises ``L_actor(b, z.detach()) + prior_coef * L_actor(b, z0)`` with
    ``z ~ q(z | c)`` and ``z0 ~ N(0, I)`` (one z0 per task, held across the task's rows), so that the
    policy acts well *before* it has seen any data of a new task. The prior term is scored by an
    extra prior critic Q~(s, a, z0) with its own soft Bellman loss (``prior_critic="separate"``) or,
    for the ablation PEARL+ (w/o), by the critic Q(s, a, z0) (``prior_critic="shared"``). The
    encoder is trained by the critic loss and the KL only.

    ``prior_coef=0`` is PEARL exactly: no prior critic is built or trained (same networks, same
    numbers as :class:`PEARL` for the same seed).

    :param policy: ``"MlpPolicy"`` or a :class:`PEARLPolicy` subclass
    :param env: an env id or env following the task protocol (as for :class:`PEARL`)
    :param prior_coef: weight ``alpha`` of the prior term (paper default 0.1); 0 gives PEARL
    :param prior_critic: ``"separate"`` (PEARL+) or ``"shared"`` (ablation PEARL+ (w/o))
    :param prior_critic_arch: hidden sizes of the prior critic (paper: [300, 300, 300]; ablation [100, 100, 100])
    :param prior_n_critics: Q networks in the prior critic (the paper: one new Q-network; 2 adds a twin minimum)
    :param prior_data: the replay rows the prior terms use: ``"all"`` (the paper) or ``"prior"``, only the transitions
        collected with z from the prior (not in the paper, off by default): the prior critic is then fitted, and the
        actor's prior term scored, on the states the z0 policy itself visits, not on states that posterior policies
        reached on their way to each task's own target (task-confounded data, docs/diagnostics.md)
    :param prior_critic_input: ``"state_z0"`` (the paper: Q~(s, a, z0)) or ``"state"``: a z-free prior critic Q~(s, a)
        (not in the paper, off by default; z0 ~ N(0, I) carries no task information, docs/pearl.md)
    :param prior_target: what the prior critic bootstraps from: ``"prior"``, its own target network (the paper's
        separate Q-network), or ``"main"``, the critic's target network at z0, ``r + gamma * V(s', z0)`` with
        ``V = Q_target(s', a', z0) - alpha log pi(a' | s', z0)``, or ``"mc"``: fitted to the Monte-Carlo soft returns
        of the trajectories collected with z from the prior (on those rows only), each bootstrapped from its own target
        network where the trajectory was cut (:mod:`sb3_pearl.pearl.returns`). ``"main"`` and ``"mc"`` are not in the
        paper and off by default (docs/pearl.md)
    :param prior_return_steps: with ``prior_target="mc"``, n of n-step returns (the tail is bootstrapped after at most
        n rewards); 0 (default): each return runs to the end of its trajectory
    :param prior_conservative_weight: weight of a conservative (CQL) penalty on the prior critic: Q~ at the z0
        policy's actions minus Q~ at the stored actions (0: off, the paper; docs/pearl.md)
    :param _init_setup_model: build the networks at construction
    :param kwargs: every other argument is :class:`PEARL`'s (``learning_rate``, ``latent_dim``, ``kl_weight``,
        ``n_train_tasks``, ``meta_batch``, ``policy_kwargs``, ``seed``, ...), passed by name, with its defaults;
        ``inspect.signature(PEARLPlus)`` lists them with PEARL+'s own

    The prior-critic designs compared in docs/pearl.md ("Prior-critic designs") combine ``prior_n_critics`` (2: twin
    minimum; 5: a pessimistic ensemble), ``prior_data``, ``prior_critic_input``, ``prior_target`` (with
    ``prior_return_steps``) and ``prior_conservative_weight``; every default is the paper's form. None is recommended:
    the pre-written selection on SafePointGoal found no design calibrated (docs/pearl.md, "What the selection found").

    PEARL+ adds to PEARL through the hooks PEARL's ``train()`` and ``save`` call: its settings and rows enter the one
    loss step (:meth:`_loss_settings`: one actor pass over the posterior and prior rows, one random draw), its terms
    the sum (:meth:`_total_loss`), its prior critic the networks, the target pairs and the saved optimizers.
    """

    networks: ClassVar[tuple[str, ...]] = (*PEARL.networks, "prior_critic", "prior_critic_target")
    prior_critic: LatentCritic | None  # None with prior_critic="shared" or prior_coef=0
    prior_critic_target: LatentCritic | None

    def __init__(
        self,
        policy: str | type[PEARLPolicy],
        env: GymEnv | str,
        *,
        prior_coef: float = 0.1,
        prior_critic: str = "separate",
        prior_critic_arch: list[int] | None = None,
        prior_n_critics: int = 1,
        prior_data: str = "all",
        prior_critic_input: str = "state_z0",
        prior_target: str = "prior",
        prior_conservative_weight: float = 0.0,
        prior_return_steps: int = 0,
        _init_setup_model: bool = True,
        **kwargs: Any,
    ):
        # Every argument checked before anything is built (docs/reliability.md); PEARL's by PEARL.__init__.
        check_pearl_plus_arguments(locals())
        super().__init__(policy, env, _init_setup_model=False, **kwargs)
        self.prior_coef = prior_coef
        self.prior_critic_mode = prior_critic
        self.prior_data = prior_data
        self.prior_target = prior_target
        self.prior_conservative_weight = float(prior_conservative_weight)
        self.prior_return_steps = prior_return_steps
        self.policy_kwargs.update(
            # The one switch: a prior critic is built only when the prior term uses it.
            prior_critic=self.prior_critic_mode if self.uses_prior_term else "none",
            prior_n_critics=prior_n_critics,
            prior_critic_input=prior_critic_input,
        )
        if prior_critic_arch is not None:
            self.policy_kwargs["prior_critic_arch"] = prior_critic_arch
        if _init_setup_model:
            self._setup_model()

    @property
    def uses_prior_term(self) -> bool:
        """Whether the actor is also trained on prior latents z0 (``prior_coef > 0``)."""
        return self.prior_coef > 0

    # ------------------------------------------------------------------------------------------
    # The hooks of PEARL's gradient step: the prior terms, in PEARL's one loss step
    # ------------------------------------------------------------------------------------------
    def _loss_settings(self) -> LossSettings:
        settings = super()._loss_settings()
        return settings._replace(
            prior_term=self.uses_prior_term,
            prior_data=self.prior_data,
            prior_target=self.prior_target,
            prior_conservative_weight=self.prior_conservative_weight,
        )

    def _total_loss(self, losses: PEARLLosses) -> th.Tensor:
        return (
            losses.critic_loss
            + self.kl_weight * losses.kl_loss
            + losses.prior_critic_loss
            + losses.actor_loss
            + self.prior_coef * losses.prior_actor_loss
            + losses.ent_coef_loss
        )

    def _target_pairs(self) -> tuple[list[th.Tensor], list[th.Tensor]]:
        sources, targets = super()._target_pairs()
        if self.prior_critic is not None and self.prior_critic_target is not None:
            sources += self.prior_critic.parameters()
            targets += self.prior_critic_target.parameters()
        return sources, targets

    def _returns_horizon(self) -> int | None:
        return self.prior_return_steps if self.prior_target == "mc" else None

    def _actor_second_term_weight(self) -> float:
        return self.prior_coef

    def _named_losses(self, losses: PEARLLosses) -> dict[str, th.Tensor]:
        return _with_prior_terms(super()._named_losses(losses), losses, "kl_loss")

    def _logged_losses(self, losses: PEARLLosses) -> dict[str, th.Tensor]:
        return _with_prior_terms(super()._logged_losses(losses), losses, "kl")

    def _divergence_settings(self) -> dict[str, Any]:
        return {**super()._divergence_settings(), "prior_coef": self.prior_coef}

    def _optimized_networks(self) -> list[str]:
        return [*super()._optimized_networks(), *(["prior_critic"] if self.prior_critic is not None else [])]

    # ------------------------------------------------------------------------------------------
    # Save / load
    # ------------------------------------------------------------------------------------------
    @classmethod
    def _added_data(cls) -> dict[str, Any]:
        """
        PEARL+'s saved settings that PEARL models saved before the two classes were split hold too, with PEARL's values.

        :return: name -> the value that stands for no prior term
        """
        return {"prior_coef": 0.0, "prior_critic_mode": "none", "prior_data": "all"}

    @classmethod
    def _variant_of(cls, data: dict[str, Any]) -> str | None:
        """
        A zip with a prior term or a prior critic is PEARL+'s: ``PEARL.load`` refuses it (it would drop them);
        ``PEARLPlus.load`` takes a PEARL zip too (``prior_coef`` 0, no prior critic).

        :param data: a zip's ``data`` entry
        :return: ``"a PEARL+ model (prior_coef=..., prior_critic=...)"``, or None for a PEARL zip
        """
        prior_coef, mode = data.get("prior_coef", 0.0), data.get("prior_critic_mode", "none")
        if prior_coef == 0.0 and mode == "none":
            return None
        return f"a PEARL+ model (prior_coef={prior_coef}, prior_critic={mode!r})"

    @classmethod
    def _check_saved_arguments(cls, saved: Mapping[str, Any]) -> None:
        """
        PEARL's checks, then :func:`check_pearl_plus_arguments` on a loaded model's prior settings (``prior_critic`` is
        saved as ``prior_critic_mode``, its architecture and inputs in ``policy_kwargs``). A PEARL model (no prior
        critic, ``prior_coef`` 0), which ``PEARLPlus.load`` takes, has no prior setting to check.

        :param saved: the attributes by name
        """
        super()._check_saved_arguments(saved)
        mode, prior_coef = saved.get("prior_critic_mode", "none"), saved.get("prior_coef", 0.0)
        if mode == "none" and prior_coef == 0.0:
            return
        policy_kwargs = saved.get("policy_kwargs")
        policy_kwargs = policy_kwargs if isinstance(policy_kwargs, dict) else {}
        keys = ("prior_critic_arch", "prior_n_critics", "prior_critic_input")
        derived = {key: policy_kwargs[key] for key in keys if key in policy_kwargs}
        check_pearl_plus_arguments(saved_arguments(PEARLPlus.__init__, saved, prior_critic=mode, **derived))

    def learn(
        self: SelfPEARLPlus,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 1,
        tb_log_name: str = "PEARLPlus",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfPEARLPlus:
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)
