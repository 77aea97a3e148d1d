"""Vehicle traces: run SUMO once per simulation of a split, stack the positions into a
:class:`~uabs_rl.traces.cache.TraceSet`, and serve a split from the cache or build it
(:func:`get_traces`).

A parallel build runs each simulation in a worker process (``uabs_rl.traces.sumo_sim``)
whose scratch folder is ``$TMPDIR/uabs_sumo_<pid>_*``; the workers die with their
parent, a later build removes the folders of dead owners, and Ctrl-C or SIGTERM
stops every worker at once and caches nothing (:class:`TracesInterrupted`). A SUMO
refusal is reported as a :class:`~uabs_rl.config.ConfigError` naming the setting at
fault.

CLI: ``uabs-traces`` (Hydra; same ``scenario``/``traces`` overrides as training).
"""

from __future__ import annotations

import logging
import os
import pickle
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from uabs_rl.config import (
    TRACE_SPLITS,
    ConfigError,
    RunConfig,
    ScenarioConfig,
    SplitConfig,
    TracesConfig,
    demand_setting,
    family_scenarios,
    fixed_demand,
    resolved_split,
    validate_scenario_traces,
)
from uabs_rl.paths import inside, pid_alive, safe_component
from uabs_rl.traces.cache import (
    TraceSet,
    cache_dir,
    check_cache_dir,
    load_cached,
    save_traceset,
    split_key,
)
from uabs_rl.traces.inputs import check_area_contains_network, scenario_inputs, split_begin
from uabs_rl.traces.sumo_sim import (
    SimRequest,
    SimResult,
    SumoRunError,
    error_path,
    load_error,
    load_result,
    run_simulation,
)

log = logging.getLogger(__name__)

SPLITS = TRACE_SPLITS
WORK_PREFIX = "uabs_sumo_"  # scratch folders of parallel builds: uabs_sumo_<owner pid>_*


class TracesInterrupted(KeyboardInterrupt):
    """A trace build stopped on Ctrl-C or SIGTERM; its workers are stopped and nothing
    was cached. ``str()`` is the message for the user, ``exit_code`` the status to exit
    with (130 after SIGINT, 143 after SIGTERM)."""

    def __init__(self, message: str, exit_code: int = 130):
        super().__init__(message)
        self.exit_code = exit_code


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread to stop a build as Ctrl-C does."""


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
        warmup_steps=int(round((split_cfg.warmup_s + split_begin(split_cfg)) / dt)),
        steps=int(round(split_cfg.duration_s / dt)),
        origin=(float(scenario.area.x_min), float(scenario.area.y_min)),
        extra_args=list(scenario.sumo.extra_args),
    ) for i in range(split_cfg.n_sims)]


class _Workers:
    """The SUMO worker processes of one parallel build, each started by a pool thread;
    :meth:`stop` kills the running ones and keeps queued ones from starting."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.procs: set[subprocess.Popen] = set()
        self.lock = threading.Lock()
        self.stopped = False

    def run(self, req: SimRequest) -> SimResult | None:
        req_path, out_path = self.folder / f"req{req.seed}.pkl", self.folder / f"out{req.seed}.npz"
        req_path.write_bytes(pickle.dumps(req))
        with self.lock:
            if self.stopped:
                return None
            proc = subprocess.Popen(
                [sys.executable, "-m", "uabs_rl.traces.sumo_sim", str(req_path), str(out_path),
                 str(os.getpid())], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            self.procs.add(proc)
        try:
            out, err = proc.communicate()
        finally:
            with self.lock:
                self.procs.discard(proc)
        if self.stopped:
            return None
        if proc.returncode == 2 and os.path.isfile(error_path(str(out_path))):
            raise load_error(error_path(str(out_path)))
        if proc.returncode != 0:
            tail = (err or out).strip().splitlines()[-5:]
            raise SumoRunError(f"the SUMO worker for seed {req.seed} exited with code "
                               f"{proc.returncode}: " + " | ".join(tail))
        return load_result(req.seed, str(out_path))

    def stop(self) -> None:
        with self.lock:
            self.stopped = True
            for proc in self.procs:
                proc.kill()


def remove_stale_work_folders() -> list[Path]:
    """Remove the scratch folders of parallel builds whose owner process is gone (killed
    with -9, say); return them."""
    removed = []
    for folder in Path(tempfile.gettempdir()).glob(f"{WORK_PREFIX}*_*"):
        pid = folder.name[len(WORK_PREFIX):].split("_")[0]
        if folder.is_dir() and pid.isdigit() and not pid_alive(int(pid)):
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(folder)
    return removed


def _run_all(requests: list[SimRequest], workers: int, desc: str) -> list[SimResult]:
    """Run the simulations, ``workers`` at a time (0 = one per core). Parallel runs are
    separate processes: libsumo holds one simulation per process."""
    n = min(len(requests), workers or os.cpu_count() or 1)
    # on a terminal only (disable=None): a log file or a pipe gets the "built" line alone
    bar = tqdm(total=len(requests), desc=desc, unit="sim", leave=False, disable=None)
    try:
        if n <= 1:
            results = []
            for r in requests:
                results.append(run_simulation(r))
                bar.update()
            return results
        return _run_parallel(requests, n, bar)
    finally:
        bar.close()


def _run_parallel(requests: list[SimRequest], n: int, bar) -> list[SimResult]:
    """``n`` worker processes at a time. The first failure, Ctrl-C or SIGTERM stops them
    all at once (queued runs are cancelled, running ones killed)."""
    folder = Path(tempfile.mkdtemp(prefix=f"{WORK_PREFIX}{os.getpid()}_"))
    workers = _Workers(folder)
    pool = ThreadPoolExecutor(n)
    try:
        futures = [pool.submit(workers.run, r) for r in requests]
        for f in futures:
            f.add_done_callback(lambda _: bar.update())
        for f in as_completed(futures):
            f.result()  # raises the first failure as soon as it happens
        return [f.result() for f in futures]
    except BaseException:
        workers.stop()
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        shutil.rmtree(folder, ignore_errors=True)


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
                workers: int = 0, begin_given: bool = True) -> TraceSet:
    """Run SUMO for every seed of the split and stack the traces (no caching).
    ``begin_given``: ``traces.<split>.begin_s`` was set (else it follows the earlier
    splits), for the advice on traces without a vehicle."""
    files = scenario_inputs(scenario)
    check_area_contains_network(scenario, files["net_file"])
    key, desc = split_key(scenario, split_cfg, split)
    requests = _requests(scenario, split_cfg)
    remove_stale_work_folders()
    t0 = time.perf_counter()
    try:
        results = _run_all(requests, workers, f"SUMO {split}")
    except SumoRunError as e:
        raise _sumo_refused(e, scenario, files, split) from None
    pos, pres = _stack(results)
    meta = dict(desc, cache_key=key, seeds=[r.seed for r in results],
                teleport_vehicle_steps=sum(r.teleports for r in results),
                build_seconds=round(time.perf_counter() - t0, 3))
    ts = TraceSet(pos, pres, meta)
    check_has_vehicles(ts, scenario, split, begin_given)
    return ts


