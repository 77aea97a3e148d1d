"""What a command line's overrides are: the words that set a key, the key each sets, and
the refusals that need no config (a setting given twice, a setting that moved)."""

from __future__ import annotations

import re
from collections.abc import Collection, Iterable, Mapping
from pathlib import Path
from typing import Any

import yaml

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


def option_file(dirs: Iterable[Path], group: str, option: str) -> Path | None:
    """The file of ``group=option`` in the first of the config folders ``dirs`` that
    holds it (None: none does)."""
    return next((f for d in dirs if (f := Path(d) / group / f"{option}.yaml").is_file()),
                None)


def option_bases(data: Mapping[str, Any], group: str) -> list[str]:
    """The options of ``group`` that an option file's ``defaults`` builds on
    (``defaults: [mygrid]`` in ``scenario/dense.yaml``: ``mygrid``), in order; not its
    ``_self_``, a schema (``qmix_schema``) or another group's entries."""
    out = []
    for entry in data.get("defaults") or []:
        name = entry.strip() if isinstance(entry, str) else ""
        if name.startswith("/"):
            other, _, name = name[1:].partition("/")
            name = name if other == group else ""
        if name and name != "_self_" and not name.endswith("_schema") and "/" not in name:
            out.append(name)
    return out


def global_package(text: str) -> bool:
    """Whether a config file's header puts it at the config's root
    (``# @package _global_``: it sets ``scenario.name`` under ``scenario:``), read as
    Hydra reads it: from the ``# @`` lines at the top, up to the first other line."""
    for line in text.splitlines():
        line = line.strip()
        if not line:
            continue
        if not re.match(r"#\s*@", line):
            return False
        if line.lstrip("#").split() == ["@package", "_global_"]:
            return True
    return False


def names_itself(dirs: Iterable[Path], group: str, option: str, key: str,
                 _seen: frozenset = frozenset()) -> bool | None:
    """Whether the file of ``group=option`` (:func:`option_file`) sets ``group.key``,
    itself or through an option of its group that it builds on (:func:`option_bases`);
    None where no such file is found or read (a config of another source: not checked
    here)."""
    dirs = list(dirs)
    path = option_file(dirs, group, option)
    if path is None or option in _seen:
        return None
    try:
        text = path.read_text()
        data = yaml.safe_load(text)
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return None
    if data is None:
        return False
    if not isinstance(data, dict):
        return None
    node = data.get(group) if global_package(text) else data
    if isinstance(node, dict) and key in node:
        return True
    return any(names_itself(dirs, group, base, key, _seen | {option})
               for base in option_bases(data, group))


def check_group_choices(choices: Mapping[str, Any], cfg: Any, dirs: Iterable[Path],
                        overrides: Iterable[str] = (),
                        registered: Mapping[str, Collection[str]] | None = None) -> None:
    """Refuse an option named as a registered mode, learner or channel model whose file
    does not select it: a ``masking/cautious.yaml`` without ``mode: cautious`` (nor an
    option it builds on with a mode) leaves the schema's ``rank``, and
    ``masking=cautious``, after the user added the ``cautious`` mode and its rule, would
    train rank masks in a folder, under labels, that say cautious. An option of another
    name is a variant of what its file composes (``masking/rank_literal.yaml`` holding
    ``recoverable: false`` runs rank masks), as it always was; the key typed on the
    command line is the user's choice, and a preset's value over the file's. ``choices``:
    each group's option (Hydra's ``runtime.choices``); ``cfg``: the composed config (the
    value that would run, for the message); ``dirs``: the config folders, in Hydra's
    order; ``overrides``: the command line's; ``registered``: per group, the names its
    registry holds (``ALGORITHMS``, ``CHANNELS``, the masking modes: the groups it
    leaves out are not checked). A resumed run's settings are its own (made before this
    check, perhaps): not checked. The :class:`ConfigError`'s ``key`` is the group."""
    typed = {override_key(o) for o in overrides}
    if "resume" in typed:
        return
    dirs = list(dirs)
    for group, key in SELF_NAMES.items():
        option = choices.get(group)
        if option is None or f"{group}.{key}" in typed or group not in (registered or {}):
            continue
        option = str(option)
        if (option.rsplit("/", 1)[-1] in registered[group]
                and names_itself(dirs, group, option, key) is False):
            section = cfg.get(group) if isinstance(cfg, Mapping) else getattr(cfg, group)
            value = (section.get(key) if isinstance(section, Mapping)
                     else getattr(section, key, None))
            value = getattr(value, "value", value)  # an enum member (masking.mode)
            leaf = option.rsplit("/", 1)[-1]
            err = ConfigError(
                f"{group}={option}: its file ({option_file(dirs, group, option)}) sets no "
                f"{key}, nor does an option it builds on, so it would run {value} under "
                f"the name of the registered {leaf}. Add the line '{key}: {leaf}' to it.")
            err.key = group
            raise err
