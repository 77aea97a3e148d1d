"""Run one SUMO simulation through libsumo and sample every vehicle's position.

Runs in a worker process (libsumo holds one simulation per process), so this module
imports neither torch nor the rest of the package.

Vehicles come from two sources that can be combined:

* a **fleet** of ``fleet_size`` vehicles, each inserted on a random route and given a
  new random destination (``vehicle.changeTarget``) when it reaches the last edge of
  its route, so the count stays steady (random-trip insertion jams or drains a small
  grid); fleet vehicle ``i`` always occupies slot ``i``;
* route files or a ``.sumocfg``: vehicles that enter and leave; each gets a free slot
  while present. A freed slot is reused only after one step without anyone in it, so
  a consumer sees a new vehicle as a new presence run.
"""

from __future__ import annotations

import ctypes
import json
import os
import pickle
import signal
import sys
import tempfile
import threading
import time
from dataclasses import dataclass

import numpy as np

FLEET_PREFIX = "uabs_fleet_"
_INVALID = 1e9  # libsumo returns -2**30 for a vehicle that is teleporting


class SumoRunError(RuntimeError):
    """SUMO failed; the message names the seed and the inputs. ``said`` holds SUMO's own
    words (one line; empty when SUMO said nothing), ``key`` the config key at fault when
    it is known here."""

    def __init__(self, message: str, said: str = "", key: str = ""):
        super().__init__(message)
        self.said, self.key = said, key


@dataclass
class SimRequest:
    seed: int
    net_file: str | None
    route_files: list[str]
    sumocfg: str | None
    fleet_size: int
    dt: float
    warmup_steps: int
    steps: int
    origin: tuple[float, float]
    extra_args: list[str]


@dataclass
class SimResult:
    seed: int
    positions: np.ndarray  # [steps, slots, 2] float32, relative to the area origin
    present: np.ndarray  # [steps, slots] bool
    teleports: int  # vehicle-steps spent teleporting (held at their last position)
    seconds: float


def _sumo_command(req: SimRequest) -> list[str]:
    cmd = ["sumo"]
    if req.sumocfg:
        cmd += ["-c", req.sumocfg]
    else:
        cmd += ["-n", req.net_file]
        if req.route_files:
            cmd += ["-r", ",".join(req.route_files)]
    cmd += ["--seed", str(req.seed), "--step-length", str(req.dt), "--begin", "0",
            "--no-step-log", "true", "--no-warnings", "true", "--duration-log.disable", "true"]
    return cmd + list(req.extra_args)


class _Fleet:
    """Keeps ``size`` vehicles driving: a new random destination at each route's end."""

    def __init__(self, ls, size: int, rng: np.random.Generator):
        self.ls, self.rng = ls, rng
        self.edges = [e for e in ls.edge.getIDList()
                      if not e.startswith(":") and ls.edge.getLaneNumber(e) > 0]
        if len(self.edges) < 2:
            raise SumoRunError("the network has fewer than 2 drivable edges: no route possible",
                               key="scenario.sumo.net_file")
        self.route_len: dict[str, int] = {}
        for i in range(size):
            vid = f"{FLEET_PREFIX}{i}"
            edges = self._random_route()
            ls.route.add(f"{vid}_route", edges)
            ls.vehicle.add(vid, f"{vid}_route", departPos="random", departSpeed="max",
                           departLane="best")
            self.route_len[vid] = len(edges)

    def _random_route(self) -> list[str]:
        for _ in range(100):
            a, b = self.rng.choice(len(self.edges), 2, replace=False)
            route = self.ls.simulation.findRoute(self.edges[a], self.edges[b])
            if route.edges:
                return list(route.edges)
        raise SumoRunError("found no connected pair of edges in 100 tries: is the network "
                           "connected?", key="scenario.sumo.net_file")

    def retarget(self, vid: str, route_index: int) -> None:
        if route_index < self.route_len[vid] - 1:
            return
        current = self.ls.vehicle.getRoadID(vid)
        for _ in range(100):
            target = self.edges[self.rng.integers(len(self.edges))]
            if target == current:
                continue
            try:
                self.ls.vehicle.changeTarget(vid, target)
            except self.ls.TraCIException:
                continue  # unreachable from here: draw another
            self.route_len[vid] = len(self.ls.vehicle.getRoute(vid))
            return


