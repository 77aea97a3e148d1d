"""Faults around the trace cache and the SUMO workers: misplaced, damaged or unwritable
cache files, SUMO refusing an input, empty traces, interrupted and killed builds."""

from __future__ import annotations

import errno
import json
import logging
import os
import pickle
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import torch

from tests.conftest import SMALL_TRACES, compose_cfg
from uabs_rl.config import PROJECT_ROOT, ConfigError
from uabs_rl.traces import build as traces_mod
from uabs_rl.traces.build import TracesInterrupted, build_split, get_traces
from uabs_rl.traces.cache import cache_path, load_traceset, save_traceset, split_key

MANHATTAN = PROJECT_ROOT / "sumo" / "manhattan" / "manhattan.net.xml"
INTERRUPTED = ("interrupted while building the train traces: nothing was cached; run the "
               "command again to build them")


def small(cache: Path, *extra: str):
    return compose_cfg("build_traces", SMALL_TRACES + [f"traces.cache_dir={cache}", *extra])


def tiny(cache: Path, *extra: str):
    """One 5 s simulation, run in this process: for inputs SUMO refuses."""
    return compose_cfg("build_traces", [
        f"traces.cache_dir={cache}", "scenario.sumo.fleet_size=3", "traces.train.n_sims=1",
        "traces.train.duration_s=5", "traces.train.warmup_s=0", "traces.workers=1", *extra])


def private_copy(trace_cache: Path, tmp_path: Path, *splits: str):
    """A cache folder of its own holding the small case's files of ``splits``."""
    cfg = small(tmp_path)
    shared = small(trace_cache)
    for split in splits:
        shutil.copy(cache_path(shared.scenario, shared.traces, split),
                    cache_path(cfg.scenario, cfg.traces, split))
    return cfg


