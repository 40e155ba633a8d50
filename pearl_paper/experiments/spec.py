"""The declarative pieces of a reproduction experiment: families, variants, paper numbers, claims.

An :class:`Experiment` (one per paper table, plus the fast family) says *what* is run: which task
families (:class:`Family`), which algorithm variants (:class:`Variant`: a zoo algorithm name plus
constructor overrides such as ``prior_coef``), which seeds, under which budget preset by default,
on which fixed meta-test seed, and what the paper reports (:class:`PaperCell`) and claims
(:class:`Claim`). *How much* is run (env steps, network sizes, meta-test sizes) is the budget
preset's business (:mod:`sb3_pearl.budgets`).

Metrics are ``"violation"`` (share of trajectories with any cost, a fraction in [0, 1]) and
``"return"``. ``k`` is the trajectory index of the meta-test (0: prior, k >= 1: after k
trajectories); a negative ``k`` counts from the end, ``k = -1`` being the last trajectory K of the
meta-test, i.e. the paper's "after adaptation".
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from sb3_pearl.registry import ALGORITHM_NAMES

Metric = Literal["violation", "return"]
Direction = Literal["lower", "higher", "equal", "not_lower", "not_higher"]
METRICS: tuple[str, ...] = ("violation", "return")
DIRECTIONS: tuple[str, ...] = ("lower", "higher", "equal", "not_lower", "not_higher")
ALGOS: tuple[str, ...] = ALGORITHM_NAMES
# Default equivalence margin of the violation rate (absolute, 5 percentage points).
VIOLATION_MARGIN = 0.05
_NAME = re.compile(r"^[a-z0-9][a-z0-9.+_-]*$")


def check_name(name: str, what: str) -> None:
    """
    Raise a clear error unless ``name`` can be a folder name of the results layout.

    :param name: the name
    :param what: what it names, for the message
    """
    if not _NAME.match(name):
        raise ValueError(f"{what} name {name!r} must be lower case letters, digits and . + _ - (it names a results folder)")


@dataclass(frozen=True)
class Criterion:
    """
    One condition of a competence check, evaluated on a meta-test over *training* tasks, trajectories ``k >= min_k``.

    :param description: what it measures, for the docs and the report
    :param kind: ``"trace_mean"`` (per trajectory the mean of a per-step info trace, then the mean over
        trajectories), ``"trace_last"`` (the last value of the trace) or ``"row_mean"`` (the mean of a
        meta-test row column, e.g. ``violated`` or ``merged``)
    :param key: the info / row key
    :param threshold: the bar
    :param better: ``"lower"``: passes if value <= threshold; ``"higher"``: if value >= threshold
    :param scale: the value is multiplied by this (e.g. -1 to turn ``reward_forward`` into a tracking error)
    :param min_k: first trajectory index counted
    """

    description: str
    kind: Literal["trace_mean", "trace_last", "row_mean"]
    key: str
    threshold: float
    better: Literal["lower", "higher"]
    scale: float = 1.0
    min_k: int = 1

    def __post_init__(self) -> None:
        if self.kind not in ("trace_mean", "trace_last", "row_mean"):
            raise ValueError(f"criterion kind must be trace_mean, trace_last or row_mean, got {self.kind!r}")
        if self.better not in ("lower", "higher"):
            raise ValueError(f"criterion better must be 'lower' or 'higher', got {self.better!r}")


@dataclass(frozen=True)
class PublishedPoint:
    """
    A point of someone else's learning curve on a family, in the reference's metric (the mean return of the last
    evaluation trajectory on the test tasks), drawn and listed beside our curves at the same env steps.

    :param env_steps: env steps of training at the point
    :param value: the published return
    :param source: who measured it, how (e.g. the averaging), and where it is written down
    """

    env_steps: int
    value: float
    source: str


@dataclass(frozen=True)
class PriorBar:
    """
    The task-independent bar of a family's prior-optimality gap: what a policy with no task data scores at k = 0.

    :param kind: ``"scripted"``, a scripted policy the family's env module declares (``SCRIPTED_PRIORS``), rolled
        out by every run on the same tasks and env seeds as the model's k = 0 trajectories; or ``"variant"``, the
        k = 0 policy of another variant of the same experiment and seed (Fine-Tune: SAC on the task mixture)
    :param name: the scripted policy's or the variant's name
    :param description: what the bar is, for the report
    """

    kind: Literal["scripted", "variant"]
    name: str
    description: str

    def __post_init__(self) -> None:
        if self.kind not in ("scripted", "variant"):
            raise ValueError(f"prior bar kind must be 'scripted' or 'variant', got {self.kind!r}")


@dataclass(frozen=True)
class Family:
    """
    A task family of the experiments (or a variant of one with other env kwargs).

    :param name: the family name of the CLI and of the results layout (``walker2d-vel``)
    :param env_id: the registered env id
    :param title: a human name (the paper's)
    :param env_kwargs: constructor kwargs of the training and test env
    :param shift_env_kwargs: kwargs of a shifted test distribution (``None``: none declared); the
        meta-test then also runs on tasks drawn from ``gym.make(env_id, **env_kwargs, **shift_env_kwargs)``
    :param shift_description: what the shift is
    :param budget_family: the family whose budget entries apply (default: ``name``); set for family
        variants such as ``safe-point-crash5``
    :param competence: the competence criteria of PEARL's posterior policy on training tasks (all must pass)
    :param return_margin: equivalence margin of the mean return, in this family's reward units (for
        the verdicts of return claims)
    :param prior_bar: the task-independent bar of the prior-optimality gap (None: the family has none)
    :param published_curve: points of published learning curves of PEARL on this family (``reproduce report`` draws
        them on the learning-curve figures and lists them under the curve tables)
    :param has_violations: whether the family's env can report a safety violation (``info["cost"]``: a fall, a crash);
        False for HalfCheetah-Vel, which never terminates, so that figures leave out its always-zero violation rate
    """

    name: str
    env_id: str
    title: str
    env_kwargs: Mapping[str, Any] = field(default_factory=dict)
    shift_env_kwargs: Mapping[str, Any] | None = None
    shift_description: str = ""
    budget_family: str | None = None
    competence: tuple[Criterion, ...] = ()
    return_margin: float = 1.0
    prior_bar: PriorBar | None = None
    published_curve: tuple[PublishedPoint, ...] = ()
    has_violations: bool = True

    def __post_init__(self) -> None:
        check_name(self.name, "family")
        if self.return_margin <= 0:
            raise ValueError(f"family {self.name}: return_margin must be > 0, got {self.return_margin}")

    @property
    def budget_name(self) -> str:
        """The family name under which the budget presets hold this family's entries."""
        return self.budget_family or self.name

    def trace_keys(self) -> tuple[str, ...]:
        """The info traces the competence criteria read."""
        return tuple(sorted({c.key for c in self.competence if c.kind.startswith("trace")}))


