"""Checkpoints and ``uabs-eval`` answer a bad input with one line naming the file (or
setting) and the fix: damaged or foreign files, checkpoints with parts missing or of
another network, NaN weights, folders without checkpoints, an unusable ``--out``; and
``uabs-eval`` prints fractions as percentages."""

from __future__ import annotations

import copy
import json
import pickle
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.test_train import smoke
from uabs_rl.algorithms.model import DuelingQNet
from uabs_rl.cli import evaluate
from uabs_rl.cli.evaluate import main as eval_main
from uabs_rl.config import ConfigError
from uabs_rl.evaluation.load import default_out_dir
from uabs_rl.runs.checkpoint import CheckpointError, load_checkpoint, load_into
from uabs_rl.traces.build import get_traces
from uabs_rl.training.resume import run


@pytest.fixture(scope="module")
def ckpt_run(trace_cache, tmp_path_factory) -> Path:
    """A smoke run whose checkpoints hold the replay buffer too (every optional part),
    its test traces built (SUMO's progress bar stays out of the captured errors)."""
    d = tmp_path_factory.mktemp("ckpt_faults_run")
    cfg = smoke(trace_cache, "train.logger=none", "train.trajectory_images=false",
                "train.checkpoint_buffer=true", "train.threads=1")
    run(cfg, d)
    get_traces(cfg.scenario, cfg.traces, "test")
    return d


@pytest.fixture(scope="module")
def state(ckpt_run) -> dict:
    return torch.load(ckpt_run / "checkpoints" / "best.pt", weights_only=True)


def one_line_error(capsys, *names: str) -> str:
    """The stderr of a refused command: one ``error:`` line naming each of ``names``,
    never torch's advice to load unsafely."""
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "weights_only" not in err and "Traceback" not in err
    for n in names:
        assert n in err, (n, err)
    return lines[0]


def edited(tmp_path: Path, state: dict, edit) -> Path:
    """A copy of ``state`` changed by ``edit``, saved as a checkpoint file."""
    st = copy.deepcopy(state)
    edit(st)
    path = tmp_path / "edited.pt"
    torch.save(st, path)
    return path


# ------------------------------------------------------------------ unreadable files
def _zip_of_text(p: Path) -> None:
    with zipfile.ZipFile(p, "w") as z:
        z.writestr("notes.txt", "not a checkpoint")


def _zip_with_bad_pickle(p: Path) -> None:
    with zipfile.ZipFile(p, "w") as z:
        z.writestr("archive/data.pkl", "x")
        z.writestr("archive/version", "3")


@pytest.mark.parametrize("make, reason", [
    (lambda p: p.write_bytes(b""), "the file is empty"),
    (lambda p: p.write_text("epoch 3: loss 0.1\n"), "not a file written by torch.save"),
    (_zip_of_text, "a zip archive that torch.save did not write"),
    (_zip_with_bad_pickle, "its pickled data is not readable"),
    (lambda p: pickle.dump({"format": 1}, p.open("wb")), "its pickled data is not readable"),
    (lambda p: torch.save({"format": 1, "x": np.zeros(3)}, p), "holds Python objects"),
    (lambda p: torch.save(torch.zeros(3), p), "holds a Tensor, not a uabs-train checkpoint"),
    (lambda p: torch.save({"learner": {}}, p), "(it has no format entry)"),
])
def test_a_file_that_is_no_checkpoint_is_one_line_without_torchs_advice(
        tmp_path, capsys, make, reason):
    path = tmp_path / "model.pt"
    make(path)
    assert eval_main([str(path)]) == 2
    one_line_error(capsys, str(path), reason)


def test_a_truncated_checkpoint_names_the_file(ckpt_run, tmp_path, capsys):
    data = (ckpt_run / "checkpoints" / "best.pt").read_bytes()
    for n, cut in enumerate((1000, len(data) - 100)):
        path = tmp_path / f"cut{n}.pt"
        path.write_bytes(data[:cut])
        assert eval_main([str(path)]) == 2
        one_line_error(capsys, str(path), "damaged")


