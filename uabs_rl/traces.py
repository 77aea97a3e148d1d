"""Vehicle traces: run SUMO once, cache padded position tensors, load them back.

A split (``train``, ``eval`` (validation) or ``test``) is a :class:`TraceSet` of
``n_sims`` simulations:
``positions [n_sims, steps, max_vehicles, 2]`` (metres, relative to the area's
lower-left corner) and ``present [n_sims, steps, max_vehicles]``. Each split is
cached in one file whose name is a hash of everything that changes it (network and
route file contents, fleet size, seeds, durations, δt, area, SUMO version, format).
A cache file is written atomically and checked on load (keys, shapes, dtypes, a
checksum of the data); a corrupt or truncated one is reported and rebuilt.

CLI: ``uabs-traces`` (Hydra; same ``scenario``/``traces`` overrides as training).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import pickle
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from uabs_rl.config import (
    PROJECT_ROOT,
    TRACE_SPLITS,
    ConfigError,
    ScenarioConfig,
    SplitConfig,
    TracesAppConfig,
    TracesConfig,
    resolve_path,
    validate_scenario_traces,
)
from uabs_rl.sumo_sim import SimRequest, SimResult, SumoRunError, load_result, run_simulation

log = logging.getLogger(__name__)

FORMAT_VERSION = 2
SPLITS = TRACE_SPLITS


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


# ----------------------------------------------------------------------------- keys
def _sha256_file(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _sumo_version() -> str:
    from importlib.metadata import version

    return version("eclipse-sumo")


def scenario_inputs(scenario: ScenarioConfig) -> dict[str, Any]:
    """Resolved input files of the scenario, with the config key that names each."""
    sumo = scenario.sumo
    if sumo.sumocfg:
        return {"sumocfg": resolve_path(sumo.sumocfg, "scenario.sumo.sumocfg"),
                "net_file": None, "route_files": []}
    routes = [resolve_path(r, f"scenario.sumo.route_files[{i}]")
              for i, r in enumerate(sumo.route_files)]
    return {"sumocfg": None, "net_file": net_file(sumo.net_file), "route_files": routes}


def netgenerate_path() -> str:
    """SUMO's netgenerate: on the PATH, else beside this Python (the eclipse-sumo wheel
    installs it into the virtual environment's bin/)."""
    return shutil.which("netgenerate") or str(Path(sys.executable).parent / "netgenerate")


def net_file(value: str) -> Path:
    """The network file ``scenario.sumo.net_file``; a ``<name>.net.xml`` that does not
    exist yet but has its ``<name>.netgcfg`` beside it (a network too big to keep in
    the repository, such as sumo/city) is built with netgenerate first."""
    try:
        return resolve_path(value, "scenario.sumo.net_file")
    except ConfigError:
        if not value.endswith(".net.xml"):
            raise
        cfg_name = Path(value).name[: -len(".net.xml")] + ".netgcfg"
        for base in (Path.cwd(), PROJECT_ROOT):
            source = (base / value).parent / cfg_name
            if source.is_file():
                break
        else:
            raise
    target = source.parent / Path(value).name
    exe = netgenerate_path()
    log.info("building %s from %s with netgenerate", target, source.name)
    tmp = target.with_name(f".tmp{os.getpid()}.{target.name}")  # no half-written network
    proc = subprocess.run([exe, "-c", source.name, "--output-file", tmp.name],
                          cwd=source.parent, capture_output=True, text=True)
    if proc.returncode == 0 and tmp.is_file():
        os.replace(tmp, target)
    else:
        tmp.unlink(missing_ok=True)
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        raise ConfigError(f"scenario.sumo.net_file: building {target} from {source} with "
                          f"netgenerate failed: {' | '.join(tail)}. Run it by hand to see why.")
    return target.resolve()


def split_key(scenario: ScenarioConfig, split_cfg: SplitConfig,
              split: str) -> tuple[str, dict[str, Any]]:
    """Cache key and the description it hashes: every parameter that changes traces."""
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
    digest = hashlib.sha256(json.dumps(desc, sort_keys=True).encode()).hexdigest()[:16]
    return f"{scenario.name}-{split}-{digest}", desc


# ----------------------------------------------------------------------------- file io
def _checksum(positions: torch.Tensor, present: torch.Tensor) -> str:
    h = hashlib.sha256(positions.contiguous().numpy().tobytes())
    h.update(present.contiguous().numpy().tobytes())
    return h.hexdigest()


def save_traceset(ts: TraceSet, path: Path) -> None:
    """Write atomically: a crash never leaves a half-written cache file behind."""
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(ts.meta, checksum=_checksum(ts.positions, ts.present))
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    torch.save({"positions": ts.positions, "present": ts.present,
                "meta_json": json.dumps(meta)}, tmp)
    os.replace(tmp, path)