@dataclass(frozen=True)
class Variant:
    """
    One algorithm setting of an experiment.

    :param name: folder name in the results layout (``pearlplus-100``)
    :param label: the paper's name (``PEARL+ (100-Node)``)
    :param algo: zoo algorithm name: ``pearl``, ``pearlplus``, ``finetune`` or ``maml``
    :param overrides: constructor kwargs set on top of the budget's (``prior_coef``, ``prior_critic``, ...)
    """

    name: str
    label: str
    algo: str
    overrides: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_name(self.name, "variant")
        if self.algo not in ALGOS:
            raise ValueError(f"variant {self.name}: unknown algo {self.algo!r}, expected one of {ALGOS}")

    def same_model(self, other: Variant) -> bool:
        """Whether ``other`` trains the same model (algorithm and overrides; names and labels aside)."""
        return (self.algo, dict(self.overrides)) == (other.algo, dict(other.overrides))


@dataclass(frozen=True)
class PaperCell:
    """
    One number the paper reports.

    :param family: family name
    :param variant: variant name
    :param metric: ``"violation"`` (fraction) or ``"return"`` (the paper's reward units)
    :param k: trajectory index (-1: after adaptation, the last trajectory)
    :param value: the number (a fraction for violation rates: 60.7% is 0.607)
    :param sd: the paper's standard deviation over runs, if given
    :param source: where in the paper
    """

    family: str
    variant: str
    metric: Metric
    k: int
    value: float
    sd: float | None = None
    source: str = ""

    def __post_init__(self) -> None:
        if self.metric not in METRICS:
            raise ValueError(f"paper cell metric must be one of {METRICS}, got {self.metric!r}")