def test_a_folder_given_as_the_checkpoint_file(tmp_path):
    folder = tmp_path / "last.pt"
    folder.mkdir()
    with pytest.raises(CheckpointError, match=r"last\.pt: it is a folder"):
        load_checkpoint(folder)


# ------------------------------------------------------------------ checkpoint structure
def _set(*keys, value):
    def edit(st):
        d = st
        for k in keys[:-1]:
            d = d[k]
        d[keys[-1]] = value
    return edit


def _del(*keys):
    def edit(st):
        d = st
        for k in keys[:-1]:
            d = d[k]
        del d[keys[-1]]
    return edit


@pytest.mark.parametrize("edit, names", [
    (_del("learner"), ["is not a complete uabs-train checkpoint: it lacks learner."]),
    (_del("learner", "qnet"), ["it lacks learner.qnet."]),
    (_set("learner", "qnet", value="weights"),
     ["learner.qnet is a str, expected a dict of tensors"]),
    (_del("counters", "episode"), ["it lacks counters.episode."]),
    (_set("rng", "torch", value=torch.zeros(3)), ["rng.torch is a Tensor, expected a uint8"]),
    (_set("replay", "written", value="10"), ["replay.written is a str, expected an integer"]),
    (_set("format", value=3), ["not a uabs-train checkpoint of format 2 (it has format 3)"]),
    (_set("config", value="manhattan"), ["edited.pt: config is a str, expected a dict"]),
    (_set("config", value={}), ["its config is empty"]),
    (_del("config", "seed"), ["its config lacks config.seed"]),
    (_set("config", "scenario", value="manhattan"),
     ["config.scenario is a str ('manhattan'), expected the scenario settings"]),
    (_set("config", "algo", "lrr", value=1.0),
     ["its stored config does not fit uabs_rl's settings (config.algo.lrr: Key 'lrr' not "
      "in 'AlgoConfig')"]),
    (_set("config", "masking", "mode", value="soft"),
     ["(config.masking.mode: Invalid value 'soft'"]),
])
def test_a_checkpoint_with_parts_missing_or_wrong_is_refused_naming_the_part(
        state, tmp_path, capsys, edit, names):
    path = edited(tmp_path, state, edit)
    assert eval_main([str(path), "--split", "eval"]) == 2
    one_line_error(capsys, str(path), *names)


@pytest.mark.parametrize("edit, names", [
    (_set("learner", "qnet", "trunk.0.weight", value=torch.zeros(16, 18)),
     ["the checkpoint's network does not fit its config (algo.hidden=[32, 32] on "
      "observations of size 18): learner.qnet.trunk.0.weight is [16, 18] in the "
      "checkpoint, [32, 18] here"]),
    (_set("config", "algo", "hidden", value=[64, 64]),
     ["learner.qnet.trunk.0.weight is [32, 18] in the checkpoint, [64, 18] here"]),
    (_set("config", "algo", "hidden", value=[32]), ["learner.qnet.trunk.2.weight is not part "
                                                    "of this network"]),
    (_del("learner", "target", "value.bias"), ["learner.target.value.bias is missing"]),
    (_set("learner", "optim", "state", 0, "exp_avg", value=torch.zeros(3)),
     ["the optimiser state does not fit the network: learner.optim.state.0.exp_avg is [3], "
      "expected [32, 18] (as trunk.0.weight)"]),
])
def test_a_network_of_another_size_names_the_tensor_and_both_shapes(
        state, tmp_path, capsys, edit, names):
    path = edited(tmp_path, state, edit)
    assert eval_main([str(path), "--split", "eval"]) == 2
    one_line_error(capsys, str(path), *names)
    with pytest.raises(CheckpointError):  # resume and populations load through it too
        load_checkpoint(path)


