"""The config layer's ground: its error, the closed sets (enums), the roles a setting
can play, and the checks every section shares (finite numbers, :data:`RANGES`)."""

from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, field, fields, is_dataclass
from enum import StrEnum
from typing import Any


class ConfigError(ValueError):
    """A config value is invalid; the message names the key and the fix."""


# run seeds (seed, seed + 1, ... of a population, train.eval_seed): the range that
# torch.Generator.manual_seed accepts, [-2^63, 2^64)
SEED_MIN, SEED_END = -(2 ** 63), 2 ** 64
# SUMO seeds (traces.<split>.first_seed + i): SUMO's --seed is a 32-bit signed integer
# and numpy's default_rng (the fleet's routes) refuses negative seeds
SUMO_SEED_MAX = 2 ** 31 - 1


# Closed sets. Member names equal their values because OmegaConf converts yaml strings
# to members by name: ``masking.mode: flat`` -> ``MaskingMode.flat``; Hydra rejects
# any other value when the config is composed.
class MaskingMode(StrEnum):
    """The anti-collision mechanism (docs/model.md §6); its rules live in
    ``uabs_rl.safety.rules``."""

    penalty = "penalty"
    flat = "flat"
    rank = "rank"


class RankNextMask(StrEnum):
    """Rank mode's double-DQN target mask at s' (see ``uabs_rl.safety.rules.RankRule``)."""

    greedy = "greedy"
    boundary = "boundary"


class LosMode(StrEnum):
    """How a link's LoS state is decided (docs/model.md §3)."""

    sample = "sample"
    expected = "expected"
    los = "los"


class LoggerKind(StrEnum):
    """Where a run's scalars go besides ``metrics.jsonl`` (TorchRL's loggers)."""

    tensorboard = "tensorboard"
    csv = "csv"
    wandb = "wandb"
    mlflow = "mlflow"
    none = "none"


class ReplayKind(StrEnum):
    """How a learner's replay draws its samples (``uabs_rl.algorithms.replay``)."""

    uniform = "uniform"
    prioritized = "prioritized"


class LossKind(StrEnum):
    """Which implementation of the 3DQN loss (``uabs_rl.algorithms.dqn3``)."""

    fused = "fused"
    torchrl = "torchrl"


def enum_value(enum: type[StrEnum], value: object, key: str) -> StrEnum:
    """``value`` as a member of ``enum``, or a ConfigError naming ``key`` and the choices."""
    try:
        return enum(value)
    except ValueError:
        choices = "|".join(m.value for m in enum)
        raise ConfigError(f"{key} must be one of {choices}, got {value!r}.") from None



class ObsFrame(StrEnum):
    """Which frame each UABS's observation is written in (``uabs_rl.env.observe``)."""

    fleet = "fleet"
    egocentric = "egocentric"



class Role(StrEnum):
    """What a setting is to a run: the one declaration (each field's ``role`` metadata,
    or its section's) from which every list of "which settings change results" is
    derived (:mod:`uabs_rl.config.roles`)."""

    runtime = "runtime"  # changes no result: progress bar, workers, logger, device, ...
    label = "label"  # a name, not a setting (obs.name): the settings beside it decide
    # how a run computes, not what: the same maths another way (algo.loss) or seeds
    # trained side by side, each as it would alone (train.population); a resumed run
    # keeps it (its checkpoints are laid out by it)
    method = "method"
    seed = "seed"  # what the runs of one experiment differ in
    world = "world"  # the world a policy acts in: uabs-eval may change it
    test = "test"  # the test traces: the world of every reported figure, never trained on
    evaluation = "evaluation"  # where evaluations start (the baselines depend on it)
    protocol = "protocol"  # how long and how often: a resumed run may change it
    policy = "policy"  # what the policy is trained as: its observation, learner, envs


def setting(r: Role, default: Any = MISSING, *, default_factory: Any = MISSING) -> Any:
    """A dataclass field of role ``r`` (``workers: int = setting(Role.runtime, 0)``); a
    section's role holds for each of its fields that declares none."""
    return field(default=default, default_factory=default_factory, metadata={"role": r})


