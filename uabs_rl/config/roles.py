"""Which settings change results, derived from the one declaration of each setting's
:class:`~uabs_rl.config.base.Role` in the schemas. Every list that tells settings apart
is one of these:

============  ==========  ===============  ============  ==========  ============
role          run folder  tells runs apart  resume keeps  uabs-eval   baselines
                name      (report groups)                 may change  depend on it
============  ==========  ===============  ============  ==========  ============
runtime       no          no                no            no          no
label         yes         no                no            no          no
method        yes         no                yes           no          no
seed          yes         no                yes           no          no
world         yes         yes               yes           yes         yes
test          yes         yes               no            yes         yes
evaluation    yes         yes               no            no          yes
protocol      yes         yes               no            no          no
policy        yes         yes               yes           no          no
============  ==========  ===============  ============  ==========  ============

(``uabs-eval`` changes whole sections, those that hold a world setting, and ``device``.)
"""

from __future__ import annotations

from dataclasses import fields, is_dataclass
from functools import cache
from typing import Any

from uabs_rl.config.base import Role
from uabs_rl.config.schema import LEARNER_SCHEMAS, RunConfig

# never a reason to tell runs apart (sweep.NEUTRAL; the seed is what a group's runs
# differ in)
NEUTRAL_ROLES = (Role.runtime, Role.label, Role.method, Role.seed)
# what a resumed run keeps (checkpoint.COMPAT_KEYS)
RESUME_ROLES = (Role.method, Role.seed, Role.world, Role.policy)
# the settings the baselines depend on: groups that differ in one get their own Fig. 4
# panel (sweep.ENV_SETTINGS)
BASELINE_ROLES = (Role.world, Role.test, Role.evaluation)
# Hydra's own settings that change no result, left out of run folder names beside the
# runtime settings (conf/config.yaml's exclude_keys)
HYDRA_RUNTIME = ("hydra.launcher.n_jobs",)


def _walk(obj: Any, prefix: str, inherited: Role | None, out: dict[str, Role]) -> None:
    for f in fields(obj):
        key, value = f"{prefix}{f.name}", getattr(obj, f.name)
        r = f.metadata.get("role", inherited)
        if is_dataclass(value):
            _walk(value, f"{key}.", r, out)
        elif key not in out:
            if r is None:
                raise TypeError(f"{key} declares no role (uabs_rl.config.base.setting)")
            out[key] = Role(r)


@cache
def setting_roles() -> dict[str, Role]:
    """Every setting's role by its flat key (``traces.train.n_sims``), in the schemas'
    order, the own settings of each learner (``algo.mixing_embed_dim``) after the
    shared ``algo`` ones."""
    out: dict[str, Role] = {}
    _walk(RunConfig(), "", None, out)
    algo_role = next(f for f in fields(RunConfig) if f.name == "algo").metadata["role"]
    extra: dict[str, Role] = {}
    for schema in LEARNER_SCHEMAS.values():
        _walk(schema(), "algo.", algo_role, extra)
    keys = list(out)
    at = max(i for i, k in enumerate(keys) if k.startswith("algo.")) + 1
    merged = keys[:at] + [k for k in extra if k not in out] + keys[at:]
    return {k: out.get(k, extra.get(k)) for k in merged}


def keys_with_role(*roles: Role) -> tuple[str, ...]:
    """The settings (flat keys, in the schemas' order) of any of ``roles``."""
    return tuple(k for k, r in setting_roles().items() if r in roles)


def sections_with_role(*roles: Role) -> tuple[str, ...]:
    """The top-level sections that hold a setting of any of ``roles``, in order."""
    return tuple(dict.fromkeys(k.split(".", 1)[0] for k in keys_with_role(*roles)))


def folder_name_excludes() -> list[str]:
    """What Hydra leaves out of a run folder's name (``exclude_keys``): the runtime
    settings, and Hydra's own."""
    return [*keys_with_role(Role.runtime), *HYDRA_RUNTIME]
