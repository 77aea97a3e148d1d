"""TensorBoard (and CSV) logs of a run killed after a checkpoint and resumed: each step
once, every value as metrics.jsonl holds it, one run in TensorBoard."""

from __future__ import annotations

from pathlib import Path

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.compat.proto.event_pb2 import Event
from tensorboard.compat.proto.summary_pb2 import Summary

from tests.test_train import records, smoke
from uabs_rl.training.resume import prepare
from uabs_rl.training.runlog import curves, events_up_to, truncate_csv

RUN = ["train.episodes=3", "train.eval_every=3", "train.threads=1"]


def killed_after_checkpoint(trace_cache, run_dir: Path, *extra: str) -> None:
    """A smoke run checkpointed at episode 3 that logged episodes 4 and 5 (and their
    evaluation) before it died: a resume's starting point."""
    prepare(smoke(trace_cache, *RUN, *extra), run_dir).fit()
    again = [f"resume={run_dir}", "train.episodes=5"]
    exp = prepare(smoke(trace_cache, *again), Path("unused"), overrides=again)
    exp.checkpoints.save = lambda i, name: None  # died before any further checkpoint
    exp.fit()


def resume(trace_cache, run_dir: Path) -> None:
    again = [f"resume={run_dir}", "train.episodes=6"]
    prepare(smoke(trace_cache, *again), Path("unused"), overrides=again).fit()


def accumulator(tb: Path) -> EventAccumulator:
    # purge_orphaned_data=False: TensorBoard's own hiding of steps that go back is off,
    # so a duplicated step shows here
    ea = EventAccumulator(str(tb), size_guidance={"scalars": 0, "images": 0},
                          purge_orphaned_data=False)
    ea.Reload()
    return ea


def curve(ea: EventAccumulator, tag: str) -> list[tuple[int, float]]:
    return [(e.step, e.value) for e in ea.Scalars(tag)]


def test_resumed_tensorboard_holds_each_step_once_as_metrics(trace_cache, tmp_path):
    run_dir = tmp_path / "run"
    killed_after_checkpoint(trace_cache, run_dir)
    recs = records(run_dir)
    assert [r["episode"] for r in recs if r["kind"] == "train"] == [1, 2, 3, 4, 5]
    before = accumulator(run_dir / "tb")
    assert [s for s, _ in curve(before, "train/return")][3:] == [
        r["env_steps"] for r in recs if r["kind"] == "train"][3:]  # logged past the ckpt

    resume(trace_cache, run_dir)
    recs = records(run_dir)
    assert [r["episode"] for r in recs if r["kind"] == "train"] == [1, 2, 3, 4, 5, 6]
    assert [r["episode"] for r in recs if r["kind"] == "eval"] == [3, 6]
    tb = run_dir / "tb"
    # one run: one event file, no timestamped hyper-parameter sub-run
    assert [p.name for p in tb.iterdir() if p.is_dir()] == []
    assert len(list(tb.glob("events.out.tfevents.*"))) == 1
    ea = accumulator(tb)
    assert ea.PluginTagToContent("hparams")  # the HPARAMS tab reads this run itself
    scalars = set(ea.Tags()["scalars"])
    want: dict[str, list[tuple[int, float]]] = {}
    for r in recs:
        for tag, v in curves(r):
            want.setdefault(tag, []).append(
                (r["env_steps"], pytest.approx(v, rel=1e-6, nan_ok=True)))
    assert set(want) <= scalars
    for tag in scalars:
        steps = [s for s, _ in curve(ea, tag)]
        assert steps == sorted(set(steps)), tag  # each step once, in order
        if tag in want:
            assert curve(ea, tag) == want[tag], tag
    # the speed curve and the pictures: dropped after the checkpoint like the rest (the
    # first episode of a run or of a resume has no speed: nothing before it to time)
    steps = {r["episode"]: r["env_steps"] for r in recs if r["kind"] == "train"}
    assert [s for s, _ in curve(ea, "speed/env_steps_per_s")] == [steps[e] for e in (2, 3, 5, 6)]
    evals = [r["env_steps"] for r in recs if r["kind"] == "eval"]
    for tag in ("eval/pg_curve", "eval/trajectories"):
        assert [i.step for i in ea.Images(tag)] == evals, tag


def test_resumed_csv_logs_hold_each_step_once(trace_cache, tmp_path):
    run_dir = tmp_path / "run"
    killed_after_checkpoint(trace_cache, run_dir, "train.logger=csv",
                            "train.trajectory_images=false")
    resume(trace_cache, run_dir)
    train = [r for r in records(run_dir) if r["kind"] == "train"]
    rows = [line.split(",") for line in
            (run_dir / "csv" / "scalars" / "train" / "return.csv").read_text().splitlines()]
    assert [(int(s), float(v)) for s, v in rows] == [
        (r["env_steps"], pytest.approx(r["return"])) for r in train]


def scalar_event(tag: str, step: int, value: float, wall_time: float = 1.0) -> Event:
    return Event(wall_time=wall_time, step=step,
                 summary=Summary(value=[Summary.Value(tag=tag, simple_value=value)]))


def test_events_up_to_rebuilds_what_metrics_hold():
    recs = [{"kind": "train", "episode": 1, "env_steps": 20, "return": 1.5, "updates": 3},
            {"kind": "train", "episode": 2, "env_steps": 40, "return": 2.5, "updates": 5},
            {"kind": "eval", "episode": 2, "env_steps": 40, "return": 7.0}]
    events = [scalar_event("train/return", 20, 1.5, wall_time=10.0),
              scalar_event("speed/env_steps_per_s", 40, 99.0, wall_time=11.0),
              # the killed run's value, then the resumed run's (a resume before the fix)
              scalar_event("train/return", 40, 9.0, wall_time=12.0),
              scalar_event("train/return", 40, 2.5, wall_time=13.0),
              scalar_event("train/return", 60, 3.5, wall_time=14.0),  # after the checkpoint
              scalar_event("train/unknown", 20, 1.0, wall_time=15.0)]  # not in metrics
    # eval/return at 40 never reached the disk: rebuilt from the records
    out = events_up_to(events, 40, recs)
    got = [(e.summary.value[0].tag, e.step, e.summary.value[0].simple_value) for e in out]
    assert got == [("train/return", 20, 1.5), ("speed/env_steps_per_s", 40, 99.0),
                   ("train/return", 40, 2.5), ("eval/return", 40, 7.0)]
    assert [e.wall_time for e in out][:2] == [10.0, 11.0]  # kept events keep their time
    assert all(e.wall_time > 0 for e in out)


def test_truncate_csv_keeps_rows_up_to_the_checkpoint(tmp_path):
    f = tmp_path / "train" / "return.csv"
    f.parent.mkdir()
    f.write_text("20,1.5\n40,2.5\n60,3.5\n80,4")
    truncate_csv(tmp_path, 40)
    assert f.read_text() == "20,1.5\n40,2.5\n"
    truncate_csv(tmp_path, -1)  # a fresh start keeps none
    assert f.read_text() == ""