_FIXES = {
    "scenario.sumo.sumocfg": "Fix the file or point {key} at another one.",
    "scenario.sumo.route_files": "Fix the file or remove it from {key}.",
    "scenario.sumo.net_file": "Fix the network or point {key} at another one.",
    "scenario.sumo.extra_args": "Fix or remove the argument (sumo --help lists them).",
}


def _sumo_refused(e: SumoRunError, scenario: ScenarioConfig, files: dict[str, Any],
                  split: str) -> Exception:
    """A SUMO failure as the user's error: a ConfigError naming the config key at fault
    and SUMO's own words when SUMO refused an input; else (a crashed worker) the
    SumoRunError itself."""
    if not (e.said or e.key):
        return SumoRunError(f"building the {split} traces failed: {e}")
    said = (e.said or str(e)).strip()
    key, what = _key_at_fault(e, said, scenario.sumo.extra_args, files)
    stop = "" if said.endswith((".", "?", "!")) else "."
    return ConfigError(f"{key}: SUMO refused {what} while building the {split} traces: "
                       f"{said}{stop} " + _FIXES[key].format(key=key))


def _key_at_fault(e: SumoRunError, said: str, extra_args: list[str],
                  files: dict[str, Any]) -> tuple[str, str]:
    """The config key a SUMO refusal is about, and its value: the input file SUMO's
    words name, else the extra argument they name, else the input in use."""
    inputs = [("scenario.sumo.sumocfg", files["sumocfg"]),
              *[("scenario.sumo.route_files", p) for p in files["route_files"]],
              ("scenario.sumo.net_file", files["net_file"])]
    if e.key:  # the network (given directly or by the .sumocfg) cannot hold the fleet
        return next((k, str(p)) for k, p in inputs if p and k != "scenario.sumo.route_files")
    for key, path in inputs:
        if path and (str(path) in said or path.name in said):
            return key, str(path)
    args = [a.lstrip("-") for a in extra_args]
    if extra_args and ("option" in said.lower() or any(len(a) > 1 and a in said for a in args)):
        return "scenario.sumo.extra_args", str(list(extra_args))
    if files["sumocfg"]:
        return "scenario.sumo.sumocfg", str(files["sumocfg"])
    if files["route_files"]:
        return "scenario.sumo.route_files", ", ".join(map(str, files["route_files"]))
    if extra_args:
        return "scenario.sumo.extra_args", str(list(extra_args))
    return "scenario.sumo.net_file", str(files["net_file"])


