"""Issue #35 as users reach it, through the commands' entry points (as subprocesses where
the fault is the process's own: killed, signalled, a full disk mid-write): a name
that becomes a path never writes outside its folder; an output folder holds one
invocation's files, complete, or the previous one untouched (kill -9, SIGTERM, a full
disk); a checkpoint copied in from another run is refused; bad input is one line on
stderr and exit status 2, never a traceback."""

from __future__ import annotations

import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from tests.conftest import SMALL_TRACES, Ran, run_command
from tests.test_train import smoke
from uabs_rl.training.resume import run

QUIET = ("train.logger=none", "train.trajectory_images=false")
LONG = "x" * 300
ROOT = Path(__file__).resolve().parents[1]


def command(module: str, *args: str, cwd: Path | None = None, hook: str = "",
            timeout: int = 300) -> subprocess.CompletedProcess | Ran:
    """``python -m uabs_rl.cli.<module> args``, run in this process (its entry point, as
    tests.conftest.run_command runs it); with ``hook``, as a subprocess in which that
    Python code runs first (a fault injected where a user's machine would have one: a
    kill, a signal, a full disk)."""
    if not hook:
        return run_command(module, *args, cwd=cwd)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    code = (f"{hook}\nimport importlib\n"
            f"importlib.import_module('uabs_rl.cli.{module}').run_main()")
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd, env=env)


def one_line(proc: subprocess.CompletedProcess | Ran, *words: str, code: int = 2) -> str:
    """The command exited with ``code`` and said one line on stderr holding ``words``."""
    assert "Traceback" not in proc.stderr + proc.stdout, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == code, proc.stderr
    assert len(lines) == 1, lines
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def tree(folder: Path) -> dict[str, bytes | None]:
    """Every entry under ``folder`` (hidden ones too), files with their bytes."""
    return {str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else None)
            for p in sorted(folder.rglob("*"))}


def listing(*folders: Path) -> dict[str, list[str]]:
    return {str(f): sorted(os.listdir(f)) for f in folders}


# ----------------------------------------------------------------------------- runs
@pytest.fixture(scope="module")
def runs(trace_cache, tmp_path_factory) -> dict[str, Path]:
    """A 3DQN smoke run (with the .hydra/config.yaml uabs-train writes), a VDN one and
    an egocentric one, trained once for the module."""
    root = tmp_path_factory.mktemp("owned_runs")
    out = {}
    for name, extra in [("dqn", ()), ("vdn", ("algo=vdn",)), ("ego", ("obs=egocentric",))]:
        cfg = smoke(trace_cache, *QUIET, *extra)
        run(cfg, root / name)
        (root / name / ".hydra").mkdir()
        OmegaConf.save(OmegaConf.structured(cfg), root / name / ".hydra" / "config.yaml")
        out[name] = root / name
    return out


def copy_run(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns(".lock", "evaluation"))
    return dst


# ----------------------------------------------------------------------------- names
TRACES = ["split=eval", *SMALL_TRACES]


@pytest.mark.parametrize("name, why", [
    ("../../../elsewhere/ESCAPED", "holds a /"),
    ("/var/ABSNAME", "holds a /"),
])
def test_a_scenario_name_never_writes_outside_the_cache(tmp_path, name, why):
    cache = tmp_path / "cache" / "traces"
    watched = [tmp_path, tmp_path.parent, tmp_path.parent.parent]
    before = listing(*watched)
    proc = command("traces", *TRACES, f"traces.cache_dir={cache}", f"scenario.name={name}",
                   cwd=tmp_path)
    one_line(proc, "scenario.name=", why)
    assert listing(*watched) == before
    assert not Path("/var/ABSNAME").exists() and not list(Path("/var").glob("ABSNAME*"))


@pytest.mark.parametrize("name, why", [
    ("a/b", "holds a /"), ("a\\b", "holds a /"), ("..", "'..', a folder"),
    ("", "empty"), ("a\x00b", "control character"), ("a\nb", "control character"),
    (LONG, "300 characters long")])
def test_the_one_rule_for_names_that_become_paths(name, why):
    from uabs_rl.config import ConfigError
    from uabs_rl.paths import safe_component

    with pytest.raises(ConfigError, match="^some.setting=") as e:
        safe_component(name, "some.setting")
    assert why in str(e.value) and "\n" not in str(e.value)
    assert safe_component("grid6-v2.1_b", "some.setting") == "grid6-v2.1_b"