def warnings_of(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


# ----------------------------------------------------------------------------- identity
def test_a_cache_file_of_another_split_is_rebuilt(trace_cache, tmp_path, train, held_out,
                                                  caplog):
    cfg = private_copy(trace_cache, tmp_path, "eval")
    eval_path = cache_path(cfg.scenario, cfg.traces, "eval")
    train_path = cache_path(cfg.scenario, cfg.traces, "train")
    shutil.copy(eval_path, train_path)  # the validation file under the training name
    with caplog.at_level(logging.WARNING, logger="uabs_rl.traces.cache"):
        ts = get_traces(cfg.scenario, cfg.traces, "train")
    assert ts.source == "built" and ts.meta["split"] == "train"
    assert ts.meta["cache_key"] == train_path.stem
    assert torch.equal(ts.positions, train.positions) and torch.equal(ts.present, train.present)
    [warning] = warnings_of(caplog)
    assert eval_path.stem in warning and train_path.stem in warning and "\n" not in warning
    again = load_traceset(train_path)  # the file now holds the train traces
    assert again.meta["split"] == "train" and torch.equal(again.positions, train.positions)
    assert torch.equal(load_traceset(eval_path).positions, held_out.positions)


def without_key(src: Path, dst: Path) -> None:
    """``src`` as the previous format wrote it: no cache key in its metadata."""
    blob = torch.load(src, weights_only=True)
    meta = json.loads(blob["meta_json"])
    del meta["cache_key"]
    blob["meta_json"] = json.dumps(meta)
    torch.save(blob, dst)


def test_a_cache_file_saved_without_its_key_is_checked_on_its_parameters(
        trace_cache, tmp_path, train, held_out, caplog, monkeypatch):
    """Files of the previous format are kept when the parameters in their metadata are
    those the name hashes, and rebuilt when not."""
    cfg = private_copy(trace_cache, tmp_path, "train", "eval")
    train_path = cache_path(cfg.scenario, cfg.traces, "train")
    eval_path = cache_path(cfg.scenario, cfg.traces, "eval")
    without_key(train_path, train_path)
    with monkeypatch.context() as m:
        m.setattr(traces_mod, "build_split", lambda *a, **k: pytest.fail("rebuilt"))
        kept = get_traces(cfg.scenario, cfg.traces, "train")
    assert kept.source == "cache" and "cache_key" not in kept.meta
    without_key(eval_path, train_path)
    with caplog.at_level(logging.WARNING, logger="uabs_rl.traces.cache"):
        rebuilt = get_traces(cfg.scenario, cfg.traces, "train")
    assert rebuilt.source == "built" and torch.equal(rebuilt.positions, train.positions)
    [warning] = warnings_of(caplog)
    assert "eval traces of other parameters" in warning and train_path.stem in warning


class _Evil:
    def __reduce__(self):
        return (print, ("pwned",))


@pytest.mark.parametrize("write,reason", [
    # a pickle payload: named, never run, and no advice to load it unsafely
    (lambda p: torch.save({"positions": _Evil()}, p, pickle_module=pickle),
     "it holds Python objects: print"),
    # random bytes said "it holds objects beyond tensors", an empty file "(EOFError: )"
    (lambda p: p.write_bytes(b""), "the file is empty"),
    (lambda p: p.write_bytes(bytes(range(256)) * 8), "not a file written by torch.save"),
], ids=["payload", "empty", "random"])
def test_a_damaged_cache_file_is_rebuilt_saying_what_is_wrong_with_it(
        trace_cache, tmp_path, train, caplog, write, reason):
    cfg = private_copy(trace_cache, tmp_path)
    path = cache_path(cfg.scenario, cfg.traces, "train")
    write(path)
    with caplog.at_level(logging.WARNING, logger="uabs_rl.traces.cache"):
        ts = get_traces(cfg.scenario, cfg.traces, "train")
    assert ts.source == "built" and torch.equal(ts.positions, train.positions)
    [warning] = warnings_of(caplog)
    assert warning == (f"trace cache file {path} is damaged or not a trace cache "
                       f"({reason}); rebuilding it")
    assert "weights_only" not in caplog.text


# ----------------------------------------------------------------------------- writing
def test_a_full_disk_leaves_no_temporary_file_and_keeps_the_old_one(tmp_path, train,
                                                                     monkeypatch):
    path = tmp_path / "t.pt"
    save_traceset(train, path)
    before = path.read_bytes()

    def full(obj, f):
        f.write(b"PK\x03\x04 half a zip")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(torch, "save", full)
    with pytest.raises(ConfigError) as e:
        save_traceset(train, path)
    assert str(e.value) == (f"traces.cache_dir: cannot write the trace cache file {path}: no "
                            f"space left on the device. Free space in {tmp_path} or set "
                            f"traces.cache_dir=<a folder with room>.")
    assert [p.name for p in tmp_path.iterdir()] == ["t.pt"] and path.read_bytes() == before

    def interrupted(obj, f):
        f.write(b"PK")
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", interrupted)
    with pytest.raises(KeyboardInterrupt):
        save_traceset(train, tmp_path / "new.pt")
    assert [p.name for p in tmp_path.iterdir()] == ["t.pt"] and path.read_bytes() == before


@pytest.mark.parametrize("where", ["a file", "below a file"])
def test_an_unusable_cache_dir_fails_before_sumo_runs(tmp_path, where, monkeypatch):
    (tmp_path / "f").write_text("not a folder")
    cache = tmp_path / "f" if where == "a file" else tmp_path / "f" / "traces"
    monkeypatch.setattr(traces_mod, "build_split", lambda *a, **k: pytest.fail("SUMO ran"))
    cfg = small(cache)
    with pytest.raises(ConfigError) as e:
        get_traces(cfg.scenario, cfg.traces, "train")
    if where == "a file":
        assert str(e.value) == (f"traces.cache_dir: {cache} is a file, not a folder. Set "
                                f"traces.cache_dir to a folder (it is made if missing).")
    else:
        assert str(e.value) == (f"traces.cache_dir: cannot write in {cache} (Not a "
                                f"directory). Set traces.cache_dir to a folder you can "
                                f"write in.")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes in read-only folders")
def test_a_read_only_cache_dir_fails_before_sumo_runs(tmp_path, monkeypatch):
    cache = tmp_path / "ro"
    cache.mkdir(mode=0o500)
    monkeypatch.setattr(traces_mod, "build_split", lambda *a, **k: pytest.fail("SUMO ran"))
    cfg = small(cache)
    with pytest.raises(ConfigError, match=r"^traces\.cache_dir: cannot write in .*Permission"):
        get_traces(cfg.scenario, cfg.traces, "train")


# ----------------------------------------------------------------------------- inputs
@pytest.fixture
def bad_inputs(tmp_path) -> dict[str, Path]:
    files = {
        "unknown_edge.rou.xml": '<routes><vehicle id="v0" depart="0"><route edges="NOPE '
                                'A0B0"/></vehicle></routes>',
        "broken.rou.xml": '<routes><vehicle id="v" depart="0"',
        "empty.rou.xml": "<routes></routes>",
        "missing_net.sumocfg": '<configuration><input><net-file value="nowhere.net.xml"/>'
                               '</input></configuration>',
        "manhattan.sumocfg": f'<configuration><input><net-file value="{MANHATTAN}"/>'
                             f'</input></configuration>',
    }
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    return {name: tmp_path / name for name in files}


@pytest.mark.parametrize("override,workers,message", [
    ("scenario.sumo.route_files=[{dir}/unknown_edge.rou.xml]", 1,
     "scenario.sumo.route_files: SUMO refused {dir}/unknown_edge.rou.xml while building the "
     "train traces: The edge 'NOPE' within the route for vehicle 'v0' is not known. The "
     "route can not be build. Fix the file or remove it from scenario.sumo.route_files."),
    ("scenario.sumo.route_files=[{dir}/broken.rou.xml]", 2,
     "scenario.sumo.route_files: SUMO refused {dir}/broken.rou.xml while building the train "
     "traces: whitespace expected In file '{dir}/broken.rou.xml' At line/column 2/35. Fix "
     "the file or remove it from scenario.sumo.route_files."),
    ("scenario.sumo.sumocfg={dir}/missing_net.sumocfg", 1,
     "scenario.sumo.sumocfg: SUMO refused {dir}/missing_net.sumocfg while building the train "
     "traces: File '{dir}/nowhere.net.xml' is not accessible (No such file or directory). "
     "Process Error. Fix the file or point scenario.sumo.sumocfg at another one."),
    ("scenario.sumo.extra_args=[--no-such-option]", 2,
     "scenario.sumo.extra_args: SUMO refused ['--no-such-option'] while building the train "
     "traces: On processing option '--no-such-option': No option with the name "
     "'no-such-option' exists. Could not parse commandline options. Fix or remove the "
     "argument (sumo --help lists them)."),
])
def test_an_input_sumo_refuses_is_one_line_naming_the_key(trace_cache, bad_inputs, override,
                                                          workers, message):
    """In this process (workers=1) or in worker processes (2 simulations, workers=2)."""
    where = str(bad_inputs["empty.rou.xml"].parent)
    cfg = tiny(trace_cache, override.format(dir=where), f"traces.workers={workers}",
               f"traces.train.n_sims={workers}")
    with pytest.raises(ConfigError) as e:
        get_traces(cfg.scenario, cfg.traces, "train")
    assert str(e.value) == message.format(dir=where)
    assert not cache_path(cfg.scenario, cfg.traces, "train").exists()


def empty_routes_refusal(trace_cache, bad_inputs, split: str, *extra: str) -> str:
    """The refusal of the ``split`` traces of routes without a vehicle (no fleet), after
    checking that nothing was cached."""
    cfg = tiny(trace_cache, "scenario.sumo.fleet_size=0", *extra,
               f"scenario.sumo.route_files=[{bad_inputs['empty.rou.xml']}]")
    with pytest.raises(ConfigError) as e:
        get_traces(cfg.scenario, cfg.traces, split)
    assert not cache_path(cfg.scenario, cfg.traces, split).exists()
    return str(e.value)


def test_a_fixed_demand_recorded_past_its_vehicles_names_begin_s(trace_cache, bad_inputs):
    """Routes recorded from a begin_s on that none of their vehicles reaches: the advice
    is the time range (begin_s), not a fleet the scenario does not use."""
    said = empty_routes_refusal(trace_cache, bad_inputs, "train", "traces.train.begin_s=10")
    assert said == (
        f"the train traces hold no vehicle: scenario.sumo.route_files "
        f"({bad_inputs['empty.rou.xml']}) put none on the roads in the 5.0 s recorded from "
        f"0.0 + 10.0 s on: its vehicles depart at the times its files give, and none drives "
        f"in that range (past the end of its demand?). Move traces.train.begin_s earlier, or "
        f"leave the begin_s settings null (the splits then follow one another from the "
        f"start).")
    # begin_s null: the split follows the earlier ones, which is what to change
    said = empty_routes_refusal(trace_cache, bad_inputs, "eval", "traces.eval.n_sims=1",
                                "traces.eval.duration_s=5", "traces.eval.warmup_s=0")
    assert said.endswith(
        "recorded from 0.0 + 5.0 s on: its vehicles depart at the times its files give, and "
        "none drives in that range (past the end of its demand?). traces.eval.begin_s is "
        "null, so the eval range follows the earlier splits': shorten their duration_s, or "
        "set traces.eval.begin_s to a time its vehicles drive in (the splits' ranges must "
        "stay disjoint).")


def test_uabs_traces_prints_a_refused_argument_as_one_line(trace_cache):
    proc = subprocess.run(
        [sys.executable, "-m", "uabs_rl.cli.traces", "split=train",
         f"traces.cache_dir={trace_cache}",
         "scenario.sumo.fleet_size=3", "traces.train.n_sims=1", "traces.train.duration_s=5",
         "traces.train.warmup_s=0", "traces.workers=1",
         "scenario.sumo.extra_args=[--no-such-option]"],
        capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    [line] = proc.stderr.splitlines()  # a pipe gets no progress bar (a terminal only)
    assert line.startswith("error: scenario.sumo.extra_args: SUMO refused ['--no-such-option']")


def test_uabs_traces_warns_of_traces_shorter_than_an_episode(tmp_path):
    """Traces too short for one episode are cached (a demo, a check of the SUMO files)
    with a warning that training and evaluation will refuse them, and why."""
    proc = subprocess.run(
        [sys.executable, "-m", "uabs_rl.cli.traces", "experiment=smoke", "split=eval",
         f"traces.cache_dir={tmp_path}", "traces.eval.duration_s=15", "traces.workers=1"],
        capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert ("  warning: these eval traces hold 15 steps, fewer than an episode's "
            "scenario.episode_steps + 1 = 21: uabs-train and uabs-eval refuse them (raise "
            "traces.eval.duration_s, or lower scenario.episode_steps)") in proc.stdout


def test_routes_without_a_vehicle_are_refused(trace_cache, bad_inputs):
    assert empty_routes_refusal(trace_cache, bad_inputs, "train") == (
        f"the train traces hold no vehicle: scenario.sumo.fleet_size is 0 and "
        f"scenario.sumo.route_files ({bad_inputs['empty.rou.xml']}) put none on the roads in "
        f"the 0.0 + 5.0 s simulated. Set scenario.sumo.fleet_size >= 1 or give routes whose "
        f"vehicles depart within traces.train.warmup_s + duration_s.")


def test_vehicles_outside_the_area_are_refused(trace_cache, bad_inputs):
    """A .sumocfg is not checked against the area before SUMO runs: its traces are."""
    cfg = tiny(trace_cache, f"scenario.sumo.sumocfg={bad_inputs['manhattan.sumocfg']}",
               "scenario.area.x_min=5000")
    with pytest.raises(ConfigError, match=r"^the train traces hold no vehicle inside "
                                          r"scenario\.area \(x 5000\.0\.\.5350\.0, y "):
        get_traces(cfg.scenario, cfg.traces, "train")


@pytest.mark.parametrize("key,value,message", [
    ("net_file", "sumo/manhattan",
     "scenario.sumo.net_file: 'sumo/manhattan' is a folder ({root}/sumo/manhattan), not a "
     ".net.xml file. Set scenario.sumo.net_file to a .net.xml file, such as "
     "sumo/manhattan/manhattan.net.xml."),
    ("route_files", "[sumo]",
     "scenario.sumo.route_files[0]: 'sumo' is a folder ({root}/sumo), not a .rou.xml file. "
     "Set scenario.sumo.route_files[0] to a .rou.xml file."),
])
def test_a_folder_given_for_an_input_file_is_named_as_such(trace_cache, key, value, message,
                                                           monkeypatch):
    monkeypatch.chdir(PROJECT_ROOT)
    cfg = tiny(trace_cache, f"scenario.sumo.{key}={value}")
    with pytest.raises(ConfigError) as e:
        get_traces(cfg.scenario, cfg.traces, "train")
    assert str(e.value) == message.format(root=PROJECT_ROOT)


@pytest.mark.parametrize("attr,value,key", [
    ("area.width", float("nan"), "scenario.area.width"),
    ("area.x_min", float("-inf"), "scenario.area.x_min"),
    ("dt", float("nan"), "scenario.dt"),
    ("train.duration_s", float("inf"), "traces.train.duration_s"),
    ("train.warmup_s", float("nan"), "traces.train.warmup_s"),
])
def test_the_cache_key_never_hashes_a_non_finite_number(attr, value, key):
    cfg = compose_cfg("build_traces", SMALL_TRACES)
    owner, name = attr.split(".") if "." in attr else ("", attr)
    target = {"area": cfg.scenario.area, "train": cfg.traces.train, "": cfg.scenario}[owner]
    setattr(target, name, value)
    with pytest.raises(ConfigError) as e:
        split_key(cfg.scenario, cfg.traces.train, "train")
    assert str(e.value) == f"{key} must be a finite number, got {value}."


# ----------------------------------------------------------------------------- processes
def sumo_workers() -> dict[int, int]:
    """Live ``uabs_rl.traces.sumo_sim`` worker processes: pid -> parent pid (zombies skipped)."""
    found = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            cmd = (d / "cmdline").read_bytes()
            state, ppid = (d / "stat").read_text().rsplit(")", 1)[1].split()[:2]
        except (OSError, IndexError):
            continue
        if b"uabs_rl.traces.sumo_sim" in cmd and state != "Z":
            found[int(d.name)] = int(ppid)
    return found


def start_long_build(cache: Path, tmp: Path) -> tuple[subprocess.Popen, set[int]]:
    """``uabs-traces`` on 4 simulations long enough never to end here, 2 workers at a time;
    returns once both workers run."""
    tmp.mkdir(exist_ok=True)
    proc = subprocess.Popen(
        [sys.executable, "-m", "uabs_rl.cli.traces", "split=train", f"traces.cache_dir={cache}",
         "traces.workers=2", "traces.train.n_sims=4", "traces.train.duration_s=1000000",
         "traces.train.warmup_s=0", "scenario.sumo.fleet_size=20"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env=dict(os.environ, TMPDIR=str(tmp)))
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        mine = {pid for pid, ppid in sumo_workers().items() if ppid == proc.pid}
        if len(mine) == 2:
            return proc, mine
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.1)
    proc.kill()
    pytest.fail("the build's two workers did not start within 90 s")


@pytest.fixture
def long_build(tmp_path):
    """Starts :func:`start_long_build` in ``tmp_path``; whatever a failed test leaves
    running is killed at teardown."""
    started = []

    def start() -> tuple[subprocess.Popen, set[int], Path, Path]:
        proc, workers = start_long_build(tmp_path / "cache", tmp_path / "tmp")
        started.append((proc, workers))
        return proc, workers, tmp_path / "cache", tmp_path / "tmp"

    yield start
    for proc, workers in started:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        for pid in workers & sumo_workers().keys():
            os.kill(pid, signal.SIGKILL)


def wait_gone(pids: set[int], seconds: float) -> set[int]:
    deadline = time.monotonic() + seconds
    while (left := pids & sumo_workers().keys()) and time.monotonic() < deadline:
        time.sleep(0.05)
    return left


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("sig,status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_an_interrupted_build_stops_its_workers_and_caches_nothing(long_build, sig, status):
    proc, workers, cache, tmp = long_build()
    t0 = time.monotonic()
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert time.monotonic() - t0 < 10
    assert proc.returncode == status
    assert err.rstrip().splitlines()[-1].split("\r")[-1] == INTERRUPTED
    assert "checkpoint" not in err and "Traceback" not in err
    assert not wait_gone(workers, 5)
    assert list(cache.iterdir()) == [] and list(tmp.iterdir()) == []


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG, /proc")
def test_workers_die_with_a_killed_build_and_the_next_build_removes_its_folder(
        long_build, trace_cache, monkeypatch):
    proc, workers, _, tmp = long_build()
    proc.kill()
    proc.communicate(timeout=30)
    assert not wait_gone(workers, 5), "SUMO workers outlived their parent"
    [stale] = tmp.iterdir()
    assert stale.name.startswith(f"uabs_sumo_{proc.pid}_")
    live = tmp / f"uabs_sumo_{os.getpid()}_x"  # this process's own: kept
    live.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    cfg = small(trace_cache)
    ts = build_split(cfg.scenario, cfg.traces.eval, "eval", workers=1)
    assert ts.n_sims == 1
    assert list(tmp.iterdir()) == [live]


def test_an_interrupted_in_process_build_names_the_traces(tmp_path, monkeypatch):
    def ctrl_c(*_a, **_k):
        raise KeyboardInterrupt

    monkeypatch.setattr(traces_mod, "run_simulation", ctrl_c)
    cfg = tiny(tmp_path)
    with pytest.raises(TracesInterrupted) as e:
        get_traces(cfg.scenario, cfg.traces, "train")
    assert str(e.value) == INTERRUPTED and isinstance(e.value, KeyboardInterrupt)
    assert e.value.exit_code == 130
    assert list(tmp_path.iterdir()) == []


def test_sumo_failures_are_attributed_to_the_input_at_fault(tmp_path):
    """The network when the fleet finds no route; the routes when SUMO names no file; a
    crashed worker (SUMO said nothing) stays a SumoRunError."""
    from uabs_rl.traces.sumo_sim import SumoRunError

    cfg = tiny(tmp_path, "scenario.sumo.route_files=[a.rou.xml,b.rou.xml]")
    files = {"sumocfg": None, "net_file": MANHATTAN,
             "route_files": [tmp_path / "a.rou.xml", tmp_path / "b.rou.xml"]}
    fleet = SumoRunError("found no connected pair of edges in 100 tries: is the network "
                         "connected?", key="scenario.sumo.net_file")
    e = traces_mod._sumo_refused(fleet, cfg.scenario, files, "eval")
    assert isinstance(e, ConfigError) and str(e) == (
        f"scenario.sumo.net_file: SUMO refused {MANHATTAN} while building the eval traces: "
        f"found no connected pair of edges in 100 tries: is the network connected? Fix the "
        f"network or point scenario.sumo.net_file at another one.")
    vehicle = SumoRunError("...", said="Vehicle 'x' has no valid route.")
    e = traces_mod._sumo_refused(vehicle, cfg.scenario, files, "eval")
    assert str(e).startswith(f"scenario.sumo.route_files: SUMO refused {tmp_path}/a.rou.xml, "
                             f"{tmp_path}/b.rou.xml while building the eval traces: Vehicle")
    crash = SumoRunError("the SUMO worker for seed 3 exited with code -9: ")
    e = traces_mod._sumo_refused(crash, cfg.scenario, files, "eval")
    assert type(e) is SumoRunError and str(e) == (
        "building the eval traces failed: the SUMO worker for seed 3 exited with code -9: ")


def test_uabs_traces_says_a_warning_is_one():
    """uabs-traces logs bare lines on stdout (conf/hydra/job_logging/uabs_traces.yaml);
    a warning's line begins with "warning: ", an info line does not."""
    import yaml

    from uabs_rl.cli.traces import Said

    conf = Path(__file__).resolve().parents[1] / "conf"
    said = yaml.safe_load((conf / "hydra" / "job_logging" / "uabs_traces.yaml").read_text())
    assert said["formatters"]["said"]["()"] == "uabs_rl.cli.traces.Said"
    assert "override hydra/job_logging: uabs_traces" in (conf / "build_traces.yaml").read_text()
    rec = lambda level: logging.LogRecord("x", level, __file__, 1, "thin", None, None)  # noqa: E731
    assert Said().format(rec(logging.WARNING)) == "warning: thin"
    assert Said().format(rec(logging.INFO)) == "thin"
