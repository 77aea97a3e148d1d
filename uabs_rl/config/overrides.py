"""What a command line's overrides are: the words that set a key, the key each sets, and
the refusals that need no config (a setting given twice, a setting that moved)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from uabs_rl.config.base import ConfigError
from uabs_rl.config.schema import MOVED


def check_moved_overrides(overrides: list[str]) -> None:
    """Refuse a command-line override of a setting that moved, saying what to type."""
    for o in overrides:
        key, _, value = o.lstrip("+~").partition("=")
        for (sec, old), (new_sec, new) in MOVED.items():
            if key == f"{sec}.{old}":
                hint = {"lookahead": "obs=lookahead (obs=lookahead_motion with the motion "
                                     "features)", "motion": "obs=lookahead_motion"}.get(
                    new, f"{new_sec}.{new}={value}")
                raise ConfigError(f"{key} moved to the observation group: type {hint} "
                                  f"instead of {o} (conf/obs holds the observations).")


# Hydra's flags that take the next word as their value (``--cfg job``, ``-cn config``)
_FLAGS_WITH_VALUE = {"-c", "--cfg", "-p", "--package", "-cn", "--config-name", "-cp",
                     "--config-path", "-cd", "--config-dir", "--experimental-rerun"}
_INFO_TOPICS = {"all", "config", "defaults", "defaults-tree", "plugins", "searchpath"}
# keys a command appends to what the user typed (uabs-train's resume= names the run's
# folder again as hydra.run.dir, or hydra.sweep.dir with -m): typed once, they appear twice
APPENDED_KEYS = ("hydra.run.dir", "hydra.sweep.dir", "hydra.output_subdir")


def override_key(word: str) -> str | None:
    """The setting a command-line word overrides (``+a.b=1``, ``~a.b``, ``a.b=1`` ->
    ``a.b``; a group with a package, ``a@p=x``, stays whole), None for a flag."""
    if word.startswith("-"):
        return None
    key, eq, _ = word.lstrip("+~").partition("=")
    return key.strip() if (eq or word.startswith("~")) and key.strip() else None


def command_line_overrides(argv: list[str]) -> list[str]:
    """The overrides of a command line: its words that are neither flags nor a flag's
    value."""
    out, skip = [], False
    for i, word in enumerate(argv):
        if skip:
            skip = False
            continue
        if word in _FLAGS_WITH_VALUE or (word == "--info" and i + 1 < len(argv)
                                         and argv[i + 1] in _INFO_TOPICS):
            skip = True
            continue
        if not word.startswith("-"):
            out.append(word)
    return out


def chooses_study(words: list[str]) -> bool:
    """Whether overrides choose a sweeper other than Hydra's own ``basic``: a tuning study
    (``hydra/sweeper=optuna``), whose trials are drawn, not listed."""
    return any(w.startswith("hydra/sweeper=") and w.split("=", 1)[1].strip() != "basic"
               for w in words)


def check_duplicate_overrides(argv: list[str]) -> None:
    """Refuse a setting given twice on the command line (``masking=flat
    masking=penalty``, ``seed=1 seed=2``; with ``-m`` too): Hydra would keep the last
    one silently, and the run folder would be named after both."""
    seen: dict[str, list[str]] = {}
    for word in command_line_overrides(argv):
        key = override_key(word)
        if key is not None:
            seen.setdefault(key, []).append(word)
    resumed = "resume" in seen
    for key, words in seen.items():
        allowed = 2 if key in APPENDED_KEYS and resumed else 1
        if len(words) > allowed:
            n = len(words) - allowed + 1
            values = ",".join(w.partition("=")[2] for w in words[:n])
            raise ConfigError(f"{key} is given {'twice' if n == 2 else f'{n} times'} on the "
                              f"command line ({', '.join(words[:n])}): give it once (a "
                              f"sweep over several values: -m {key}={values}).")


# the setting by which each config group's option files name themselves: the file of
# masking=flat sets ``mode: flat``, which selects the masks the env builds, and the
# labels of runs, reports and evaluations read it
SELF_NAMES = {"algo": "name", "channel": "name", "masking": "mode", "obs": "name",
              "scenario": "name"}


def check_group_choices(choices: Mapping[str, Any], cfg: Any,
                        overrides: Iterable[str] = ()) -> None:
    """Refuse a group option whose file does not name itself: a ``conf/masking/
    cautious.yaml`` without ``mode: cautious`` leaves the schema's ``rank``, and
    ``masking=cautious`` would train rank masks in a folder, under labels, that say
    cautious. ``choices``: each group's option (Hydra's ``runtime.choices``); ``cfg``:
    the composed config; ``overrides``: the command line's, where ``masking.mode=flat``
    typed beside the default ``masking=rank`` is the user's own choice."""
    typed = {override_key(o) for o in overrides}
    for group, key in SELF_NAMES.items():
        option = choices.get(group)
        section = getattr(cfg, group, None) if not isinstance(cfg, Mapping) else cfg.get(group)
        if option is None or section is None or f"{group}.{key}" in typed:
            continue
        value = (section.get(key) if isinstance(section, Mapping)
                 else getattr(section, key, None))
        value = getattr(value, "value", value)  # an enum member (masking.mode)
        option = str(option).rsplit("/", 1)[-1]
        if value is not None and str(value) != option:
            raise ConfigError(
                f"{group}={option} composes {group}.{key}={value}, not {option}: its file "
                f"({group}/{option}.yaml, in conf/ or your --config-dir) must name its "
                f"option, else it runs {value} under {option}'s name. Add the line "
                f"'{key}: {option}' to it (under '{group}:' in a file of "
                f"'# @package _global_').")