def test_load_into_names_the_tensor_and_both_shapes(state, tmp_path):
    net = DuelingQNet(18, 4, [16])
    with pytest.raises(CheckpointError, match=r"x\.pt: the checkpoint's network does not fit "
                       r"this config: learner\.qnet\.trunk\.0\.weight is \[32, 18\] in the "
                       r"checkpoint, \[16, 18\] here"):
        load_into(net, state["learner"]["qnet"], tmp_path / "x.pt", "learner.qnet")
    fits = DuelingQNet(18, 4, [32, 32])
    load_into(fits, state["learner"]["qnet"], tmp_path / "x.pt", "learner.qnet")
    assert all(torch.equal(a, b) for a, b in zip(fits.state_dict().values(),
                                                 state["learner"]["qnet"].values(),
                                                 strict=True))


def test_nan_weights_are_refused_naming_the_tensor(state, tmp_path, capsys):
    def poison(st):
        st["learner"]["qnet"]["advantage.weight"][0, :2] = torch.tensor([np.nan, np.inf])
    path = edited(tmp_path, state, poison)
    assert eval_main([str(path), "--split", "eval"]) == 2
    one_line_error(capsys, str(path), "learner.qnet.advantage.weight holds 1 NaN and 1 "
                   "infinite values (of 128)", "the training diverged")


# ------------------------------------------------------------------ settings
def test_an_episode_longer_than_the_held_out_traces_names_the_settings(ckpt_run, capsys):
    assert eval_main([str(ckpt_run), "scenario.episode_steps=500"]) == 2
    one_line_error(capsys, "scenario.episode_steps=500 needs windows of 501 steps but the "
                   "test traces hold 200 steps (traces.test.duration_s=200 s at "
                   "scenario.dt=1 s): lower scenario.episode_steps or raise "
                   "traces.test.duration_s.")
    assert eval_main([str(ckpt_run), "scenario.episode_steps=500", "--split", "eval"]) == 2
    one_line_error(capsys, "the eval traces hold 100 steps (traces.eval.duration_s=100 s")


def test_a_window_longer_than_the_episode_is_refused_by_uabs_eval(ckpt_run, capsys):
    assert eval_main([str(ckpt_run), "scenario.window_steps=50", "--split", "eval"]) == 2
    one_line_error(capsys, "scenario.window_steps", "got 50")


def test_too_many_validation_windows_name_train_eval_windows(trace_cache, tmp_path):
    with pytest.raises(ConfigError, match=r"^train\.eval_windows=1000 but the eval traces hold "
                       r"4 non-overlapping windows of 20 steps \(21 recorded instants "
                       r"each; 1 x 100 instants\): lower "
                       r"train\.eval_windows or raise traces\.eval\.n_sims / "
                       r"traces\.eval\.duration_s\.$"):
        run(smoke(trace_cache, "train.eval_windows=1000", "train.logger=none",
                  "train.threads=1"), tmp_path)


# ------------------------------------------------------------------ paths
def test_a_population_folder_points_to_its_members(ckpt_run, tmp_path, capsys):
    for s in (0, 1):
        d = tmp_path / f"seed={s}" / "checkpoints"
        d.mkdir(parents=True)
        (d / "best.pt").write_bytes((ckpt_run / "checkpoints" / "best.pt").read_bytes())
    assert eval_main([str(tmp_path)]) == 2
    one_line_error(capsys, f"{tmp_path} is a population: evaluate one member, e.g. uabs-eval "
                   f"{tmp_path / 'seed=0'}, or report all with uabs-report {tmp_path}.")


