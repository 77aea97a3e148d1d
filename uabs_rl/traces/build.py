"""Vehicle traces: run SUMO once, cache padded position tensors, load them back.

A split (``train``, ``eval`` (validation) or ``test``) is a :class:`TraceSet` of
``n_sims`` simulations:
``positions [n_sims, steps, max_vehicles, 2]`` (metres, relative to the area's
lower-left corner) and ``present [n_sims, steps, max_vehicles]``. Each split is
cached in one file whose name is a hash of everything that changes it (network and
route file contents, fleet size, seeds, durations, δt, area, SUMO version, format).
A cache file is written atomically and checked on load (keys, shapes, dtypes, a
checksum of the data, and the split and key it was saved under); a corrupt,
truncated or misplaced one is reported and rebuilt.

A parallel build runs each simulation in a worker process (``uabs_rl.traces.sumo_sim``)
whose scratch folder is ``$TMPDIR/uabs_sumo_<pid>_*``; the workers die with their
parent, a later build removes the folders of dead owners, and Ctrl-C or SIGTERM
stops every worker at once and caches nothing (:class:`TracesInterrupted`).

CLI: ``uabs-traces`` (Hydra; same ``scenario``/``traces`` overrides as training).
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import math
import os
import pickle
import re
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
    RunConfig,
    ScenarioConfig,
    SplitConfig,
    TracesConfig,
    family_scenarios,
    resolve_path,
    resolved_split,
    validate_scenario_traces,
)
from uabs_rl.paths import check_path, inside, pid_alive, safe_component
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

FORMAT_VERSION = 2
SPLITS = TRACE_SPLITS
WORK_PREFIX = "uabs_sumo_"  # scratch folders of parallel builds: uabs_sumo_<owner pid>_*


class TraceCacheError(RuntimeError):
    """A cache file is unreadable or inconsistent."""


class TracesInterrupted(KeyboardInterrupt):
    """A trace build stopped on Ctrl-C or SIGTERM; its workers are stopped and nothing
    was cached. ``str()`` is the message for the user, ``exit_code`` the status to exit
    with (130 after SIGINT, 143 after SIGTERM)."""

    def __init__(self, message: str, exit_code: int = 130):
        super().__init__(message)
        self.exit_code = exit_code


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread to stop a build as Ctrl-C does."""


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


def _refuse_folder(value: str, key: str, suffix: str) -> None:
    """A folder given where a file is expected: say so (resolve_path would say "file
    not found"), and name the ``suffix`` files it holds."""
    p = Path(value).expanduser()
    candidates = [p] if p.is_absolute() else [Path.cwd() / p, PROJECT_ROOT / p]
    if any(c.is_file() for c in candidates):
        return
    for c in candidates:
        if c.is_dir():
            inside = sorted(f.name for f in c.glob(f"*{suffix}"))
            such = f", such as {value.rstrip('/')}/{inside[0]}" if inside else ""
            raise ConfigError(f"{key}: {value!r} is a folder ({c.resolve()}), not a {suffix} "
                              f"file. Set {key} to a {suffix} file{such}.")


def _input_file(value: str, key: str, suffix: str) -> Path:
    _refuse_folder(value, key, suffix)
    return resolve_path(value, key)


def scenario_inputs(scenario: ScenarioConfig) -> dict[str, Any]:
    """Resolved input files of the scenario, with the config key that names each."""
    sumo = scenario.sumo
    if sumo.sumocfg:
        return {"sumocfg": _input_file(sumo.sumocfg, "scenario.sumo.sumocfg", ".sumocfg"),
                "net_file": None, "route_files": []}
    routes = [_input_file(r, f"scenario.sumo.route_files[{i}]", ".rou.xml")
              for i, r in enumerate(sumo.route_files)]
    return {"sumocfg": None, "net_file": net_file(sumo.net_file), "route_files": routes}


def netgenerate_path() -> str:
    """SUMO's netgenerate: on the PATH, else beside this Python (the eclipse-sumo wheel
    installs it into the virtual environment's bin/)."""
    return shutil.which("netgenerate") or str(Path(sys.executable).parent / "netgenerate")


def _normalise_header(path: Path, final_name: str) -> None:
    """Drop what differs between two builds of one network from netgenerate's header
    comment: its start time and the (temporary) output name. The trace cache key hashes
    the network file, so without this every checkout's first build would key (and
    build) its traces anew."""
    text = path.read_text()
    head, sep, rest = text.partition("-->")
    head = re.sub(r"generated on \S+ by", "generated by", head).replace(path.name,
                                                                        final_name)
    path.write_text(head + sep + rest)


def net_file(value: str) -> Path:
    """The network file ``scenario.sumo.net_file``; a ``<name>.net.xml`` that does not
    exist yet but has its ``<name>.netgcfg`` beside it (a network too big to keep in
    the repository, such as sumo/city) is built with netgenerate first."""
    _refuse_folder(value, "scenario.sumo.net_file", ".net.xml")
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
        _normalise_header(tmp, target.name)
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
    a = scenario.area
    for name, value in [("scenario.dt", scenario.dt), ("scenario.area.x_min", a.x_min),
                        ("scenario.area.y_min", a.y_min), ("scenario.area.width", a.width),
                        ("scenario.area.height", a.height),
                        (f"traces.{split}.duration_s", split_cfg.duration_s),
                        (f"traces.{split}.warmup_s", split_cfg.warmup_s),
                        (f"traces.{split}.begin_s", _begin(split_cfg))]:
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
    if _begin(split_cfg):  # keyed only when set: recordings from the warm-up on keep their keys
        desc["begin_s"] = _begin(split_cfg)
    if files["sumocfg"]:  # what the .sumocfg names: editing a route file is a new key
        cfg_dir = files["sumocfg"].parent  # names relative to it: no checkout path
        desc["sumocfg_inputs_sha256"] = {os.path.relpath(p, cfg_dir): _sha256_file(p) for p
                                         in sumocfg_inputs(files["sumocfg"])}
    return f"{scenario.name}-{split}-{_digest(desc)}", desc