def check_has_vehicles(ts: TraceSet, scenario: ScenarioConfig, split: str,
                       begin_given: bool = True) -> None:
    """Traces without a vehicle inside the area would train on a reward of 0: refused.
    ``begin_given``: ``traces.<split>.begin_s`` was set, not resolved after the earlier
    splits (:func:`~uabs_rl.config.split_begin`)."""
    a = scenario.area
    x, y = ts.positions[..., 0], ts.positions[..., 1]
    inside = ts.present & (x >= 0) & (y >= 0) & (x <= a.width) & (y <= a.height)
    if inside.any():
        return
    sumo = scenario.sumo
    source = (f"scenario.sumo.sumocfg ({sumo.sumocfg})" if sumo.sumocfg else
              f"scenario.sumo.route_files ({', '.join(sumo.route_files) or 'none'})")
    if ts.present.any():
        raise ConfigError(
            f"the {split} traces hold no vehicle inside scenario.area (x {a.x_min}.."
            f"{a.x_min + a.width}, y {a.y_min}..{a.y_min + a.height}): the vehicles of "
            f"{source} drive elsewhere. Set scenario.area to the rectangle they drive in.")
    begin = ts.meta.get("begin_s")
    when = (f"{ts.meta.get('warmup_s')} + {ts.meta.get('duration_s')} s simulated" if not begin
            else f"{ts.meta.get('duration_s')} s recorded from {ts.meta.get('warmup_s')} + "
                 f"{begin} s on")
    within = "warmup_s + duration_s" if not begin else "warmup_s + begin_s + duration_s"
    if begin and fixed_demand(scenario):  # recorded late
        fix = (f"Move traces.{split}.begin_s earlier, or leave the begin_s settings null "
               f"(the splits then follow one another from the start)" if begin_given else
               f"traces.{split}.begin_s is null, so the {split} range follows the earlier "
               f"splits': shorten their duration_s, or set traces.{split}.begin_s to a "
               f"time its vehicles drive in (the splits' ranges must stay disjoint)")
        raise ConfigError(
            f"the {split} traces hold no vehicle: {source} put none on the roads in the "
            f"{when}: its vehicles depart at the times its files give, and none drives "
            f"in that range (past the end of its demand?). {fix}.")
    raise ConfigError(
        f"the {split} traces hold no vehicle: scenario.sumo.fleet_size is "
        f"{sumo.fleet_size} and {source} put none on the roads in the {when}. Set "
        f"scenario.sumo.fleet_size >= 1 or give routes whose vehicles depart within "
        f"traces.{split}.{within}.")


def thinning(ts: TraceSet, scenario: ScenarioConfig, split: str,
             begin_given: bool = True) -> str | None:
    """Words for a fixed demand's traces whose vehicles thin out within the recorded range
    (the last tenth of the steps holds under half the vehicles of the first: a range past
    the end of the demand, or in its draining), else None. A fleet keeps its size."""
    if not fixed_demand(scenario) or ts.steps < 10:
        return None
    tenth = ts.steps // 10
    per_step = ts.present.float().sum(-1).mean(0)  # [steps], mean over the simulations
    first, last = float(per_step[:tenth].mean()), float(per_step[-tenth:].mean())
    if first <= 0 or last >= first / 2:
        return None
    fix = (f"Move traces.{split}.begin_s earlier (or leave it null) to record while it "
           f"lasts." if begin_given else
           f"traces.{split}.begin_s is null, so the {split} range follows the earlier "
           f"splits': shorten their duration_s to record it while the demand lasts.")
    return (f"the {split} traces' vehicles thin out within the recorded range, from "
            f"{first:.0f} present per step in its first tenth to {last:.0f} in its last: "
            f"the demand of {demand_setting(scenario)} ends or drains there. {fix}")