def test_a_folder_without_the_checkpoint_says_what_was_looked_for(ckpt_run, tmp_path, capsys):
    assert eval_main([str(tmp_path)]) == 2
    one_line_error(capsys, f"no checkpoint at {tmp_path / 'checkpoints' / 'best.pt'}",
                   "not a uabs-train run folder")
    only_last = tmp_path / "run"
    (only_last / "checkpoints").mkdir(parents=True)
    (only_last / "checkpoints" / "last.pt").write_bytes(
        (ckpt_run / "checkpoints" / "last.pt").read_bytes())
    assert eval_main([str(only_last)]) == 2
    one_line_error(capsys, f"{only_last / 'checkpoints'} holds only last.pt; evaluate it "
                   f"with --checkpoint last.")
    assert eval_main([str(ckpt_run / "checkpoints")]) == 2
    one_line_error(capsys, "is a run's checkpoints folder", f"uabs-eval {ckpt_run},")
    started = tmp_path / "started"
    started.mkdir()
    (started / "metrics.jsonl").write_text("")
    assert eval_main([str(started)]) == 2
    one_line_error(capsys, "stopped before its first evaluation",
                   f"uabs-train resume={started}")
    assert eval_main([str(tmp_path / "nowhere")]) == 2
    one_line_error(capsys, "no such file or folder")


@pytest.mark.parametrize("out, names", [
    ("file", ["is a file, not a folder"]),
    ("file/sub", ["cannot be made:", "is a file, not a folder"]),
    ("/sys/uabs_eval_out", ["cannot be"]),
])
def test_an_unusable_out_folder_is_refused_before_evaluating(
        ckpt_run, tmp_path, capsys, monkeypatch, out, names):
    if out.startswith("/sys") and not Path("/sys").is_dir():
        pytest.skip("no /sys here")
    (tmp_path / "file").write_text("x")
    target = Path(out) if out.startswith("/") else tmp_path / out
    ran = []
    monkeypatch.setattr(evaluate, "evaluate_policies", lambda *a, **k: ran.append(1))
    assert eval_main([str(ckpt_run), "--split", "eval", "--out", str(target)]) == 2
    one_line_error(capsys, f"--out {target}", "pass a folder you can write with --out",
                   *names)
    assert not ran


def test_a_checkpoint_file_outside_a_run_writes_beside_itself(tmp_path):
    assert default_out_dir(tmp_path / "x.pt") == tmp_path / "evaluation"
    run_dir = tmp_path / "run"
    assert default_out_dir(run_dir / "checkpoints" / "best.pt") == \
        run_dir / "evaluation"


