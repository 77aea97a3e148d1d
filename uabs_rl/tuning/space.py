"""A study's search space: Hydra sweep overrides (``choice``, ``range``, ``interval``,
``tag(log, ...)``) as Optuna distributions, and a trial's values back as overrides."""

from __future__ import annotations

import difflib
from typing import Any

from uabs_rl.config import CONF_DIR, ConfigError

PRIMITIVE = (type(None), bool, int, float, str)


def override_text(value: Any) -> str:
    """A value as a Hydra override writes it: ``[64, 64]`` for a list, ``null``,
    ``true``; a float in full (``repr``), so that re-typing it gives the same number."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return "[" + ", ".join(override_text(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {override_text(v)}" for k, v in value.items()) + "}"
    return repr(value) if isinstance(value, float) else str(value)


def known_keys(flat: dict[str, Any]) -> set[str]:
    """What a search space may name: every setting of the run's config (flat, as
    ``algo.lr``) and every config group (``masking``, ``obs``, ...)."""
    groups = {d.name for d in CONF_DIR.iterdir() if d.is_dir() and d.name != "hydra"}
    return set(flat) | groups


def check_key(key: str, known: set[str], where: str) -> None:
    """Refuse a search-space key that names no setting, in one line with the closest
    names."""
    if key in known:
        return
    close = difflib.get_close_matches(key, sorted(known), n=3, cutoff=0.6)
    hint = f" (did you mean {' or '.join(close)}?)" if close else ""
    raise ConfigError(f"{where}: {key} is not a setting of uabs-train{hint}: name a key "
                      f"of the run's config (uabs-train --cfg job lists them), or a config "
                      f"group such as masking.")


def distribution(key: str, sweep: Any, where: str):
    """The Optuna distribution of a Hydra sweep value (parsed by Hydra's override
    parser). Choices of lists or mappings (``algo.hidden``) are drawn as their override
    text."""
    from hydra.core.override_parser.types import ChoiceSweep, IntervalSweep, RangeSweep
    from optuna.distributions import (
        CategoricalDistribution,
        FloatDistribution,
        IntDistribution,
    )

    log = "log" in (getattr(sweep, "tags", None) or ())
    if isinstance(sweep, ChoiceSweep):
        choices = list(sweep.list)
        if not choices:
            raise ConfigError(f"{where}: {key}=choice() has no values: give at least one.")
        if not all(isinstance(c, PRIMITIVE) for c in choices):
            choices = [override_text(c) for c in choices]
        return CategoricalDistribution(choices)
    if isinstance(sweep, RangeSweep):
        start, stop, step = sweep.start, sweep.stop, sweep.step
        if all(isinstance(x, int) for x in (start, stop, step)) and step > 0 and stop > start:
            return IntDistribution(start, start + (stop - 1 - start) // step * step, step=step)
        raise ConfigError(f"{where}: {key}=range({start}, {stop}, {step}) is not a rising "
                          f"range of integers: use interval(low, high) for real numbers.")
    if isinstance(sweep, IntervalSweep):
        lo, hi = sweep.start, sweep.end
        if not lo < hi or (log and lo <= 0):
            raise ConfigError(f"{where}: {key}=interval({lo}, {hi}) needs low < high"
                              f"{' and low > 0 (a log scale)' if log else ''}.")
        if isinstance(lo, int) and isinstance(hi, int):
            return IntDistribution(lo, hi, log=log)
        return FloatDistribution(float(lo), float(hi), log=log)
    raise ConfigError(f"{where}: {key} is given one value: give a range to search "
                      f"(choice(...), range(...), interval(...)), or set it beside the "
                      f"sweep as key=value.")


def search_space(params: dict[str, str], arguments: list[str], known: set[str]
                 ) -> tuple[dict[str, Any], list[str]]:
    """The search space (``hydra.sweeper.params``, then the sweeps typed on the command
    line, which add to it or replace an entry; a setting given one value there is pinned,
    out of the space) and the overrides every trial shares (the command line's other
    words)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    space: dict[str, Any] = {}
    for key, text in (params or {}).items():
        where = "hydra.sweeper.params"
        check_key(str(key), known, where)
        try:
            override = parser.parse_override(f"{key}={text}")
        except Exception as e:  # Hydra's grammar errors: their first line
            first = (str(e).strip().splitlines() or [type(e).__name__])[0]
            raise ConfigError(f"{where}.{key}: {text!r} does not parse: {first}") from None
        space[str(key)] = distribution(str(key), override.value(), f"{where}.{key}")
    fixed = []
    for word in arguments:
        override = parser.parse_override(word)
        if override.is_sweep_override():
            key = override.get_key_element().lstrip("+~")
            check_key(key, known, "the command line")
            space[key] = distribution(key, override.value(), "the command line")
        else:
            fixed.append(word)
    for key in {w.split("=", 1)[0].lstrip("+~") for w in fixed} & set(space):
        del space[key]  # a value typed on the command line pins the setting
    return space, fixed


def trial_overrides(params: dict[str, Any]) -> list[str]:
    """A trial's values as overrides, in a fixed order."""
    return [f"{k}={v if isinstance(v, str) else override_text(v)}"
            for k, v in sorted(params.items())]