def load_traceset(path: Path) -> TraceSet:
    """Load and verify a cache file; raise :class:`TraceCacheError` if it is not sound."""
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # truncated zip, wrong format, ...
        raise TraceCacheError(f"cannot read {path}: {type(e).__name__}: {e}") from e
    if not isinstance(blob, dict) or not {"positions", "present", "meta_json"} <= blob.keys():
        raise TraceCacheError(f"{path} lacks the keys positions/present/meta_json")
    pos, pres = blob["positions"], blob["present"]
    try:
        meta = json.loads(blob["meta_json"])
    except (TypeError, json.JSONDecodeError) as e:
        raise TraceCacheError(f"{path} has unreadable metadata: {e}") from e
    if pos.dtype != torch.float32 or pres.dtype != torch.bool or pos.ndim != 4 \
            or pos.shape[:3] != pres.shape or pos.shape[-1] != 2:
        raise TraceCacheError(f"{path} has inconsistent tensors: positions "
                              f"{tuple(pos.shape)} {pos.dtype}, present {tuple(pres.shape)} "
                              f"{pres.dtype}")
    if meta.get("checksum") != _checksum(pos, pres):
        raise TraceCacheError(f"{path} fails its checksum: the data was altered or damaged")
    return TraceSet(pos, pres, meta, source="cache")


# ----------------------------------------------------------------------------- build
def read_net(net_file: Path | str):
    """The SUMO network of ``net_file`` (sumolib), or a ConfigError naming the key and
    the file when sumolib cannot read it."""
    import sumolib

    try:
        return sumolib.net.readNet(str(net_file), withInternal=True)
    except Exception as e:  # sumolib raises KeyError, ValueError, SAX errors, ...
        raise ConfigError(
            f"scenario.sumo.net_file: {net_file} is not a SUMO network sumolib can read "
            f"({type(e).__name__}: {str(e)[:120]}). Rebuild it with netgenerate or "
            f"netconvert (sumo/README.md), or point scenario.sumo.net_file at another "
            f"file.") from None


def check_area_contains_network(scenario: ScenarioConfig, net_file: Path | None) -> None:
    """Every lane (internal ones too) must lie inside the area: vehicles stay inside."""
    if net_file is None:
        return
    net = read_net(net_file)
    xs, ys = [], []
    for edge in net.getEdges(withInternal=True):
        for lane in edge.getLanes():
            for x, y in lane.getShape():
                xs.append(x)
                ys.append(y)
    a = scenario.area
    lo_x, lo_y, hi_x, hi_y = min(xs), min(ys), max(xs), max(ys)
    if lo_x < a.x_min or lo_y < a.y_min or hi_x > a.x_min + a.width \
            or hi_y > a.y_min + a.height:
        raise ConfigError(
            f"scenario.area (x {a.x_min}..{a.x_min + a.width}, y {a.y_min}.."
            f"{a.y_min + a.height}) does not contain the network's lanes (x {lo_x:.1f}.."
            f"{hi_x:.1f}, y {lo_y:.1f}..{hi_y:.1f}) of {net_file}. Set scenario.area.x_min/"
            f"y_min/width/height to a rectangle that contains them.")


def _requests(scenario: ScenarioConfig, split_cfg: SplitConfig) -> list[SimRequest]:
    files = scenario_inputs(scenario)
    dt = float(scenario.dt)
    return [SimRequest(
        seed=split_cfg.first_seed + i,
        net_file=str(files["net_file"]) if files["net_file"] else None,
        route_files=[str(p) for p in files["route_files"]],
        sumocfg=str(files["sumocfg"]) if files["sumocfg"] else None,
        fleet_size=int(scenario.sumo.fleet_size),
        dt=dt,
        warmup_steps=int(round(split_cfg.warmup_s / dt)),
        steps=int(round(split_cfg.duration_s / dt)),
        origin=(float(scenario.area.x_min), float(scenario.area.y_min)),
        extra_args=list(scenario.sumo.extra_args),
    ) for i in range(split_cfg.n_sims)]


def _run_in_subprocess(req: SimRequest, tmp: Path) -> SimResult:
    req_path, out_path = tmp / f"req{req.seed}.pkl", tmp / f"out{req.seed}.npz"
    req_path.write_bytes(pickle.dumps(req))
    proc = subprocess.run([sys.executable, "-m", "uabs_rl.sumo_sim", str(req_path),
                           str(out_path)], capture_output=True, text=True)
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-5:]
        raise SumoRunError(f"the SUMO worker for seed {req.seed} exited with code "
                           f"{proc.returncode}: " + " | ".join(tail))
    return load_result(req.seed, str(out_path))


