"""Which settings change results: each setting's role is declared once, in the schemas,
and every list that tells settings apart is derived from it (uabs_rl.config.roles):
resume's compatibility check, the report's grouping, uabs-eval's overrides and the
settings Hydra leaves out of run folder names."""

from __future__ import annotations

from omegaconf import OmegaConf

from tests.test_faults import uabs_train_here
from tests.test_run_folder_faults import copy_of, finished_run  # noqa: F401
from uabs_rl.config import (
    CONF_DIR,
    Role,
    default_settings,
    folder_name_excludes,
    keys_with_role,
    setting_roles,
)
from uabs_rl.evaluation.load import EVAL_GROUPS
from uabs_rl.runs import sweep
from uabs_rl.runs.checkpoint import COMPAT_KEYS, config_differences
from uabs_rl.runs.metrics import read_metrics

RUNTIME = {"traces.cache_dir", "traces.workers", "train.checkpoint_buffer", "train.logger",
           "train.trajectory_images", "train.progress", "train.compile", "train.compile_update",
           "train.threads",
           "device", "resume"}


def test_every_setting_has_one_role():
    roles = setting_roles()
    assert list(roles) == list(default_settings())  # learners' own settings included
    assert roles["algo.mixing_embed_dim"] == Role.policy
    assert roles["traces.test.n_sims"] == Role.test and roles["obs.name"] == Role.label
    assert set(keys_with_role(Role.runtime)) == RUNTIME


def test_hydra_leaves_out_of_folder_names_the_derived_list():
    """conf/config.yaml's exclude_keys is the runtime settings and Hydra's own, in the
    schemas' order."""
    yaml = OmegaConf.load(CONF_DIR / "config.yaml")
    assert list(yaml.hydra.job.config.override_dirname.exclude_keys) == folder_name_excludes()


def test_the_lists_agree():
    """A report never tells runs apart by a setting resume ignores, except the test
    traces and the protocol (how long, how often, where evaluations start), which
    change what is reported; resume keeps the seed, the learner's implementation and the
    population, which the report pools."""
    settings = set(setting_roles())
    neutral = set(sweep.NEUTRAL)
    assert neutral == RUNTIME | {"seed", "train.population", "algo.loss", "obs.name"}
    ignored_on_resume = settings - COMPAT_KEYS
    assert ignored_on_resume - neutral == {
        *(k for k in settings if k.startswith("traces.test.")),
        "train.episodes", "train.eval_every", "train.eval_windows", "train.eval_seed"}
    assert COMPAT_KEYS & neutral == {"seed", "train.population", "algo.loss"}
    assert EVAL_GROUPS == ("scenario", "channel", "masking", "traces")
    assert set(sweep.ENV_SETTINGS) == {k for k in settings if k.split(".")[0] in EVAL_GROUPS
                                       and k not in RUNTIME} | {"train.eval_seed"}
    assert not set(folder_name_excludes()) & (settings - RUNTIME)


def test_resume_ignores_what_changes_no_result():
    saved = {"traces": {"workers": 0, "cache_dir": "a", "test": {"n_sims": 8}},
             "obs": {"name": "paper"}, "train": {"threads": None, "episodes": 6}}
    now = {"traces": {"workers": 4, "cache_dir": "b", "test": {"n_sims": 2}},
           "obs": {"name": "mine"}, "train": {"threads": 2, "episodes": 9}}
    assert config_differences(saved, now) == []
    assert config_differences({"algo": {"loss": "fused"}}, {"algo": {"loss": "torchrl"}}) == [
        "algo.loss: 'fused' in the checkpoint, 'torchrl' now"]


def test_the_original_command_resumes_with_traces_workers_appended(finished_run, tmp_path):  # noqa: F811
    """``uabs-train <original command> resume=<run> traces.workers=4``: SUMO's worker
    processes change no result, so the run continues."""
    run_dir, args = finished_run
    run_dir = copy_of(run_dir, tmp_path)
    p = uabs_train_here(tmp_path, *args, "train.episodes=6", f"resume={run_dir}",
                        "traces.workers=4")
    assert p.returncode == 0, p.stderr[-2000:]
    assert [r["episode"] for r in read_metrics(run_dir / "metrics.jsonl")
            if r["kind"] == "train"] == list(range(1, 7))