def _begin(split_cfg: SplitConfig) -> float:
    """The split's ``begin_s`` (null read as 0: callers pass :func:`resolved_split`)."""
    return float(split_cfg.begin_s or 0.0)


def sumocfg_inputs(sumocfg: Path) -> list[Path]:
    """The existing files a .sumocfg's ``<input>`` section names (network, routes,
    additional files), relative to the .sumocfg's folder as SUMO reads them, in the
    order given; [] when the file is no XML this can read (SUMO says why when it runs)."""
    import xml.etree.ElementTree as ET

    try:
        root = ET.parse(sumocfg).getroot()
    except (ET.ParseError, OSError):
        return []
    found: list[Path] = []
    for option in ("net-file", "route-files", "additional-files"):
        for el in root.iter(option):
            for name in re.split(r"[,\s]+", el.get("value", "").strip()):
                p = Path(name) if Path(name).is_absolute() else sumocfg.parent / name
                if name and p.is_file() and p not in found:
                    found.append(p)
    return found


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


# ----------------------------------------------------------------------------- file io
def _checksum(positions: torch.Tensor, present: torch.Tensor) -> str:
    h = hashlib.sha256(positions.contiguous().numpy().tobytes())
    h.update(present.contiguous().numpy().tobytes())
    return h.hexdigest()


def save_traceset(ts: TraceSet, path: Path) -> None:
    """Write atomically: a crash, Ctrl-C or full disk never leaves a half-written cache
    file (nor its temporary file) behind, and never damages the previous file. A write
    that fails is a ConfigError naming ``traces.cache_dir``."""
    meta = dict(ts.meta, checksum=_checksum(ts.positions, ts.present))
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:  # through a Python file: a full disk is ENOSPC
            torch.save({"positions": ts.positions, "present": ts.present,
                        "meta_json": json.dumps(meta)}, f)
        os.replace(tmp, path)
    except BaseException as e:
        tmp.unlink(missing_ok=True)
        if not isinstance(e, OSError):
            raise
        why = ("no space left on the device" if e.errno == errno.ENOSPC
               else e.strerror or str(e))
        raise ConfigError(f"traces.cache_dir: cannot write the trace cache file {path}: "
                          f"{why}. Free space in {path.parent} or set traces.cache_dir="
                          f"<a folder with room>.") from None


def load_traceset(path: Path) -> TraceSet:
    """Load and verify a cache file; raise :class:`TraceCacheError` if it is not sound."""
    damaged = f"{path} is damaged or not a trace cache"
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:  # torch's text advises an unsafe retry: not repeated
        raise TraceCacheError(f"{damaged} (it holds objects beyond tensors)") from None
    except Exception as e:  # truncated zip, wrong format, ...
        first = (str(e).splitlines() or [""])[0][:160]
        reason = type(e).__name__ + ("" if "weights_only" in first else f": {first}")
        raise TraceCacheError(f"{damaged} ({reason})") from None
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
        warmup_steps=int(round((split_cfg.warmup_s + _begin(split_cfg)) / dt)),
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
    bar = tqdm(total=len(requests), desc=desc, unit="sim", leave=False)
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
                workers: int = 0) -> TraceSet:
    """Run SUMO for every seed of the split and stack the traces (no caching)."""
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
    check_has_vehicles(ts, scenario, split)
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


def check_has_vehicles(ts: TraceSet, scenario: ScenarioConfig, split: str) -> None:
    """Traces without a vehicle inside the area would train on a reward of 0: refused."""
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
    raise ConfigError(
        f"the {split} traces hold no vehicle: scenario.sumo.fleet_size is "
        f"{sumo.fleet_size} and {source} put none on the roads in the {when}. Set "
        f"scenario.sumo.fleet_size >= 1 or give routes whose vehicles depart within "
        f"traces.{split}.{within}.")


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
        raise ConfigError(f"{key}: {d} is a file, not a folder. Set traces.cache_dir to a "
                          f"folder (it is made if missing).")
    try:
        d.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=d):
            pass
    except OSError as e:
        raise ConfigError(f"{key}: cannot write in {d} ({e.strerror or e}). Set "
                          f"traces.cache_dir to a folder you can write in.") from None
    return d


def _load_cached(path: Path, key: str, desc: dict[str, Any]) -> TraceSet | None:
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
    ts = _load_cached(path, key, desc)
    if ts is not None:
        check_has_vehicles(ts, scenario, split)  # a file cached before this check
        if verbose:
            log.info("traces %s: cache hit %s", split, path)
        return ts
    check_cache_dir(traces_cfg)
    try:
        with _sigterm_interrupts():
            ts = build_split(scenario, split_cfg, split, traces_cfg.workers)
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
    return ts


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