@dataclass(frozen=True)
class Claim:
    """
    A comparison the paper makes: ``variant`` against ``reference`` on ``metric`` at trajectory ``k``.

    :param family: family name
    :param variant: the variant the claim is about
    :param reference: the variant it is compared with
    :param metric: ``"violation"`` or ``"return"``
    :param k: trajectory index (-1: the last)
    :param direction: ``"lower"`` / ``"higher"``: variant minus reference is negative / positive;
        ``"equal"``: no material difference (within ``margin``); ``"not_lower"`` / ``"not_higher"``:
        not worse by more than ``margin`` in that direction (non-inferiority, "close to or better")
    :param margin: equivalence margin in our units (None: :data:`VIOLATION_MARGIN` for violation
        rates, the family's ``return_margin`` for returns)
    :param source: the paper's statement or numbers
    """

    family: str
    variant: str
    reference: str
    metric: Metric
    k: int
    direction: Direction
    margin: float | None = None
    source: str = ""

    def __post_init__(self) -> None:
        if self.metric not in METRICS:
            raise ValueError(f"claim metric must be one of {METRICS}, got {self.metric!r}")
        if self.direction not in DIRECTIONS:
            raise ValueError(f"claim direction must be one of {DIRECTIONS}, got {self.direction!r}")
        if self.variant == self.reference:
            raise ValueError(f"claim on {self.variant}: the reference must be another variant")