def _run_all(requests: list[SimRequest], workers: int, desc: str) -> list[SimResult]:
    """Run the simulations, ``workers`` at a time (0 = one per core). Parallel runs are
    separate processes: libsumo holds one simulation per process."""
    n = min(len(requests), workers or os.cpu_count() or 1)
    bar = tqdm(total=len(requests), desc=desc, unit="sim", leave=False)
    try:
        if n <= 1:
            results = []
            for r in requests:
                results.append(run_simulation(r))
                bar.update()
            return results
        with tempfile.TemporaryDirectory(prefix="uabs_sumo_") as tmp, ThreadPoolExecutor(n) as pool:
            futures = [pool.submit(_run_in_subprocess, r, Path(tmp)) for r in requests]
            for f in futures:
                f.add_done_callback(lambda _: bar.update())
            return [f.result() for f in futures]
    finally:
        bar.close()


def _stack(results: list[SimResult]) -> tuple[torch.Tensor, torch.Tensor]:
    steps = results[0].positions.shape[0]
    slots = max(r.positions.shape[1] for r in results)
    pos = np.zeros((len(results), steps, slots, 2), dtype=np.float32)
    pres = np.zeros((len(results), steps, slots), dtype=bool)
    for i, r in enumerate(results):
        pos[i, :, : r.positions.shape[1]] = r.positions
        pres[i, :, : r.present.shape[1]] = r.present
    return torch.from_numpy(pos), torch.from_numpy(pres)


def build_split(scenario: ScenarioConfig, split_cfg: SplitConfig, split: str,
                workers: int = 0) -> TraceSet:
    """Run SUMO for every seed of the split and stack the traces (no caching)."""
    files = scenario_inputs(scenario)
    check_area_contains_network(scenario, files["net_file"])
    _, desc = split_key(scenario, split_cfg, split)
    requests = _requests(scenario, split_cfg)
    t0 = time.perf_counter()
    try:
        results = _run_all(requests, workers, f"SUMO {split}")
    except SumoRunError as e:
        raise SumoRunError(f"building {split} traces failed: {e}") from e
    pos, pres = _stack(results)
    meta = dict(desc, seeds=[r.seed for r in results],
                teleport_vehicle_steps=sum(r.teleports for r in results),
                build_seconds=round(time.perf_counter() - t0, 3))
    return TraceSet(pos, pres, meta)


def cache_dir(traces_cfg: TracesConfig) -> Path:
    """``traces.cache_dir``, or ``$UABS_RL_CACHE/traces`` (default ``~/.cache/uabs_rl``)."""
    if traces_cfg.cache_dir:
        return Path(str(traces_cfg.cache_dir)).expanduser()
    return Path(os.environ.get("UABS_RL_CACHE", "~/.cache/uabs_rl")).expanduser() / "traces"


def cache_path(scenario: ScenarioConfig, traces_cfg: TracesConfig, split: str) -> Path:
    key, _ = split_key(scenario, getattr(traces_cfg, split), split)
    return cache_dir(traces_cfg) / f"{key}.pt"


def get_traces(scenario: ScenarioConfig, traces_cfg: TracesConfig, split: str,
               verbose: bool = True) -> TraceSet:
    """The split's traces: from the cache when sound, else built with SUMO and cached."""
    if split not in SPLITS:
        raise ConfigError(f"split must be one of {SPLITS}, got {split!r}.")
    validate_scenario_traces(scenario, traces_cfg)
    path = cache_path(scenario, traces_cfg, split)
    if path.exists():
        try:
            ts = load_traceset(path)
            if verbose:
                log.info("traces %s: cache hit %s", split, path)
            return ts
        except TraceCacheError as e:
            log.warning("trace cache file is damaged, rebuilding it: %s", e)
    ts = build_split(scenario, getattr(traces_cfg, split), split, traces_cfg.workers)
    save_traceset(ts, path)
    if verbose:
        log.info("traces %s built in %.2f s -> %s\n  %s", split, ts.meta["build_seconds"], path,
                 ts.summary())
    return ts


# ----------------------------------------------------------------------------- CLI
def build(cfg: TracesAppConfig, _output_dir: Path | None = None) -> None:
    """Body of ``uabs-traces``: build or load the requested splits and say which."""
    splits = SPLITS if cfg.split == "all" else (cfg.split,)
    for split in splits:
        t0 = time.perf_counter()
        ts = get_traces(cfg.scenario, cfg.traces, split, verbose=False)
        how = "built with SUMO" if ts.source == "built" else "loaded from cache"
        print(f"{how} in {time.perf_counter() - t0:.2f} s: {ts.summary()}\n  "
              f"{cache_path(cfg.scenario, cfg.traces, split)}")


def main() -> None:
    """Entry point of ``uabs-traces``."""
    from uabs_rl.cli import hydra_main

    hydra_main("build_traces", build)


if __name__ == "__main__":
    main()