class _Slots:
    """Maps vehicle ids to tensor slots: fleet ids fixed, others reuse freed slots."""

    def __init__(self, fleet_size: int):
        self.fleet_size = fleet_size
        self.slot: dict[str, int] = {}
        self.free: list[int] = []
        self.cooling: list[int] = []
        self.next = fleet_size

    def get(self, vid: str) -> int:
        if vid.startswith(FLEET_PREFIX):
            return int(vid[len(FLEET_PREFIX):])
        if vid not in self.slot:
            if self.free:
                self.slot[vid] = self.free.pop()
            else:
                self.slot[vid], self.next = self.next, self.next + 1
        return self.slot[vid]

    def end_step(self, gone: list[str]) -> None:
        self.free += self.cooling  # slots empty for a whole step are reusable
        self.cooling = [self.slot.pop(v) for v in gone if v in self.slot]


class _SumoMessages:
    """Collects what SUMO prints on the process's stderr (file descriptor 2) while
    active: libsumo's exceptions often say only "Process Error" or "Could not parse
    commandline options" and leave the reason on stderr. On a normal exit the text is
    passed on to stderr unchanged."""

    def __enter__(self) -> _SumoMessages:
        sys.stderr.flush()
        self.file = tempfile.TemporaryFile()
        self.saved = os.dup(2)
        os.dup2(self.file.fileno(), 2)
        self.consumed = False
        return self

    def said(self, exc: BaseException) -> str:
        """SUMO's messages and the exception's text, one line, without repeats."""
        self.consumed = True
        self.file.seek(0)
        lines = self.file.read().decode(errors="replace").splitlines() + str(exc).splitlines()
        parts: list[str] = []
        for line in lines:
            line = line.strip().removeprefix("Error:").strip()
            if line and line not in parts and not line.startswith("Quitting"):
                parts.append(line)
        return " ".join(parts)

    def __exit__(self, *exc) -> None:
        os.dup2(self.saved, 2)
        os.close(self.saved)
        if not self.consumed:
            self.file.seek(0)
            text = self.file.read()
            if text:
                os.write(2, text)
        self.file.close()


def run_simulation(req: SimRequest) -> SimResult:
    """Simulate ``warmup_steps + steps`` steps and record the last ``steps``."""
    import libsumo as ls  # imported here: a worker process holds one simulation

    sumo_errors = (ls.TraCIException, ls.FatalTraCIError)
    start = time.perf_counter()
    with _SumoMessages() as messages:
        try:
            ls.start(_sumo_command(req))
        except sumo_errors as e:
            said = messages.said(e)
            raise SumoRunError(f"SUMO did not start (seed {req.seed}, command "
                               f"{' '.join(_sumo_command(req))}): {said}", said) from None
        try:
            return _record(ls, req, start)
        except sumo_errors as e:
            said = messages.said(e)
            raise SumoRunError(f"SUMO failed during the simulation (seed {req.seed}): {said}",
                               said) from None
        finally:
            ls.close()


