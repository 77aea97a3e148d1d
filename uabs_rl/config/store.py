"""The schemas as Hydra sees them (its ConfigStore), composing a config as the commands
do, and turning a composed or stored config into checked dataclasses."""

from __future__ import annotations

from dataclasses import fields, is_dataclass
from functools import cache
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

from uabs_rl.config.base import ConfigError
from uabs_rl.config.roles import setting_roles
from uabs_rl.config.schema import (
    LEARNER_SCHEMAS,
    AlgoConfig,
    ChannelConfig,
    MaskingConfig,
    ObsConfig,
    RunConfig,
    ScenarioConfig,
    TracesAppConfig,
    TracesConfig,
    algo_schema,
)

PROJECT_ROOT = Path(__file__).resolve().parents[2]


def register_configs() -> None:
    cs = ConfigStore.instance()
    cs.store(group="scenario", name="scenario_schema", node=ScenarioConfig)
    cs.store(group="obs", name="obs_schema", node=ObsConfig)
    cs.store(group="channel", name="channel_schema", node=ChannelConfig)
    cs.store(group="masking", name="masking_schema", node=MaskingConfig)
    cs.store(name="traces_app_schema", node=TracesAppConfig)
    cs.store(group="traces", name="traces_schema", node=TracesConfig)
    cs.store(group="algo", name="algo_schema", node=AlgoConfig)
    for name, schema in LEARNER_SCHEMAS.items():  # conf/algo/<name>.yaml selects it
        cs.store(group="algo", name=f"{name}_schema", node=schema)
    cs.store(name="run_schema", node=RunConfig)


CONF_DIR = PROJECT_ROOT / "conf"


def compose(config_name: str = "config", overrides: list[str] | None = None) -> Any:
    """Compose a config as the CLI would (``config`` for uabs-train, ``build_traces``
    for uabs-traces) and return it as checked dataclasses: for notebooks and scripts."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = hydra_compose(config_name=config_name, overrides=list(overrides or []))
    return to_container(cfg)


def resolve_path(value: str, key: str) -> Path:
    """Resolve a config path against the cwd, then the project root; fail naming ``key``."""
    p = Path(value).expanduser()
    candidates = [p] if p.is_absolute() else [Path.cwd() / p, PROJECT_ROOT / p]
    for c in candidates:
        if c.is_file():
            return c.resolve()
    tried = ", ".join(str(c) for c in candidates)
    raise ConfigError(f"{key}: file not found: {value!r} (looked at {tried}). "
                      f"Set {key} to an existing file.")


def _check_known_keys(obj: Any, node: Any, prefix: str) -> None:
    """Refuse keys a dataclass does not have (``+key=...`` would otherwise vanish)."""
    if not (is_dataclass(obj) and isinstance(node, DictConfig)):
        return
    known = {f.name for f in fields(obj)}
    for key in node.keys():
        if key not in known:
            raise ConfigError(f"unknown config key {prefix}{key}: {type(obj).__name__} has "
                              f"{sorted(known)}. Remove it or fix its spelling.")
        _check_known_keys(getattr(obj, key), node._get_node(key), f"{prefix}{key}.")


def to_container(cfg: Any) -> Any:
    """Resolved dataclasses from a composed DictConfig; unknown keys are an error."""
    if isinstance(cfg, DictConfig):
        obj = OmegaConf.to_object(cfg)
        _check_known_keys(obj, cfg, "")
        return obj
    return cfg


def structured_run(stored: Any) -> DictConfig:
    """:class:`RunConfig` as OmegaConf's structured config, its ``algo`` section the
    schema of the learner ``stored`` (a stored config, a dict) names: what a stored config
    is merged into."""
    conf = OmegaConf.structured(RunConfig)
    algo = stored.get("algo") if hasattr(stored, "get") else None
    name = algo.get("name") if hasattr(algo, "get") else None
    if algo_schema(name) is not AlgoConfig:
        conf.algo = OmegaConf.structured(algo_schema(name))
    return conf


def flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    """A nested dict of settings as flat keys (``{"algo.lr": 1e-4, ...}``); lists stay
    whole."""
    if isinstance(d, dict):
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(flatten(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: d}


@cache
def default_settings() -> dict[str, Any]:
    """Every setting's default by flat key, as plain values (enums as strings), each
    learner's own settings included (``algo.mixing_embed_dim``), in the order of
    :func:`uabs_rl.config.roles.setting_roles`."""
    flat: dict[str, Any] = {}
    for run in (RunConfig(), *(RunConfig(algo=s()) for s in LEARNER_SCHEMAS.values())):
        d = OmegaConf.to_container(OmegaConf.structured(run), enum_to_str=True)
        for k, v in flatten(d).items():
            flat.setdefault(k, v)
    return {k: flat[k] for k in setting_roles()}


def own_learner_settings(algo: Any) -> Any:
    """A stored ``algo`` section without the settings of other learners: every run
    written before a learner's settings had a schema of their own stored
    ``mixing_embed_dim``, which only ``algo=qmix`` reads."""
    if not hasattr(algo, "get"):
        return algo
    own = {f.name for f in fields(algo_schema(algo.get("name")))}
    others = {f.name for s in LEARNER_SCHEMAS.values() for f in fields(s)} - own
    return {k: v for k, v in algo.items() if k not in others} if others & set(algo) else algo


def check_config_dirs(dirs: list[Path], chosen: list[tuple[str, str]],
                      flag: str = "--config-dir") -> None:
    """Each folder exists, and none holds an option of the same name as one of the
    package's that the command chooses (``chosen``: group, option): Hydra reads the
    package's ``conf/`` first, so ``uabs-train`` would ignore such a file of yours
    where ``uabs-eval`` reads it; refused in both."""
    for d in dirs:
        try:
            here = d.is_dir()
        except OSError as e:  # a name too long, a folder that cannot be searched
            raise ConfigError(f"{flag} {d}: cannot be read ({e.strerror}): give a folder "
                              f"you can read.") from None
        if not here:
            raise ConfigError(f"{flag} {d}: no such folder: give the folder that holds "
                              f"your <group>/<option>.yaml files (e.g. scenario/).")
        for group, option in chosen:
            mine, ours = d / group / f"{option}.yaml", CONF_DIR / group / f"{option}.yaml"
            if mine.is_file() and ours.is_file():
                raise ConfigError(
                    f"{flag} {d}: {mine} has the name of the package's "
                    f"conf/{group}/{option}.yaml, and Hydra reads the package's "
                    f"first: rename yours (e.g. {group}/my_{option}.yaml, chosen with "
                    f"{group}=my_{option}).")