def test_a_family_city_name_is_checked_too(tmp_path):
    cache = tmp_path / "cache"
    proc = command("traces", "split=train", *SMALL_TRACES, f"traces.cache_dir={cache}",
                   "family=[{name: ../up}]", cwd=tmp_path)
    one_line(proc, "family[0].name=")
    assert not (tmp_path / "up-train").exists() and not cache.exists()


def test_train_and_eval_refuse_a_name_that_leaves_the_cache(runs, trace_cache, tmp_path):
    watched = [tmp_path, trace_cache, trace_cache.parent]
    before = listing(*watched)
    name = "scenario.name=../../../elsewhere/ESCAPED"
    proc = command("train", "experiment=smoke", *QUIET, "train.progress=false",
                   f"traces.cache_dir={trace_cache}", name,
                   f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    one_line(proc, "scenario.name=")
    proc = command("evaluate", str(runs["dqn"]), name, "--out", str(tmp_path / "ev"),
                   cwd=tmp_path)
    one_line(proc, "scenario.name=")
    after = listing(*watched)
    after[str(tmp_path)] = [n for n in after[str(tmp_path)] if n != "run"]  # Hydra's, emptied
    assert after == before
    assert not list((tmp_path / "run").rglob("*.pt")) if (tmp_path / "run").exists() else True


# ----------------------------------------------------------------------------- payloads
class Payload:
    """Unpickled, it would create the file ``path``."""

    def __init__(self, path: Path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def test_a_cache_file_holding_a_pickle_payload_never_runs_it(tmp_path):
    from tests.conftest import compose_cfg
    from uabs_rl.traces.cache import cache_path

    cache = tmp_path / "cache"
    cfg = compose_cfg("build_traces", SMALL_TRACES + [f"traces.cache_dir={cache}"])
    target = cache_path(cfg.scenario, cfg.traces, "eval")
    target.parent.mkdir(parents=True)
    sentinel = tmp_path / "RAN"
    torch.save({"positions": Payload(sentinel), "present": 0, "meta_json": "{}"}, target,
               pickle_module=pickle)
    proc = command("traces", *TRACES, f"traces.cache_dir={cache}", cwd=tmp_path)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr + proc.stdout
    warned = [ln for ln in (proc.stdout + proc.stderr).splitlines() if "damaged" in ln]
    assert len(warned) == 1 and "holds Python objects: " in warned[0]
    assert not sentinel.exists()


def test_a_checkpoint_payload_and_a_yaml_tag_never_run(runs, tmp_path):
    sentinel = tmp_path / "RAN"
    bad = copy_run(runs["dqn"], tmp_path / "run")
    torch.save({"format": 2, "x": Payload(sentinel)}, bad / "checkpoints" / "best.pt",
               pickle_module=pickle)
    one_line(command("evaluate", str(bad)), "best.pt")
    user = tmp_path / "conf" / "scenario"
    user.mkdir(parents=True)
    (user / "evil.yaml").write_text(
        f'name: !!python/object/apply:builtins.open ["{sentinel}", "w"]\n')
    one_line(command("evaluate", str(runs["dqn"]), "scenario=evil", "--config-dir",
                     str(tmp_path / "conf"), "--out", str(tmp_path / "ev")),
             "scenario=evil", "evil.yaml")
    assert not sentinel.exists() and not (tmp_path / "ev").exists()


# ----------------------------------------------------------------------------- report folders
@pytest.fixture(scope="module")
def sweep(runs, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("report_sweep")
    copy_run(runs["dqn"], root / "dqn")
    return root


def report(sweep: Path, out: Path, *extra: str,
           hook: str = "") -> subprocess.CompletedProcess | Ran:
    return command("report", str(sweep), "--no-baselines", "--out", str(out), *extra,
                   hook=hook)


KILL_AT_COMPARISON = """
import os, signal
import uabs_rl.report.build as r
_write = r.write_csv
def _write_csv(path, *a, **k):
    _write(path, *a, **k)
    if path.name == "comparison.csv":  # table2 and the figures are written by now
        os.kill(os.getpid(), signal.{sig})
r.write_csv = _write_csv
"""


@pytest.fixture(scope="module")
def previous(sweep, tmp_path_factory) -> tuple[Path, dict]:
    """A complete report folder, as a report written before marker files existed left
    it (with the baseline files a full report writes), and its contents."""
    out = tmp_path_factory.mktemp("reports") / "report"
    proc = report(sweep, out)
    assert proc.returncode == 0, proc.stderr
    (out / ".uabs-report").unlink()
    (out / "baselines.csv").write_text("policy,return\ngreedy,1\n")
    (out / "learned_vs_baselines.md").write_text("# old\n")
    return out, tree(out)


def fresh(previous: tuple[Path, dict], tmp_path: Path) -> Path:
    out = tmp_path / "report"
    shutil.copytree(previous[0], out)
    return out


def test_no_baselines_after_a_full_report_leaves_no_old_baseline_files(sweep, previous,
                                                                       tmp_path):
    out = fresh(previous, tmp_path)
    proc = report(sweep, out)
    assert proc.returncode == 0, proc.stderr
    names = set(os.listdir(out))
    assert "baselines.csv" not in names and "learned_vs_baselines.md" not in names
    assert {"table2.md", "summary.md", "fig4_pg.png", ".uabs-report"} <= names
    assert os.listdir(tmp_path) == ["report"]  # no temporary folder left beside it


@pytest.mark.parametrize("sig, code", [("SIGKILL", -9), ("SIGTERM", 143)])
def test_a_report_killed_mid_write_leaves_the_previous_one_whole(sweep, previous, tmp_path,
                                                                 sig, code):
    out = fresh(previous, tmp_path)
    proc = report(sweep, out, hook=KILL_AT_COMPARISON.format(sig=sig))
    if sig == "SIGTERM":
        one_line(proc, "interrupted", code=143)
        assert os.listdir(tmp_path) == ["report"]
    else:
        assert proc.returncode == code
        assert [n for n in os.listdir(tmp_path) if n != "report"]  # its temporary folder
    assert tree(out) == previous[1]  # the previous report, byte for byte, and only it
    if sig == "SIGKILL":  # the next start removes what the killed one left
        one_line(command("report", str(sweep), str(tmp_path / "nowhere"), "--out", str(out)))
        assert os.listdir(tmp_path) == ["report"] and tree(out) == previous[1]


KILL_BETWEEN_RENAMES = """
import os, signal
from pathlib import Path
_replace = os.replace
def replace(src, dst):
    _replace(src, dst)
    if Path(dst).name.startswith(".report.old-"):  # the old folder moved away, new not in
        os.kill(os.getpid(), signal.SIGKILL)
os.replace = replace
"""


def test_a_report_killed_between_the_renames_is_finished_by_the_next_start(sweep, previous,
                                                                         tmp_path):
    out = fresh(previous, tmp_path)
    proc = report(sweep, out, hook=KILL_BETWEEN_RENAMES)
    assert proc.returncode == -9 and not out.exists()
    # the next command finds the complete new report and puts it in place (then refuses
    # its own bad input, writing nothing)
    one_line(command("report", str(sweep), str(tmp_path / "nowhere"), "--out", str(out)))
    assert os.listdir(tmp_path) == ["report"]
    names = set(os.listdir(out))
    assert ".uabs-report" in names and "baselines.csv" not in names
    assert "table2.md" in names and "summary.md" in names


def test_a_full_disk_and_foreign_files_leave_the_folder_untouched(sweep, previous, tmp_path):
    out = fresh(previous, tmp_path)
    full = KILL_AT_COMPARISON.replace("os.kill(os.getpid(), signal.{sig})",
                                      "raise OSError(28, 'No space left on device')")
    one_line(report(sweep, out, hook=full), "--out", "no space left on the device")
    assert tree(out) == previous[1] and os.listdir(tmp_path) == ["report"]
    (out / "notes.txt").write_text("mine\n")
    kept = tree(out)
    one_line(report(sweep, out), "notes.txt", "did not write")
    assert tree(out) == kept
    assert tree(out) == kept and sorted(os.listdir(tmp_path)) == ["report"]


@pytest.mark.parametrize("args, words", [
    (["--out", "{out}/notes.txt"], ["is a file, not a folder"]),
    (["--out", "{tmp}/" + LONG], ["--out", "300 bytes"]),
    (["{tmp}/" + LONG], ["FOLDER", "300 bytes"]),
    (["{tmp}/nowhere"], ["nowhere"]),
])
def test_report_refusals_are_one_line(sweep, tmp_path, capsys, args, words):
    from uabs_rl.cli.report import main

    out = tmp_path / "report"
    out.mkdir()
    (out / "notes.txt").write_text("mine\n")
    kept = tree(tmp_path)
    args = [a.format(out=out, tmp=tmp_path) for a in args]
    assert main([str(sweep) if len(args) == 2 else args[0], "--no-baselines",
                 *(args if len(args) == 2 else [])]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and all(w in err[0] for w in words), err
    assert tree(tmp_path) == kept


# ----------------------------------------------------------------------------- eval folders
def test_eval_on_another_split_leaves_none_of_the_previous_pictures(runs, tmp_path):
    out = tmp_path / "ev"
    first = command("evaluate", str(runs["dqn"]), "--policy", "learned", "--policy", "greedy",
                    "--out", str(out))
    assert first.returncode == 0, first.stderr
    assert (out / "trajectories_greedy.png").is_file()
    second = command("evaluate", str(runs["dqn"]), "--split", "eval", "--out", str(out))
    assert second.returncode == 0, second.stderr
    assert sorted(os.listdir(out)) == [".uabs-eval", "eval.json", "trajectories_learned.pdf",
                                       "trajectories_learned.png"]
    assert '"split": "eval"' in (out / "eval.json").read_text()
    assert os.listdir(tmp_path) == ["ev"]


# ----------------------------------------------------------------------------- foreign checkpoints
def test_a_checkpoint_of_another_run_is_refused(runs, tmp_path):
    """A VDN run's best.pt copied into the 3DQN run: another run id. An egocentric
    run's, into a copy without run.json: other settings than the folder's
    .hydra/config.yaml. uabs-eval and uabs-report refuse both, naming the file."""
    vdn = copy_run(runs["dqn"], tmp_path / "sweep" / "vdn_copied")
    shutil.copy(runs["vdn"] / "checkpoints" / "best.pt", vdn / "checkpoints" / "best.pt")
    one_line(command("evaluate", str(vdn), "--out", str(tmp_path / "ev")),
             str(vdn / "checkpoints" / "best.pt"), "another run")
    ego = copy_run(runs["dqn"], tmp_path / "ego_copied")
    (ego / "run.json").unlink()
    shutil.copy(runs["ego"] / "checkpoints" / "best.pt", ego / "checkpoints" / "best.pt")
    one_line(command("evaluate", str(ego), "--out", str(tmp_path / "ev")),
             str(ego / "checkpoints" / "best.pt"), ".hydra/config.yaml", "obs.")
    one_line(command("report", str(tmp_path / "sweep")), "best.pt", "another run")
    assert not (tmp_path / "ev").exists() and not (tmp_path / "sweep" / "report").exists()


def test_eval_bad_inputs_are_one_line(runs, tmp_path):
    empty = copy_run(runs["dqn"], tmp_path / "run")
    (empty / "checkpoints" / "best.pt").write_bytes(b"")
    one_line(command("evaluate", str(empty)), "best.pt", "empty")
    assert sorted(os.listdir(tmp_path)) == ["run"] and not (empty / "evaluation").exists()


@pytest.mark.parametrize("args, words", [
    (["{run}", "--split", "bogus"], ["--split", "bogus"]),
    (["{tmp}/" + LONG], ["PATH", "300 bytes"]),
    (["{run}", "--out", "{tmp}/" + LONG], ["--out", "300 bytes"]),
    (["{run}", "scenario=../scenario/x"], ["scenario=", "holds a /"]),
])
def test_eval_refusals_are_one_line(runs, tmp_path, capsys, args, words):
    from uabs_rl.cli.evaluate import main

    args = [a.format(run=runs["dqn"], tmp=tmp_path) for a in args]
    try:
        code = main(args)
    except SystemExit as e:  # argparse
        code = e.code
    assert code == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and all(w in err[0] for w in words), err
    assert os.listdir(tmp_path) == []


def test_uabs_traces_checks_its_split_and_cache_folder(tmp_path):
    from tests.conftest import compose_cfg
    from uabs_rl.cli.traces import build
    from uabs_rl.config import ConfigError

    cfg = compose_cfg("build_traces", [*SMALL_TRACES, "split=bogus",
                                       f"traces.cache_dir={tmp_path}"])
    with pytest.raises(ConfigError, match="^split must be one of train, eval, test or all"):
        build(cfg)
    cfg = compose_cfg("build_traces", [*SMALL_TRACES, "split=eval",
                                       f"traces.cache_dir={tmp_path / LONG}"])
    with pytest.raises(ConfigError, match="^traces.cache_dir: .* 300 bytes long"):
        build(cfg)
    assert os.listdir(tmp_path) == []