def _record(ls, req: SimRequest, start: float) -> SimResult:
    rng = np.random.default_rng(req.seed)
    fleet = _Fleet(ls, req.fleet_size, rng) if req.fleet_size > 0 else None
    slots = _Slots(req.fleet_size)
    ls.simulation.subscribe([ls.VAR_DEPARTED_VEHICLES_IDS, ls.VAR_ARRIVED_VEHICLES_IDS])
    rows: list[tuple[np.ndarray, np.ndarray]] = []
    teleports, ox, oy = 0, req.origin[0], req.origin[1]
    last_xy: dict[str, tuple[float, float]] = {}
    for t in range(req.warmup_steps + req.steps):
        ls.simulationStep()
        sim = ls.simulation.getSubscriptionResults()
        for vid in sim[ls.VAR_DEPARTED_VEHICLES_IDS]:
            ls.vehicle.subscribe(vid, [ls.VAR_POSITION, ls.VAR_ROUTE_INDEX])
        idx, xy = [], []
        for vid, d in ls.vehicle.getAllSubscriptionResults().items():
            if fleet is not None and vid.startswith(FLEET_PREFIX):
                fleet.retarget(vid, d[ls.VAR_ROUTE_INDEX])
            x, y = d[ls.VAR_POSITION]
            if abs(x) > _INVALID or abs(y) > _INVALID:
                # Mid-teleport (SUMO resolves a rare gridlock): the vehicle stays where it
                # was stuck until it reappears, so the fleet count never drops.
                teleports += 1
                if vid not in last_xy:
                    continue
                x, y = last_xy[vid]
            last_xy[vid] = (x, y)
            idx.append(slots.get(vid))
            xy.append((x - ox, y - oy))
        arrived = list(sim[ls.VAR_ARRIVED_VEHICLES_IDS])
        for vid in arrived:
            last_xy.pop(vid, None)
        slots.end_step(arrived)
        if t >= req.warmup_steps:
            rows.append((np.asarray(idx, dtype=np.int64), np.asarray(xy, dtype=np.float32)))
    n_slots = max([slots.next] + [int(i.max()) + 1 for i, _ in rows if len(i)])
    positions = np.zeros((req.steps, n_slots, 2), dtype=np.float32)
    present = np.zeros((req.steps, n_slots), dtype=bool)
    for t, (i, xy) in enumerate(rows):
        if len(i):
            positions[t, i] = xy
            present[t, i] = True
    return SimResult(req.seed, positions, present, teleports, time.perf_counter() - start)


def error_path(out_path: str) -> str:
    """Where a worker writes its :class:`SumoRunError` (JSON) when SUMO fails."""
    return out_path + ".error.json"


def _watch_parent(parent: int) -> None:
    while True:
        time.sleep(1.0)
        if os.getppid() != parent:
            os._exit(1)


def _die_with_parent(parent: int) -> None:
    """End this worker when the process that started it ends, even by ``kill -9``: on
    Linux the kernel sends SIGKILL (PR_SET_PDEATHSIG); everywhere a thread checks once a
    second that the parent is still the same process."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent:  # the parent ended before the line above
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent,), daemon=True).start()


def _worker_main(argv: list[str]) -> int:
    """``python -m uabs_rl.traces.sumo_sim REQUEST.pkl RESULT.npz PARENT_PID``: one simulation
    in its own process (libsumo holds one simulation per process). Ctrl-C is left to the
    parent, which stops its workers itself."""
    req_path, out_path, parent = argv
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent(int(parent))
    with open(req_path, "rb") as f:
        req = pickle.load(f)
    try:
        res = run_simulation(req)
    except SumoRunError as e:
        with open(error_path(out_path), "w") as f:
            json.dump({"message": str(e), "said": e.said, "key": e.key}, f)
        return 2
    np.savez(out_path, positions=res.positions, present=res.present,
             teleports=res.teleports, seconds=res.seconds)
    return 0


def load_error(path: str) -> SumoRunError:
    """The :class:`SumoRunError` a worker wrote with :func:`error_path`."""
    with open(path) as f:
        d = json.load(f)
    return SumoRunError(d["message"], d["said"], d["key"])


def load_result(seed: int, path: str) -> SimResult:
    with np.load(path) as z:
        return SimResult(seed, z["positions"], z["present"], int(z["teleports"]),
                         float(z["seconds"]))


if __name__ == "__main__":
    sys.exit(_worker_main(sys.argv[1:]))