def check_finite(obj: Any, prefix: str = "") -> None:
    """Refuse a NaN or infinite float anywhere in the dataclass ``obj`` (nested configs
    and lists included), naming its key: ``prefix`` + the field's path. A NaN passes
    every ``<``/``>`` range check and trains (or caches traces) on nonsense."""
    for f in fields(obj):
        key, value = f"{prefix}{f.name}", getattr(obj, f.name)
        if is_dataclass(value):
            check_finite(value, f"{key}.")
            continue
        for v in value if isinstance(value, list | tuple) else [value]:
            if isinstance(v, float) and not math.isfinite(v):
                null = " (or null)" if "None" in str(f.type) else ""
                raise ConfigError(f"{key} must be a finite number{null}, got {value!r}. "
                                  f"Set {key} to a finite value.")


def _raise_first(checks: list[tuple[bool, str, str, Any]]) -> None:
    """Raise a ConfigError for the first failed ``(ok, key, rule, value)`` check."""
    for ok, key, rule, value in checks:
        if not ok:
            raise ConfigError(f"{key} {rule}, got {value!r}.")



# ----------------------------------------------------------------------------- ranges
@dataclass(frozen=True)
class Range:
    """The values a numeric setting may take: ``lo`` to ``hi`` (``lo_open`` /
    ``hi_open``: the bound itself excluded), in ``unit``; ``text`` shows a bound that
    reads better as a power (2^64)."""

    lo: float
    hi: float
    unit: str = ""
    lo_open: bool = False
    hi_open: bool = False
    text: tuple[str, str] | None = None

    def holds(self, v: float) -> bool:
        above = v > self.lo if self.lo_open else v >= self.lo
        below = v < self.hi if self.hi_open else v <= self.hi
        return above and below

    def __str__(self) -> str:
        lo, hi = self.text or (_num(self.lo), _num(self.hi))
        unit = f" {self.unit}" if self.unit else ""
        return f"{'(' if self.lo_open else '['}{lo}, {hi}{')' if self.hi_open else ']'}{unit}"


def _num(x: float) -> str:
    """A bound as people write it: 3600, 0.001, 10^9, -1e+08."""
    if float(x).is_integer() and abs(x) < 1e7:
        return str(int(x))
    k = math.log10(abs(x)) if x else 0.0
    return f"{'-' if x < 0 else ''}10^{round(k)}" if k.is_integer() and k > 0 else f"{x:g}"


def _r(lo: float, hi: float, unit: str = "", **kw: Any) -> Range:
    return Range(lo, hi, unit, **kw)


def _pos(hi: float, unit: str = "") -> Range:  # (0, hi]
    return Range(0, hi, unit, lo_open=True)


SEED_RANGE = Range(SEED_MIN, SEED_END, hi_open=True, text=("-2^63", "2^64"))
# every number's range, by dataclass and field: filled by uabs_rl.config.schema
RANGES: dict[type, dict[str, Range]] = {}


def check_ranges(obj: Any, prefix: str = "") -> None:
    """Refuse a number of the dataclass ``obj`` (nested configs and lists included)
    outside its :data:`RANGES` entry, naming its key (``prefix`` + the field's path)."""
    table = RANGES.get(type(obj), {})
    for f in fields(obj):
        key, value = f"{prefix}{f.name}", getattr(obj, f.name)
        if is_dataclass(value):
            check_ranges(value, f"{key}.")
            continue
        rng = table.get(f.name)
        if rng is None or value is None:
            continue
        for v in value if isinstance(value, list | tuple) else [value]:
            if isinstance(v, bool) or not isinstance(v, int | float):
                continue
            if not rng.holds(v):
                each = " (each entry)" if isinstance(value, list | tuple) else ""
                raise ConfigError(f"{key}{each} must be in {rng}, got {v!r}.")