def test_a_checkpoint_file_is_named_as_what_was_evaluated(ckpt_run, tmp_path, capsys):
    """``uabs-eval RUN/checkpoints/last.pt`` prints and records the file it evaluated
    (it said "best checkpoint" of any file); ``--checkpoint`` beside a file is refused."""
    last = ckpt_run / "checkpoints" / "last.pt"
    out = tmp_path / "ev"
    assert eval_main([str(last), "--split", "eval", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"steps, checkpoint {last}" in text and "best checkpoint" not in text
    assert json.loads((out / "eval.json").read_text())["checkpoint"] == str(last)
    # a second evaluation into the same folder says what it replaced
    assert eval_main([str(ckpt_run), "--split", "eval", "--policy", "greedy",
                      "--out", str(out)]) == 0
    assert ("they replace the evaluation of learned that was there (--out DIR writes "
            "another folder)") in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        eval_main([str(last), "--checkpoint", "best", "--out", str(tmp_path / "no")])
    assert e.value.code == 2 and not (tmp_path / "no").exists()
    err = capsys.readouterr().err
    assert "--checkpoint best chooses a run folder's checkpoint" in err and str(last) in err


# ------------------------------------------------------------------ formats
def test_number_formats():
    assert evaluate.percent(0.12345) == "12.3 %" and evaluate.percent(-1e-5) == "0.0 %"
    assert evaluate.points({"diff": 0.012, "ci_low": -0.003, "ci_high": 0.027}) == \
        "+1.2 pt [-0.3, +2.7]"
    assert evaluate.return_difference({"diff": 45.56, "ci_low": -82.2, "ci_high": -0.4}) == \
        "+46 [-82, +0]"
    assert evaluate.whole(-45.5) == "-46" and evaluate.whole(0.4, sign=True) == "+0"


def test_uabs_eval_prints_percentages_and_whole_returns(ckpt_run, tmp_path, capsys):
    out = tmp_path / "ev"
    assert eval_main([str(ckpt_run), "--split", "eval", "--policy", "all",
                      "--out", str(out)]) == 0
    text = capsys.readouterr().out
    res = json.loads((out / "eval.json").read_text())
    rows = {line.split()[0]: line.split() for line in text.splitlines()
            if line.split() and line.split()[0] in res["policies"]
            and line.split()[1].lstrip("-").isdigit()}
    assert set(rows) == {"learned", "random", "greedy", "oracle"}
    for name, cells in rows.items():
        rec = res["policies"][name]
        assert cells[1] == str(round(rec["return"]))
        assert cells[6:] == [f"{100 * rec['served_fraction']:.1f}", "%",
                             f"{100 * rec['pg']:.1f}", "%"]
    d = res["differences"]["greedy"]
    line = next(ln for ln in text.splitlines() if ln.strip().startswith("greedy  R:"))
    assert evaluate.return_difference(d["return"]) in line
    assert evaluate.points(d["served_fraction"]) in line and " pt [" in line


def test_a_format_1_checkpoint_loads_with_its_replay_in_todays_layout(state, tmp_path):
    """Format 1 held the replay as a flat ring of per-agent transitions; it loads as
    format 2 with the same transitions in the same step slots."""
    replay = state["replay"]
    m, held = replay["data"]["obs"].shape[1], replay["data"]["obs"].shape[0]
    size = held * m  # the smoke run's buffer has not wrapped
    cap = state["config"]["algo"]["buffer_size"]
    assert size < cap and state["counters"]["env_steps"] * m == size  # n_envs = 1
    old = {**state, "format": 1, "replay": {
        "data": {k: v.reshape(size, *v.shape[2:]) for k, v in replay["data"].items()},
        "cursor": size % cap, "size": size, "generator": replay["generator"]}}
    torch.save(old, tmp_path / "old.pt")
    loaded = load_checkpoint(tmp_path / "old.pt")
    assert loaded["format"] == 2 and loaded["replay"]["written"] == replay["written"]
    for k, v in replay["data"].items():
        assert torch.equal(loaded["replay"]["data"][k], v), k


def test_a_run_saved_before_settings_were_added_resumes_with_their_defaults(
        ckpt_run, trace_cache, tmp_path):
    """A checkpoint (and run folder) written before algo.replay, algo.priority_* and
    algo.mixing_embed_dim existed resumes: an absent setting is its default, not a
    difference of settings."""
    import shutil

    import yaml

    run_dir = tmp_path / "old"
    shutil.copytree(ckpt_run, run_dir)
    added = ("replay", "priority_alpha", "priority_beta", "mixing_embed_dim")
    for name in ("last.pt", "best.pt"):
        path = run_dir / "checkpoints" / name
        st = torch.load(path, weights_only=True)
        st["config"]["algo"] = {k: v for k, v in st["config"]["algo"].items() if k not in added}
        torch.save(st, path)
    hydra_cfg = run_dir / ".hydra" / "config.yaml"
    if hydra_cfg.exists():
        d = yaml.safe_load(hydra_cfg.read_text())
        d["algo"] = {k: v for k, v in d["algo"].items() if k not in added}
        hydra_cfg.write_text(yaml.safe_dump(d))
    episodes = int(st["config"]["train"]["episodes"]) + 1
    # the original command re-typed with a new setting at its default, resume= appended
    again = [f"resume={run_dir}", f"train.episodes={episodes}", "algo.replay=uniform"]
    run(smoke(trace_cache, *again), Path("unused"), overrides=again)
    assert load_checkpoint(run_dir / "checkpoints" / "last.pt")["counters"]["episode"] == episodes
    with pytest.raises(CheckpointError, match=r"algo\.replay: 'uniform' in the checkpoint"):
        bad = [f"resume={run_dir}", "algo.replay=prioritized"]
        run(smoke(trace_cache, *bad), Path("unused"), overrides=bad)