@dataclass(frozen=True)
class Experiment:
    """
    A reproduction experiment (one paper table, or the fast family).

    :param name: CLI and folder name (``table1``)
    :param title: what it reproduces
    :param description: the setting, for the report
    :param families: the task families
    :param variants: the algorithm variants (each runs on every family)
    :param seeds: default model seeds
    :param variant_seeds: variants declared with other seeds than ``seeds``, ``{variant: seeds}`` (e.g. two rows
        of Tables II and III at Table I's 10 seeds, the others at theirs); see :meth:`seeds_of`
    :param family_seeds: families declared with other seeds than the variants', ``{family: seeds}`` (e.g. candidate
        redefinitions of a family, each declared at one seed beside the families run at three); they take precedence
        over ``variant_seeds`` on that family
    :param budget: default budget preset
    :param eval_seed: the fixed meta-test seed: the test tasks are ``sample_tasks(n_tasks, eval_seed)``
        of the family env, the same for every variant and model seed (common random numbers); also
        the ``crn_seed`` of the meta-test
    :param reference: the variant the claims compare with (PEARL, or alpha = 0)
    :param paper: the paper's numbers
    :param claims: the paper's comparisons, each with a verdict in the report
    :param shared: variants whose runs belong to another experiment, ``{variant: experiment}``: the other experiment
        declares the same variant (same algorithm and overrides) on the same families with the same eval seed, so its
        runs are this experiment's too (planned, skipped and stored under the other experiment's folder, reported
        in both); checked by :func:`check_shared`
    :param after_selection: variants that run only once the experiment's selection rule has picked them (the
        ``prior-critic`` experiment: alpha 1 for the two designs its rule selects, docs/pearl.md): until every run the
        rule reads is complete, ``reproduce run`` without ``--variants`` leaves them out and ``reproduce status`` lists
        them as awaiting the selection; afterwards the ones not selected are never planned by default. The one rule
        implemented is the prior-critic selection (``alpha-1-<design>`` variants,
        :func:`~pearl_paper.reproduce.prior_report.selection_gate`); a shared variant cannot be gated (its owner plans it)
    :param selected_by: the experiment whose rule gates ``after_selection`` (``""``: this one); ``prior-critic-walker``'s
        designs are those the ``prior-critic`` selection picks
    """

    name: str
    title: str
    description: str
    families: tuple[Family, ...]
    variants: tuple[Variant, ...]
    seeds: tuple[int, ...] = (0, 1, 2, 3)
    variant_seeds: Mapping[str, tuple[int, ...]] = field(default_factory=dict)
    family_seeds: Mapping[str, tuple[int, ...]] = field(default_factory=dict)
    budget: str = "cpu"
    eval_seed: int = 1_000_003
    reference: str = "pearl"
    paper: tuple[PaperCell, ...] = ()
    claims: tuple[Claim, ...] = ()
    shared: Mapping[str, str] = field(default_factory=dict)
    after_selection: tuple[str, ...] = ()
    selected_by: str = ""

    def __post_init__(self) -> None:
        check_name(self.name, "experiment")
        self.validate()

    def validate(self) -> None:
        """Raise a clear error for duplicated names or a paper cell / claim naming an unknown family or variant."""
        for what, names in (("family", [f.name for f in self.families]), ("variant", [v.name for v in self.variants])):
            duplicates = sorted({n for n in names if names.count(n) > 1})
            if duplicates:
                raise ValueError(f"experiment {self.name}: duplicated {what} names {duplicates}")
        families = {f.name for f in self.families}
        variants = {v.name for v in self.variants}
        if self.reference not in variants:
            raise ValueError(
                f"experiment {self.name}: reference {self.reference!r} is not one of its variants {sorted(variants)}"
            )
        unknown = sorted(set(self.after_selection) - variants)
        if unknown:
            raise ValueError(f"experiment {self.name}: after_selection names unknown variants {unknown}")
        owned_elsewhere = sorted(set(self.after_selection) & set(self.shared))
        if owned_elsewhere:
            raise ValueError(
                f"experiment {self.name}: after_selection names shared variants {owned_elsewhere}: their owner plans "
                "them whatever this experiment's rule selects"
            )
        unknown = sorted(set(self.variant_seeds) - variants)
        if unknown:
            raise ValueError(f"experiment {self.name}: variant_seeds names unknown variants {unknown}")
        unknown = sorted(set(self.family_seeds) - families)
        if unknown:
            raise ValueError(f"experiment {self.name}: family_seeds names unknown families {unknown}")
        declared = {name: self.seeds_of(name) for name in sorted(variants)} | dict(sorted(self.family_seeds.items()))
        for name, seeds in declared.items():
            if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
                raise ValueError(
                    f"experiment {self.name}: the seeds of {name} must be distinct integers >= 0, at least one; got "
                    f"{list(seeds)}"
                )
        if any(self.eval_seed in seeds for seeds in declared.values()):
            raise ValueError(f"experiment {self.name}: eval_seed {self.eval_seed} must differ from the model seeds")
        items: list[PaperCell | Claim] = [*self.paper, *self.claims]
        for item in items:
            names = [item.variant] + ([item.reference] if isinstance(item, Claim) else [])
            if item.family not in families or any(n not in variants for n in names):
                raise ValueError(
                    f"experiment {self.name}: {type(item).__name__} {item} names an unknown family or variant "
                    f"(families {sorted(families)}, variants {sorted(variants)})"
                )

    def seeds_of(self, variant: str, family: str | None = None) -> tuple[int, ...]:
        """
        The model seeds declared for ``variant`` (on ``family``): the family's own (``family_seeds``), else the
        variant's (``variant_seeds``), else the experiment's.

        :param variant: a variant name
        :param family: a family name (None: the variant's seeds on a family without seeds of its own)
        """
        if family is not None and family in self.family_seeds:
            return tuple(self.family_seeds[family])
        return tuple(self.variant_seeds.get(variant, self.seeds))

    def owner(self, variant: str) -> str:
        """The experiment whose results folder holds the runs of ``variant`` (this one, unless it is shared)."""
        return self.shared.get(variant, self.name)

    def family(self, name: str) -> Family:
        """The family called ``name`` (ValueError listing the experiment's families otherwise)."""
        for family in self.families:
            if family.name == name:
                return family
        raise ValueError(f"experiment {self.name} has no family {name!r}: choose among {[f.name for f in self.families]}")

    def variant(self, name: str) -> Variant:
        """The variant called ``name`` (ValueError listing the experiment's variants otherwise)."""
        for variant in self.variants:
            if variant.name == name:
                return variant
        raise ValueError(f"experiment {self.name} has no variant {name!r}: choose among {[v.name for v in self.variants]}")

    def paper_value(self, family: str, variant: str, metric: str, k: int, last_k: int) -> PaperCell | None:
        """
        The paper's number of a cell, if it reports one.

        :param family: family name
        :param variant: variant name
        :param metric: ``"violation"`` or ``"return"``
        :param k: trajectory index of the cell (>= 0)
        :param last_k: the last trajectory index K of the meta-test (what ``k = -1`` means)
        :return: the paper cell or None
        """
        for cell in self.paper:
            if (cell.family, cell.variant, cell.metric) == (family, variant, metric) and resolve_k(cell.k, last_k) == k:
                return cell
        return None