@contextmanager
def _sigterm_interrupts() -> Iterator[None]:
    """SIGTERM stops a build as Ctrl-C does (in the main thread; elsewhere nothing)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame) -> None:
        stop = _Terminated()
        stop.exit_code = 128 + signum  # 143 after SIGTERM, 129 after SIGHUP
        raise stop

    previous = signal.signal(signal.SIGTERM, interrupt)
    hangup = signal.getsignal(signal.SIGHUP)
    if hangup is not signal.SIG_IGN:  # a closed terminal stops a build as SIGTERM does
        signal.signal(signal.SIGHUP, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)
        signal.signal(signal.SIGHUP, signal.SIG_DFL if hangup is None else hangup)


def get_traces(scenario: ScenarioConfig, traces_cfg: TracesConfig, split: str,
               verbose: bool = True, name_setting: str = "scenario.name") -> TraceSet:
    """The split's traces: from the cache when sound, else built with SUMO and cached.
    ``name_setting`` is the setting that named the scenario (``family[i].name`` for a
    family's city), for the refusal of a name that is not a plain file name."""
    if split not in SPLITS:
        raise ConfigError(f"split must be one of {SPLITS}, got {split!r}.")
    safe_component(scenario.name, name_setting)  # it names the cache file
    validate_scenario_traces(scenario, traces_cfg)
    split_cfg = resolved_split(scenario, traces_cfg, split)
    key, desc = split_key(scenario, split_cfg, split)
    d = cache_dir(traces_cfg)
    path = inside(d / f"{key}.pt", d, name_setting)
    ts = load_cached(path, key, desc)
    begin_given = getattr(traces_cfg, split).begin_s is not None
    if ts is not None:
        check_has_vehicles(ts, scenario, split, begin_given)  # cached before this check
        _warn_thinning(ts, scenario, split, begin_given)
        if verbose:
            log.info("traces %s: cache hit %s", split, path)
        return ts
    check_cache_dir(traces_cfg)
    try:
        with _sigterm_interrupts():
            ts = build_split(scenario, split_cfg, split, traces_cfg.workers, begin_given)
            save_traceset(ts, path)
    except TracesInterrupted:
        raise
    except KeyboardInterrupt as e:
        raise TracesInterrupted(f"interrupted while building the {split} traces: nothing "
                                f"was cached; run the command again to build them",
                                getattr(e, "exit_code", 143) if isinstance(e, _Terminated)
                                else 130) from None
    if verbose:
        log.info("traces %s built in %.2f s -> %s\n  %s", split, ts.meta["build_seconds"], path,
                 ts.summary())
    _warn_thinning(ts, scenario, split, begin_given)
    return ts


def _warn_thinning(ts: TraceSet, scenario: ScenarioConfig, split: str,
                   begin_given: bool) -> None:
    """A warning line for traces whose fixed demand thins out (:func:`thinning`): at
    every load, so a run's log says it too."""
    words = thinning(ts, scenario, split, begin_given)
    if words:
        log.warning(words)


def stack_cities(sets: list[TraceSet], areas: list[tuple[float, float]],
                 names: list[str]) -> TraceSet:
    """Several cities' traces as one (a family, ``RunConfig.family``): their simulations
    side by side, vehicle slots padded (absent) to the largest fleet's, steps cut to the
    shortest; ``meta`` says each simulation's city (``city_of_sim``) and each city's
    (W, H) (``city_area``), which ``UABSEnv`` reads."""
    steps = min(s.steps for s in sets)
    v = max(s.max_vehicles for s in sets)
    n = sum(s.n_sims for s in sets)
    pos = torch.zeros(n, steps, v, 2)
    present = torch.zeros(n, steps, v, dtype=torch.bool)
    city_of_sim: list[int] = []
    for c, s in enumerate(sets):
        i = len(city_of_sim)
        pos[i:i + s.n_sims, :, :s.max_vehicles] = s.positions[:, :steps]
        present[i:i + s.n_sims, :, :s.max_vehicles] = s.present[:, :steps]
        city_of_sim += [c] * s.n_sims
    meta = {**sets[0].meta, "cities": list(names), "city_of_sim": city_of_sim,
            "city_area": [[float(w), float(h)] for w, h in areas]}
    return TraceSet(pos, present, meta, source="family")


def check_names(cfg: RunConfig) -> None:
    """``scenario.name`` and every ``family[i].name`` name trace cache files: each must
    be a plain file name (:func:`uabs_rl.paths.safe_component`)."""
    safe_component(cfg.scenario.name, "scenario.name")
    for i, city in enumerate(family_scenarios(cfg)):
        safe_component(city.name, f"family[{i}].name")


def training_traces(cfg: RunConfig) -> TraceSet:
    """The training traces of ``cfg``: its scenario's, or every city of its family
    stacked (:func:`stack_cities`), each built with SUMO or read from the cache."""
    cities = family_scenarios(cfg)
    if not cities:
        return get_traces(cfg.scenario, cfg.traces, "train")
    check_names(cfg)
    sets = []
    for i, city in enumerate(cities):
        ts = get_traces(city, cfg.traces, "train", name_setting=f"family[{i}].name")
        log.info("family city %s: %s", city.name, ts.summary())
        sets.append(ts)
    return stack_cities(sets, [(c.area.width, c.area.height) for c in cities],
                        [c.name for c in cities])
