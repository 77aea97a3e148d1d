"""Bad inputs get one clear message naming the input and the fix (docs/bad_inputs.md
lists them with the test behind each)."""

from __future__ import annotations

import pickle
from pathlib import Path

import pytest
import torch
from omegaconf.errors import ValidationError

from tests.conftest import SMALL_TRACES, compose_cfg, run_command
from tests.test_train import records, smoke
from uabs_rl.cli.evaluate import main as eval_main
from uabs_rl.config import ConfigError
from uabs_rl.runs.checkpoint import CheckpointError, load_checkpoint
from uabs_rl.runs.metrics import MetricsError, read_metrics
from uabs_rl.safety.make import resolve_device
from uabs_rl.training.resume import prepare, run
from uabs_rl.training.startup import validate_run


def test_malformed_network_file_names_the_key(tmp_path, trace_cache):
    bad = tmp_path / "bad.net.xml"
    bad.write_text('<net version="1.20"><location netOffset="0,0"/><edge id="e"/></net>')
    from uabs_rl.traces.build import get_traces

    cfg = compose_cfg("build_traces", SMALL_TRACES + [f"traces.cache_dir={trace_cache}",
                                                      f"scenario.sumo.net_file={bad}"])
    with pytest.raises(ConfigError, match=r"scenario\.sumo\.net_file: .* not a SUMO network"):
        get_traces(cfg.scenario, cfg.traces, "eval")


def test_uabs_traces_config_error_is_one_line(trace_cache):
    proc = run_command("traces", "scenario.dt=-1", f"traces.cache_dir={trace_cache}")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == ["error: scenario.dt must be > 0 seconds, "
                                                "got -1.0."]


@pytest.mark.parametrize("line, why", [
    (b'{"kind": "tr', "not JSON"), (b"17", "not a train or eval record"),
    (b"\xff\xfe{}", "not UTF-8 text"),
    (b'{"kind": "train", "episode": "3", "env_steps": 60}', "its episode or env_steps")])
def test_corrupt_metrics_line_names_the_file_and_line(tmp_path, line, why):
    """Every line resume refuses, uabs-report refuses too: one line naming file, line and
    why (a bare number or bytes that are not text once ended in a traceback)."""
    m = tmp_path / "metrics.jsonl"
    m.write_bytes(b'{"kind": "train", "episode": 1, "env_steps": 20}\n' + line + b"\n")
    with pytest.raises(MetricsError, match=rf"metrics\.jsonl, line 2, is {why}"):
        read_metrics(m)


def test_pickled_objects_are_refused_without_unsafe_advice(tmp_path):
    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    path = tmp_path / "evil.pt"
    torch.save({"format": 1, "x": Evil()}, path, pickle_module=pickle)
    with pytest.raises(CheckpointError, match="could run code") as e:
        load_checkpoint(path)
    assert "weights_only" not in str(e.value)


def test_uabs_eval_windows_names_the_flag(rank_run, capsys):
    with pytest.raises(SystemExit):
        eval_main([str(rank_run), "--windows", "-1"])
    assert "--windows must be >= 1" in capsys.readouterr().err
    assert eval_main([str(rank_run), "--split", "eval", "--windows", "1000"]) == 2
    err = capsys.readouterr().err
    assert "--windows 1000" in err and "n_eval_windows" not in err


@pytest.fixture(scope="module")
def rank_run(trace_cache, tmp_path_factory):
    d = tmp_path_factory.mktemp("bad_inputs_run")
    run(smoke(trace_cache, "train.trajectory_images=false", "train.logger=none"), d)
    assert records(d)
    return d


@pytest.mark.parametrize("override,message", [
    ("train.episodes=7", r"train\.episodes must be a multiple of train\.n_envs"),
    ("scenario.episode_steps=400", r"traces hold \d+ steps but an episode needs"),
])
def test_more_config_values_fail_naming_the_key(trace_cache, tmp_path, override, message):
    cfg = smoke(trace_cache, override, "train.n_envs=2") if "episodes" in override else \
        smoke(trace_cache, override)
    with pytest.raises(ConfigError, match=message):
        validate_run(cfg)
        run(cfg, tmp_path / "run")


def test_eval_every_that_n_envs_does_not_divide_evaluates_after_each_multiple(
        trace_cache, tmp_path):
    """Rounds of n_envs = 2 episodes, train.eval_every = 3: an evaluation after the round
    that reaches each multiple of 3 (episodes 4 and 6) and at the end (before: only at
    common multiples, every 6, half those asked for); a run stopped at 4 and continued by
    its command with resume= appended evaluates as the run that did not stop."""
    args = ["train.n_envs=2", "train.eval_every=3", "train.trajectory_images=false",
            "train.logger=none"]
    whole, part = tmp_path / "whole", tmp_path / "part"
    run(smoke(trace_cache, *args, "train.episodes=8"), whole)
    run(smoke(trace_cache, *args, "train.episodes=4"), part)
    more = [*args, "train.episodes=8", f"resume={part}"]
    prepare(smoke(trace_cache, *more), Path("unused"), overrides=more).fit()
    for d in (whole, part):
        assert [r["episode"] for r in records(d) if r["kind"] == "eval"] == [4, 6, 8]


def test_unknown_masking_mode_is_rejected_at_composition(trace_cache):
    with pytest.raises(Exception) as e:
        smoke(trace_cache, "masking.mode=soft")
    text = str(e.value) + str(e.value.__cause__)
    assert "soft" in text and "penalty" in text and "rank" in text
    assert isinstance(e.value, ValidationError) or "masking.mode" in text


def test_cuda_on_a_machine_without_it(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ConfigError, match=r"device=cuda but CUDA is not available.*device=cpu"):
        resolve_device("cuda")