def check_shared(experiment: Experiment, experiments: Mapping[str, Experiment]) -> None:
    """
    Raise a clear error unless every shared variant of ``experiment`` is declared identically by its owner.

    :param experiment: the experiment
    :param experiments: every experiment by name
    """
    for name, owner_name in experiment.shared.items():
        where = f"experiment {experiment.name}: shared variant {name!r}"
        owner = experiments.get(owner_name)
        if owner is None or owner is experiment:
            raise ValueError(f"{where} names the owner {owner_name!r}, which is not another experiment")
        mine = experiment.variant(name)
        theirs = owner.variant(name)
        if not mine.same_model(theirs):
            raise ValueError(f"{where} is declared differently in {owner_name}: {theirs} against {mine}")
        if owner.eval_seed != experiment.eval_seed:
            raise ValueError(f"{where}: {owner_name} has eval seed {owner.eval_seed}, not {experiment.eval_seed}")
        for family in experiment.families:
            if owner.family(family.name) != family:
                raise ValueError(f"{where}: family {family.name} differs in {owner_name}")


def resolve_k(k: int, last_k: int) -> int:
    """``k`` as a trajectory index: negative values count from the end (-1 is ``last_k``)."""
    return k if k >= 0 else last_k + 1 + k


def claims_from_paper(
    paper: Sequence[PaperCell],
    reference: str,
    metric: Metric = "violation",
    margin: float = VIOLATION_MARGIN,
    source: str = "",
) -> tuple[Claim, ...]:
    """
    The claims a table of paper numbers makes against its reference variant.

    For every cell of ``metric`` whose variant is not ``reference`` and whose reference cell (same
    family and k) exists: ``"lower"`` / ``"higher"`` if the paper's difference is at least
    ``margin`` in size (in the paper's units), ``"equal"`` otherwise.

    :param paper: the paper's numbers
    :param reference: the reference variant
    :param metric: the metric compared
    :param margin: the smallest paper difference read as a claimed difference
    :param source: prefix of each claim's source text
    :return: the claims
    """
    refs = {(c.family, c.k): c for c in paper if c.variant == reference and c.metric == metric}
    claims = []
    for cell in paper:
        ref = refs.get((cell.family, cell.k))
        if cell.metric != metric or cell.variant == reference or ref is None:
            continue
        delta = cell.value - ref.value
        direction: Direction = "equal" if abs(delta) < margin else ("lower" if delta < 0 else "higher")
        shown = [f"{100 * v:g}%" if metric == "violation" else f"{v:g}" for v in (cell.value, ref.value)]
        claims.append(
            Claim(
                family=cell.family,
                variant=cell.variant,
                reference=reference,
                metric=metric,
                k=cell.k,
                direction=direction,
                source=f"{source}: {shown[0]} vs {shown[1]}".lstrip(": "),
            )
        )
    return tuple(claims)


def paper_cells(
    family: str,
    metric: Metric,
    rows: Mapping[str, Sequence[float | None]],
    ks: Sequence[int],
    scale: float = 1.0,
    source: str = "",
) -> tuple[PaperCell, ...]:
    """
    Paper cells from a table written as ``{variant: [value per k]}`` (None: not reported).

    :param family: family name
    :param metric: the metric
    :param rows: values per variant, in the order of ``ks``
    :param ks: the trajectory index of each column
    :param scale: factor applied to each value (0.01 turns percentages into fractions)
    :param source: where in the paper
    :return: the cells
    """
    cells = []
    for variant, values in rows.items():
        if len(values) != len(ks):
            raise ValueError(f"paper row {variant} of {family}: {len(values)} values for {len(ks)} columns")
        for k, value in zip(ks, values):
            if value is not None:
                cells.append(PaperCell(family, variant, metric, k, round(value * scale, 10), source=source))
    return tuple(cells)
