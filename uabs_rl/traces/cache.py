"""The trace cache: :class:`TraceSet`, its key, and its files.

A split (``train``, ``eval`` (validation) or ``test``) is a :class:`TraceSet` of
``n_sims`` simulations:
``positions [n_sims, steps, max_vehicles, 2]`` (metres, relative to the area's
lower-left corner) and ``present [n_sims, steps, max_vehicles]``. Each split is
cached in one file whose name is a hash of everything that changes it (network and
route file contents, fleet size, seeds, durations, δt, area, SUMO version, format).
A cache file is written atomically and checked on load (keys, shapes, dtypes, a
checksum of the data, and the split and key it was saved under); a corrupt,
truncated or misplaced one is reported and rebuilt (:func:`uabs_rl.traces.build.get_traces`).
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from uabs_rl.config import (
    ConfigError,
    ScenarioConfig,
    SplitConfig,
    TracesConfig,
    resolved_split,
)
from uabs_rl.paths import atomic_file, check_path, inside, safe_component
from uabs_rl.traces.inputs import scenario_inputs, split_begin, sumocfg_inputs

log = logging.getLogger(__name__)

FORMAT_VERSION = 2


class CacheFolderError(ConfigError):
    """The trace cache folder ``folder`` cannot hold the traces, for ``reason`` (a file,
    not writable, full): the commands that take no ``traces.cache_dir`` (``uabs-report``)
    say how to give another."""

    def __init__(self, message: str, folder: Path, reason: str):
        super().__init__(message)
        self.folder, self.reason = folder, reason


class TraceCacheError(RuntimeError):
    """A cache file is unreadable or inconsistent."""


@dataclass
class TraceSet:
    positions: torch.Tensor  # [n_sims, steps, max_vehicles, 2] float32, metres from area origin
    present: torch.Tensor  # [n_sims, steps, max_vehicles] bool
    meta: dict[str, Any]
    source: str = "built"  # "built" (SUMO ran) or "cache"; not stored in the file

    @property
    def n_sims(self) -> int:
        return self.positions.shape[0]

    @property
    def steps(self) -> int:
        return self.positions.shape[1]

    @property
    def max_vehicles(self) -> int:
        return self.positions.shape[2]

    def summary(self) -> str:
        n = self.present.sum(-1).float()
        return (f"{self.meta['split']}: {self.n_sims} sims x {self.steps} steps x "
                f"{self.max_vehicles} slots, vehicles present per step "
                f"{n.mean():.1f} (min {n.min():.0f}, max {n.max():.0f})")


def _sha256_file(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _sumo_version() -> str:
    from importlib.metadata import version

    return version("eclipse-sumo")


def split_key(scenario: ScenarioConfig, split_cfg: SplitConfig,
              split: str) -> tuple[str, dict[str, Any]]:
    """Cache key and the description it hashes: every parameter that changes traces."""
    a = scenario.area
    for name, value in [("scenario.dt", scenario.dt), ("scenario.area.x_min", a.x_min),
                        ("scenario.area.y_min", a.y_min), ("scenario.area.width", a.width),
                        ("scenario.area.height", a.height),
                        (f"traces.{split}.duration_s", split_cfg.duration_s),
                        (f"traces.{split}.warmup_s", split_cfg.warmup_s),
                        (f"traces.{split}.begin_s", split_begin(split_cfg))]:
        if not math.isfinite(value):  # never a key (or a simulation) of nan / inf
            raise ConfigError(f"{name} must be a finite number, got {value}.")
    files = scenario_inputs(scenario)
    hashed = [p for p in [files["sumocfg"], files["net_file"], *files["route_files"]] if p]
    desc = {
        "format": FORMAT_VERSION,
        "split": split,
        "sumo_version": _sumo_version(),
        "input_sha256": {p.name: _sha256_file(p) for p in hashed},
        "fleet_size": scenario.sumo.fleet_size,
        "extra_args": list(scenario.sumo.extra_args),
        "area": [scenario.area.x_min, scenario.area.y_min,
                 scenario.area.width, scenario.area.height],
        "dt": scenario.dt,
        "first_seed": split_cfg.first_seed,
        "n_sims": split_cfg.n_sims,
        "duration_s": split_cfg.duration_s,
        "warmup_s": split_cfg.warmup_s,
    }
    if split_begin(split_cfg):  # keyed only when set: warm-up recordings keep their keys
        desc["begin_s"] = split_begin(split_cfg)
    if files["sumocfg"]:  # what the .sumocfg names: editing a route file is a new key
        cfg_dir = files["sumocfg"].parent  # names relative to it: no checkout path
        desc["sumocfg_inputs_sha256"] = {os.path.relpath(p, cfg_dir): _sha256_file(p) for p
                                         in sumocfg_inputs(files["sumocfg"])}
    return f"{scenario.name}-{split}-{_digest(desc)}", desc


def _digest(desc: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(desc, sort_keys=True, allow_nan=False).encode()
                          ).hexdigest()[:16]


def _not_this_key(meta: dict[str, Any], key: str, desc: dict[str, Any]) -> str | None:
    """What a loaded cache file holds when it is not the traces of ``key`` (a file
    copied or renamed onto another split's name), else None. A file written before the
    key was stored is checked on the description in its meta, which the key hashes."""
    if "cache_key" in meta:
        found = meta["cache_key"]
        return None if found == key else f"the {meta.get('split')} traces saved as {found}"
    if _digest({k: meta.get(k) for k in desc}) == _digest(desc):
        return None
    return f"the {meta.get('split')} traces of other parameters (saved without a key)"


def _checksum(positions: torch.Tensor, present: torch.Tensor) -> str:
    h = hashlib.sha256(positions.contiguous().numpy().tobytes())
    h.update(present.contiguous().numpy().tobytes())
    return h.hexdigest()


def save_traceset(ts: TraceSet, path: Path) -> None:
    """Write atomically: a crash, Ctrl-C or full disk never leaves a half-written cache
    file (nor its temporary file) behind, and never damages the previous file. A write
    that fails is a :class:`CacheFolderError` naming ``traces.cache_dir``."""
    meta = dict(ts.meta, checksum=_checksum(ts.positions, ts.present))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_file(path) as f:
            torch.save({"positions": ts.positions, "present": ts.present,
                        "meta_json": json.dumps(meta)}, f)
    except OSError as e:
        why = ("no space left on the device" if e.errno == errno.ENOSPC
               else e.strerror or str(e))
        raise CacheFolderError(f"traces.cache_dir: cannot write the trace cache file "
                               f"{path}: {why}. Free space in {path.parent} or set "
                               f"traces.cache_dir=<a folder with room>.", path.parent,
                               f"cannot write {path.name}: {why}") from None


def load_traceset(path: Path) -> TraceSet:
    """Load and verify a cache file; raise :class:`TraceCacheError` if it is not sound."""
    from uabs_rl.runs.checkpoint import UnreadableFile, read_weights

    damaged = f"{path} is damaged or not a trace cache"
    try:  # why torch refused it, in a few words (never torch's unsafe retry advice)
        blob = read_weights(path)
    except UnreadableFile as e:
        objects = f": {e.objects}" if e.objects else ""
        raise TraceCacheError(f"{damaged} ({e}{objects})") from None
    if not isinstance(blob, dict) or not {"positions", "present", "meta_json"} <= blob.keys():
        raise TraceCacheError(f"{damaged} (it lacks the keys positions/present/meta_json)")
    pos, pres = blob["positions"], blob["present"]
    try:
        meta = json.loads(blob["meta_json"])
    except (TypeError, json.JSONDecodeError) as e:
        raise TraceCacheError(f"{damaged} (unreadable metadata: {e})") from None
    if not isinstance(meta, dict) or not isinstance(pos, torch.Tensor) \
            or not isinstance(pres, torch.Tensor):
        raise TraceCacheError(f"{damaged} (its entries are not tensors and metadata)")
    if pos.dtype != torch.float32 or pres.dtype != torch.bool or pos.ndim != 4 \
            or pos.shape[:3] != pres.shape or pos.shape[-1] != 2:
        raise TraceCacheError(f"{damaged} (inconsistent tensors: positions "
                              f"{tuple(pos.shape)} {pos.dtype}, present {tuple(pres.shape)} "
                              f"{pres.dtype})")
    if meta.get("checksum") != _checksum(pos, pres):
        raise TraceCacheError(f"{damaged} (it fails its checksum: the data was altered)")
    return TraceSet(pos, pres, meta, source="cache")


def cache_dir(traces_cfg: TracesConfig) -> Path:
    """``traces.cache_dir``, or ``$UABS_RL_CACHE/traces`` (default ``~/.cache/uabs_rl``)."""
    if traces_cfg.cache_dir:
        return check_path(Path(str(traces_cfg.cache_dir)).expanduser(), "traces.cache_dir")
    return check_path(Path(os.environ.get("UABS_RL_CACHE", "~/.cache/uabs_rl")).expanduser()
                      / "traces", "traces.cache_dir (unset: $UABS_RL_CACHE/traces)")


def cache_path(scenario: ScenarioConfig, traces_cfg: TracesConfig, split: str,
               name_setting: str = "scenario.name") -> Path:
    """The cache file of the split: ``<cache_dir>/<scenario.name>-<split>-<hash>.pt``.
    The name must be a plain file name (``name_setting`` names it in the refusal) and
    the file lies inside the cache folder, whatever the name."""
    safe_component(scenario.name, name_setting)
    key, _ = split_key(scenario, resolved_split(scenario, traces_cfg, split), split)
    d = cache_dir(traces_cfg)
    return inside(d / f"{key}.pt", d, name_setting)


def check_cache_dir(traces_cfg: TracesConfig) -> Path:
    """The cache folder, made if missing and checked writable: a build that could not
    be cached fails before SUMO runs, naming ``traces.cache_dir``."""
    d = cache_dir(traces_cfg)
    key = "traces.cache_dir" if traces_cfg.cache_dir else \
        "traces.cache_dir (unset: $UABS_RL_CACHE/traces or ~/.cache/uabs_rl/traces)"
    if d.exists() and not d.is_dir():
        raise CacheFolderError(f"{key}: {d} is a file, not a folder. Set traces.cache_dir "
                               f"to a folder (it is made if missing).", d,
                               "a file, not a folder")
    try:
        d.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=d):
            pass
    except OSError as e:
        raise CacheFolderError(f"{key}: cannot write in {d} ({e.strerror or e}). Set "
                               f"traces.cache_dir to a folder you can write in.", d,
                               f"cannot write in it: {e.strerror or e}") from None
    return d


def load_cached(path: Path, key: str, desc: dict[str, Any]) -> TraceSet | None:
    """The cache file at ``path`` when it is sound and holds the traces of ``key``;
    else None, with one warning line when a file was there."""
    if not path.exists():
        return None
    try:
        ts = load_traceset(path)
    except TraceCacheError as e:
        log.warning("trace cache file %s; rebuilding it", e)
        return None
    other = _not_this_key(ts.meta, key, desc)
    if other is not None:
        log.warning("trace cache file %s holds %s, not the %s traces %s its name says; "
                    "rebuilding it", path, other, desc["split"], key)
        return None
    return ts
