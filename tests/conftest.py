from __future__ import annotations

from pathlib import Path

import pytest

from uabs_rl.config import compose
from uabs_rl.traces.build import get_traces

# A small but real SUMO case: 20 vehicles, 60 s recorded after 10 s of warm-up.
SMALL_TRACES = [
    "scenario.sumo.fleet_size=20",
    "traces.train.n_sims=2",
    "traces.train.duration_s=60",
    "traces.train.warmup_s=10",
    "traces.eval.n_sims=1",
    "traces.eval.duration_s=60",
    "traces.eval.warmup_s=10",
]


def compose_cfg(config_name: str, overrides: list[str]):
    """Compose a config exactly as the CLI would, and return it as dataclasses."""
    return compose(config_name, overrides)


@pytest.fixture(scope="session")
def trace_cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("trace_cache")


@pytest.fixture(scope="session")
def small_traces_cfg(trace_cache):
    return compose_cfg("build_traces", SMALL_TRACES + [f"traces.cache_dir={trace_cache}"])


@pytest.fixture(scope="session")
def train(small_traces_cfg):
    """The small case's training traces (2 sims x 60 s, 20 vehicles)."""
    return get_traces(small_traces_cfg.scenario, small_traces_cfg.traces, "train")


@pytest.fixture(scope="session")
def held_out(small_traces_cfg):
    """The small case's held-out traces (1 sim x 60 s)."""
    return get_traces(small_traces_cfg.scenario, small_traces_cfg.traces, "eval")
