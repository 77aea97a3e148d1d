"""The deployable planner (``mpc``): the planner's search fed by a predictor. With a
predictor that returns the true future it is the clairvoyant planner action for action
(and at H = 1 the oracle); the constant-velocity predictor never reads a position after
step t; its error k steps ahead by hand; the mpc flies only legal moves."""

from __future__ import annotations

import csv
import json
import math
import re

import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModuleBase, TensorDictSequential

from tests.test_planner import eval_env as planner_env
from tests.test_train import smoke
from uabs_rl.cli.evaluate import main as eval_main
from uabs_rl.env.params import EnvParams
from uabs_rl.env.service import move_scores
from uabs_rl.env.uabs_env import ACTION, BEAM_PRIORITY, MASK, POSITION, UABSEnv
from uabs_rl.evaluation.baselines import MPC, baseline_policy
from uabs_rl.evaluation.evaluator import Evaluator
from uabs_rl.evaluation.planner import (
    PlannerScore,
    footprint,
    footprint_path,
    lattice_index,
    lattice_offsets,
    on_lattice,
)
from uabs_rl.evaluation.predict import (
    ConstantVelocity,
    Predictor,
    TrueFuture,
    Within,
    make_predictor,
    parse_sees,
    prediction_error,
    schedule,
)
from uabs_rl.report.build import build_report
from uabs_rl.safety.make import make_env, make_selector
from uabs_rl.safety.rules import ACTION_VALUE, rank_order
from uabs_rl.traces.cache import TraceSet
from uabs_rl.training.resume import run


def eval_env(trace_cache, *overrides: str, windows: int = 2):
    return planner_env(trace_cache, *overrides, windows=windows)


def rollout(cfg, env, name: str, horizon: int = 1, predictor: Predictor | None = None):
    policy = baseline_policy(name, env, make_selector(env), seed=0, horizon=horizon,
                             predictor=predictor)
    return Evaluator(env, cfg.train.eval_seed).evaluate(policy)


class Replay(Predictor):
    """The true future read straight from the traces' rows (not through env.vehicles):
    a predictor that happens to be right."""

    name = "replay"

    def __call__(self, env: UABSEnv, horizon: int) -> dict[str, torch.Tensor]:
        st, steps = env.state, env.veh_pos.shape[1]
        rows = [(st["start"] + st["t"] + k).clamp_max(steps - 1) for k in range(1, horizon + 1)]
        return {"veh": torch.stack([env.veh_pos[st["sim"], r] for r in rows]),
                "present": torch.stack([st["prev_present"],
                                        *(env.veh_present[st["sim"], r] for r in rows)]),
                **schedule(env, horizon)}


def poisoned(predict, env: UABSEnv, horizon: int) -> dict[str, torch.Tensor]:
    """``predict(env, horizon)`` with every trace row after each env's step t (to its
    window's end) replaced by garbage while it predicts (the env steps on the true
    traces)."""
    st, pos, present = env.state, env.veh_pos, env.veh_present
    t = int(st["t"][0])
    assert (st["t"] == t).all()  # the windows run in lock step: no window's rows are
    # another's future
    gen = torch.Generator().manual_seed(t)
    kept = []
    for sim, start in zip(st["sim"].tolist(), st["start"].tolist(), strict=True):
        sl = slice(start + t + 1, start + env.params.episode_steps + 1)
        kept.append((sim, sl, pos[sim, sl].clone(), present[sim, sl].clone()))
        n = pos[sim, sl].shape
        pos[sim, sl] = 1e4 * torch.rand(n, generator=gen) - 5e3
        present[sim, sl] = torch.rand(n[:1] + n[2:], generator=gen) < 0.5
    try:
        return predict(env, horizon)
    finally:
        for sim, sl, p, q in kept:
            pos[sim, sl], present[sim, sl] = p, q


class Poisoned(ConstantVelocity):
    """Constant velocity reading garbage after step t (:func:`poisoned`)."""

    def __call__(self, env: UABSEnv, horizon: int) -> dict[str, torch.Tensor]:
        return poisoned(super().__call__, env, horizon)


@pytest.mark.parametrize("overrides", [("masking=flat",), ("masking=rank",)])
def test_mpc_with_the_true_future_is_the_planner_action_for_action(trace_cache, overrides):
    cfg, env = eval_env(trace_cache, *overrides)
    planner_rec, planner = rollout(cfg, env, "planner", horizon=3)
    mpc_rec, mpc = rollout(cfg, env, "mpc", horizon=3, predictor=Replay())
    assert torch.equal(mpc[ACTION], planner[ACTION])
    assert mpc_rec["returns"] == planner_rec["returns"]
    # and a predictor is what makes the difference: constant velocity plans otherwise
    _, cv = rollout(cfg, env, "mpc", horizon=3)
    assert not torch.equal(cv[ACTION], planner[ACTION])


@pytest.mark.parametrize("overrides", [("masking=flat",), ("masking=rank",)])
def test_mpc_with_horizon_1_and_the_true_future_is_the_oracle(trace_cache, overrides):
    cfg, env = eval_env(trace_cache, *overrides)
    oracle_rec, oracle = rollout(cfg, env, "oracle")
    for pred in (TrueFuture(), Replay()):
        rec, mpc = rollout(cfg, env, "mpc", horizon=1, predictor=pred)
        assert torch.equal(mpc[ACTION], oracle[ACTION]), pred.name
        assert rec["returns"] == oracle_rec["returns"]


def test_constant_velocity_never_reads_after_step_t(trace_cache):
    cfg, env = eval_env(trace_cache, "masking=rank")
    rec, cv = rollout(cfg, env, "mpc", horizon=3, predictor=ConstantVelocity())
    bad_rec, bad = rollout(cfg, env, "mpc", horizon=3, predictor=Poisoned())
    assert torch.equal(bad[ACTION], cv[ACTION])
    assert bad_rec["returns"] == rec["returns"]
    # the poison is real: the clairvoyant planner given the same garbage plans otherwise

    class PoisonedTruth(Poisoned):
        def __call__(self, env, horizon):
            saved = ConstantVelocity.__call__
            try:
                ConstantVelocity.__call__ = lambda s, e, h: TrueFuture()(e, h)
                return super().__call__(env, horizon)
            finally:
                ConstantVelocity.__call__ = saved

    _, truth = rollout(cfg, env, "mpc", horizon=3, predictor=TrueFuture())
    _, fooled = rollout(cfg, env, "mpc", horizon=3, predictor=PoisonedTruth())
    assert not torch.equal(fooled[ACTION], truth[ACTION])


@pytest.mark.parametrize("overrides", [("masking=flat",), ("masking=rank",),
                                       ("masking=rank", "scenario.n_uabs=6")])
def test_mpc_flies_only_legal_moves(trace_cache, overrides):
    cfg, env = eval_env(trace_cache, *overrides)
    d_th = env.base_env.params.d_th
    h = 2 if cfg.scenario.n_uabs > 3 else 3
    preds = [ConstantVelocity()] + ([Within(ConstantVelocity(), 60.0)]
                                    if cfg.masking.mode == "rank" else [])
    for pred in preds:
        rec, td = rollout(cfg, env, "mpc", horizon=h, predictor=pred)
        assert td[MASK].gather(-1, td[ACTION][..., None]).all(), pred.name
        diag = td["next", "diagnostics"]
        assert diag["illegal_moves"].sum() == 0 and diag["collisions"].sum() == 0
        assert rec["collisions"] == 0 and rec["proximity"] == 0 and rec["fallbacks"] == 0
        assert rec["closest_approach"] >= d_th - 1e-3


def hand_traces(p: EnvParams, steps: int) -> TraceSet:
    """Vehicle 0 drives at 2 m per step, vehicle 1 accelerates (x = 10 + t² m), vehicle
    2 is absent until step 3."""
    t = torch.arange(steps, dtype=torch.float32)
    pos = torch.zeros(1, steps, 3, 2)
    pos[0, :, 0, 0], pos[0, :, 1, 0], pos[0, :, 2, 0] = 5 + 2 * t, 10 + t * t, 50.0
    pos[..., 1] = 40.0
    present = torch.ones(1, steps, 3, dtype=torch.bool)
    present[0, :3, 2] = False
    return TraceSet(pos, present, {"dt": p.dt, "split": "test"})


def test_prediction_error_by_hand(trace_cache):
    cfg = smoke(trace_cache, "masking=penalty", "scenario.n_uabs=1")
    t_steps = cfg.scenario.episode_steps
    p = EnvParams.from_config(cfg.scenario, cfg.channel)
    env = make_env(cfg.scenario, cfg.channel, cfg.masking, hand_traces(p, t_steps + 1),
                   "test", n_envs=1, n_eval_windows=1, seed=0, spec_mask=False)
    env.set_seed(0)
    env.reset()
    base = env.base_env
    # constant velocity predicts x_t + k (x_t − x_{t−1}); at t = 0 there is no past
    # (no motion). Vehicle 0: error 2k at t = 0, 0 after. Vehicle 1: the truth is
    # 10 + (t + k)², the prediction 10 + t² + k (2t − 1): error k² + k, k² at t = 0.
    # Vehicle 2 (present from step 3) stands still the step it appears, then is exact.
    for k, got in prediction_error(base, ConstantVelocity(), (1, 2, 5)).items():
        n_t = t_steps - k + 1  # t = 0 .. T − k
        errors = [2 * k, k * k] + [k * k + k] * (n_t - 1)  # vehicles 0 and 1
        errors += [0.0] * (n_t - 1)  # vehicle 0 after t = 0
        # vehicle 2: predicted present at t >= 3 only; at t = 3 it stands still, 0 m off
        errors += [0.0] * (n_t - 3)
        assert got["n"] == len(errors), k
        assert got["mean_m"] == pytest.approx(sum(errors) / len(errors), rel=1e-5), k
        assert got["rmse_m"] == pytest.approx((sum(e * e for e in errors) / len(errors)) ** 0.5,
                                              rel=1e-5)
    # the true future is never off; the step counter is put back
    assert all(e["mean_m"] == 0 for e in prediction_error(base, TrueFuture(), (1, 3)).values())
    assert int(base.state["t"][0]) == 0


def test_within_sees_only_the_vehicles_near_a_uabs_and_options(trace_cache):
    cfg, env = eval_env(trace_cache, "masking=rank", windows=2)
    env.set_seed(0)
    env.reset()
    base = env.base_env
    full = ConstantVelocity()(base, 3)
    near = Within(ConstantVelocity(), 40.0)(base, 3)
    veh, present = base.vehicles(0)
    d = (veh[:, None] - base.state["pos"][..., None]).norm(dim=2).amin(1)  # [E, V]
    assert torch.equal(near["present"][1:], full["present"][1:] & (d <= 40.0)[None])
    assert torch.equal(near["present"][0], full["present"][0])
    assert torch.equal(near["veh"], full["veh"])
    assert isinstance(make_predictor("cv", 40.0), Within)
    assert isinstance(make_predictor("true"), TrueFuture)
    assert parse_sees("all") == "all" and parse_sees("150") == 150.0
    for bad in ("-1", "far", "nan", "inf"):
        with pytest.raises(ValueError, match="--sees must be 'all' or a distance"):
            parse_sees(bad)
    with pytest.raises(ValueError, match="unknown predictor 'bus'"):
        make_predictor("bus")


@pytest.fixture(scope="module")
def smoke_run(trace_cache, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("mpc") / "run"
    run(smoke(trace_cache, "train.episodes=2", "train.trajectory_images=false"), run_dir)
    return run_dir


def test_the_beam_width_and_rounds_reach_the_search_and_name_the_policy(trace_cache):
    """``beam`` (``uabs-eval --mpc-beam``): the paths the mpc's and the planner's search
    keep per first move; ``rounds`` (``--mpc-rounds``) its passes over the fleet; each
    named in a table's label only where it is not the default (the uncoordinated search
    makes one pass whatever it is given)."""
    from uabs_rl.evaluation.baselines import policy_label
    from uabs_rl.evaluation.planner import BEAM, ROUNDS

    _, env = eval_env(trace_cache, "masking=rank")
    for name in (MPC, "planner"):
        score = baseline_policy(name, env, make_selector(env), horizon=3)[0]
        assert (score.beam, score.rounds) == (BEAM, ROUNDS) == (16, 2)
        score = baseline_policy(name, env, make_selector(env), horizon=3, beam=4, rounds=1)[0]
        assert (score.beam, score.rounds) == (4, 1)
        assert baseline_policy(name, env, make_selector(env), horizon=3, rounds=3,
                               coordinated=False)[0].rounds == 1
    assert policy_label(MPC, 5, "cv", beam=4) == "mpc H=5 (cv, beam 4)"
    assert policy_label(MPC, 5, "cv", beam=BEAM) == policy_label(MPC, 5, "cv") == "mpc H=5 (cv)"
    assert policy_label("planner", 5, beam=8) == "planner H=5 (clairvoyant, beam 8)"
    assert policy_label(MPC, 5, "cv", beam=4, rounds=1) == "mpc H=5 (cv, beam 4, 1 round)"
    assert policy_label(MPC, 5, "cv", rounds=3) == "mpc H=5 (cv, 3 rounds)"
    assert policy_label(MPC, 5, "cv", rounds=ROUNDS) == "mpc H=5 (cv)"
    assert policy_label(MPC, 5, "cv", coordinated=False, rounds=1) == \
        "mpc H=5 (cv, uncoordinated)"
    with pytest.raises(ValueError, match="the beam must keep at least one path, got 0"):
        PlannerScore(env.base_env, 3, torch.Generator(), beam=0)
    with pytest.raises(ValueError, match="at least one pass, got rounds=0"):
        PlannerScore(env.base_env, 3, torch.Generator(), rounds=0)


@pytest.mark.parametrize("h", [2, 3])
def test_one_round_is_the_first_pass_of_two(trace_cache, h):
    """``rounds=1``: each UABS searched once, in rank order, given the plans of those
    before it (the k-th given k); the default's second pass searches each again, given
    all the others' plans (checked on the first decision of a rank-masked evaluation)."""
    from uabs_rl.evaluation.predict import ConstantVelocity

    _, env = eval_env(trace_cache, "masking=rank")
    td = env.reset()
    m = env.base_env.params.n_uabs
    for rounds in (1, 2):
        score = PlannerScore(env.base_env, h, torch.Generator().manual_seed(0), rounds=rounds,
                             predictor=ConstantVelocity())
        calls = []

        def spy(pos, plan, others, *args, calls=calls, search=score.search, **kwargs):
            calls.append(others.sum(-1).tolist())  # how many plans each search is given
            return search(pos, plan, others, *args, **kwargs)

        score.search = spy
        score.scores(td)
        assert [c[0] for c in calls] == [*range(m), *[m - 1] * (m * (rounds - 1))]


def test_uabs_eval_mpc_reports_its_settings_and_compute(smoke_run, tmp_path, capsys):
    run_dir = smoke_run
    out = tmp_path / "ev"
    assert eval_main([str(run_dir), "--checkpoint", "last", "--policy", "greedy",
                      "--policy", "mpc", "--mpc-horizon", "3", "--sees", "150",
                      "--mpc-beam", "4", "--mpc-rounds", "1", "--windows", "2",
                      "--out", str(out)]) == 0
    text = capsys.readouterr().out
    res = json.loads((out / "eval.json").read_text())
    mpc = res["policies"]["mpc"]
    assert (mpc["horizon"], mpc["beam"], mpc["rounds"], mpc["predictor"], mpc["sees"]) == (
        3, 4, 1, "cv", 150.0)
    assert mpc["ms_per_decision"] > 0 and res["policies"]["greedy"]["ms_per_decision"] > 0
    assert "mpc: horizon 3, beam 4, 1 round, predictor cv, sees the vehicles within 150 m; " \
        in text
    assert "compute per decision (the whole fleet, ms per step" in text
    # the whole evaluation's time and this process's peak memory, as a number of MiB
    # (and the thread governor's line where a busy machine made it use fewer threads)
    assert re.search(r"^evaluated 2 policies in \d+\.\d s, peak memory [1-9]\d* MiB"
                     r"(; torch threads: .*)?$", text, re.M), text
    with pytest.raises(SystemExit) as e:
        eval_main([str(run_dir), "--policy", "mpc", "--sees", "near"])
    assert e.value.code == 2
    assert "--sees must be 'all' or a distance >= 0 in metres, got 'near'" in \
        capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        eval_main([str(run_dir), "--policy", "mpc", "--mpc-beam", "0"])
    assert e.value.code == 2 and "--mpc-beam must be >= 1, got 0" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        eval_main([str(run_dir), "--policy", "mpc", "--mpc-rounds", "0"])
    assert e.value.code == 2 and "--mpc-rounds must be >= 1, got 0" in capsys.readouterr().err


def test_uabs_eval_looks_at_the_cpus_every_step_unless_omp_fixes_its_threads(
        smoke_run, tmp_path, capsys, monkeypatch):
    """uabs-eval hands the thread governor (fewer torch threads while other processes keep
    the CPUs busy) to the evaluator, which calls it after every step of every rollout;
    OMP_NUM_THREADS fixes the count; a change is named in the last line."""
    from uabs_rl.cli import evaluate as cli

    made = []

    class Governor:
        def __init__(self, most, fixed):
            self.most, self.n, self.fixed, self.calls, self.changes = most, most, fixed, 0, 1
            self.active = not fixed
            made.append(self)

        def check(self):
            self.calls += 1
            return self.n

    monkeypatch.setattr(cli, "ThreadGovernor", Governor)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    args = [str(smoke_run), "--checkpoint", "last", "--policy", "greedy", "--policy",
            "oracle", "--windows", "2"]
    assert eval_main([*args, "--out", str(tmp_path / "a")]) == 0
    text = capsys.readouterr().out
    (gov,) = made
    episode = int(re.search(r"2 windows of (\d+) steps", text)[1])
    # two rollouts, a look after every step but the last (TorchRL's rollout callback)
    assert not gov.fixed and gov.calls == 2 * (episode - 1)
    assert "fewer while other processes kept the CPUs busy (1 change(s))" in text
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert eval_main([*args, "--out", str(tmp_path / "b")]) == 0
    assert made[1].fixed and made[1].calls == 0


def test_uabs_report_mpc_sits_beside_greedy_and_the_oracle(smoke_run, tmp_path):
    out = tmp_path / "report"
    res = build_report(smoke_run, out, mpc=2)
    mode = next(iter(res["grouping"].groups.values()))[0].mode
    names = ("random", "greedy", "oracle", "mpc")
    assert list(res["baselines"]) == [f"{b} ({mode} masks)" for b in names]
    with open(out / "baselines.csv") as f:
        assert [r["policy"].split()[0] for r in csv.DictReader(f)] == list(names)
    lvb = res["learned_vs_baselines"]
    assert {r["baseline"] for r in lvb} == set(names)
    row = next(r for r in lvb if r["baseline"] == "mpc" and r["metric"] == "served_fraction")
    mpc = res["baselines"][f"mpc ({mode} masks)"]
    assert mpc["horizon"] == 2 and mpc["predictor"] == "cv"
    assert row["baseline_value"] == pytest.approx(float(np.mean(mpc["served_fractions"])))
    assert (out / "fig4_pg.png").stat().st_size > 10_000
    assert (mpc["beam"], mpc["rounds"]) == (16, 2)
    # --mpc-beam, --mpc-rounds: that mpc
    narrow = build_report(smoke_run, tmp_path / "narrow", mpc=2, mpc_beam=1, mpc_rounds=1)
    mpc = narrow["baselines"][f"mpc ({mode} masks)"]
    assert (mpc["horizon"], mpc["beam"], mpc["rounds"]) == (2, 1, 1)
    with open(tmp_path / "narrow" / "baselines.csv") as f:  # the search beside its figures
        rows = {r["policy"].split()[0]: r for r in csv.DictReader(f)}
    assert [rows["mpc"][k] for k in ("horizon", "beam", "rounds", "predictor")] == \
        ["2", "1", "1", "cv"]
    assert [rows["greedy"][k] for k in ("horizon", "beam", "rounds")] == ["", "", ""]
    # the learned-vs-baselines page names the mpc with its search, in its intro and rows
    md = (tmp_path / "narrow" / "learned_vs_baselines.md").read_text()
    assert ("evaluated with random, greedy and oracle (and the deployable mpc H=2 (cv, "
            "beam 1, 1 round), constant-velocity prediction) on every test window") in md
    assert "| mpc H=2 (cv, beam 1, 1 round) | " in md
    # without --mpc nothing of it
    plain = build_report(smoke_run, tmp_path / "plain")
    assert list(plain["baselines"]) == [f"{b} ({mode} masks)" for b in names[:3]]
    md = (tmp_path / "plain" / "learned_vs_baselines.md").read_text()
    assert "evaluated with random, greedy and oracle on every test window" in md


def test_uabs_report_passes_the_mpcs_search_on(smoke_run, tmp_path, monkeypatch, capsys):
    """``uabs-report DIR --mpc 2 --mpc-beam 1 --mpc-rounds 1``: build_report is asked for
    that mpc (a spy that stops there: nothing is written)."""
    import uabs_rl.cli.report as cli
    from uabs_rl.runs.sweep import ReportError

    asked = {}

    def spy(*args, **kwargs):
        asked.update(kwargs)
        raise ReportError("stopped by the test")

    monkeypatch.setattr(cli, "build_report", spy)
    assert cli.main([str(smoke_run), "--mpc", "2", "--mpc-beam", "1", "--mpc-rounds", "1",
                     "--out", str(tmp_path / "r")]) == 2
    assert (asked["mpc"], asked["mpc_beam"], asked["mpc_rounds"]) == (2, 1, 1)
    assert "stopped by the test" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("module, args, says", [
    ("evaluate", ["RUN", "--policy", "mpc", "--mpc-horizon", "0"], "--mpc-horizon must be >= 1"),
    ("report", ["DIR", "--mpc", "0"], "--mpc H needs H >= 1"),
    ("report", ["DIR", "--mpc", "5", "--no-baselines"], "--mpc H needs H >= 1"),
    ("report", ["DIR", "--mpc-beam", "4"], "--mpc-beam sets the search of --mpc H: give "
                                            "--mpc H too"),
    ("report", ["DIR", "--mpc", "5", "--mpc-rounds", "0"], "--mpc-rounds must be >= 1, got 0"),
    # an option of a policy not evaluated (before: ignored without a word)
    ("evaluate", ["RUN", "--mpc-beam", "4"], "--mpc-beam sets the mpc / hybrid / leaf policy, "
                                             "which this command does not evaluate: add "
                                             "--policy mpc, or leave --mpc-beam out"),
    ("evaluate", ["RUN", "--policy", "all", "--sees", "150"], "--sees sets the mpc"),
    ("evaluate", ["RUN", "--policy", "mpc", "--hybrid-weight", "2"],
     "--hybrid-weight sets the hybrid / leaf policy"),
    ("evaluate", ["RUN", "--policy", "mpc", "--horizon", "3"], "--horizon sets the planner")])
def test_mpc_option_errors_are_one_line(module, args, says, capsys):
    import importlib

    main = importlib.import_module(f"uabs_rl.cli.{module}").main
    with pytest.raises(SystemExit) as e:
        main(args)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0]


# ------------------------------------------------ the search's footprint table, checked
def reference_next_priority(p, served, present, prev_present, start):
    """next_priority as it was first written (the reference of the test below)."""
    lead = (slice(None),) + (None,) * (p.dim() - 2)
    present, prev_present = present[lead], prev_present[lead]
    reset = start[lead + (None,)] | (present & ~prev_present)
    return (p + served.float()).masked_fill(reset, 1.0).masked_fill(~present, 0.0)


class ReferencePlanner(PlannerScore):
    """The planner's search as it was first written: every candidate of every search
    tested against every vehicle (no footprint table), each candidate's priorities
    copied from its beam's. The fast search must give its scores bit for bit."""

    @torch.no_grad()
    def future(self, td, w=None, first=None):  # first: not used, scored in every search
        p = self.env.params
        pos, allowed = td.get(POSITION), td.get(MASK)
        e, m = pos.shape[:2]
        rows = torch.arange(e, device=pos.device)
        w = self.world() if w is None else w
        order = rank_order(td.get(BEAM_PRIORITY))
        plan = pos[:, :, None, :].expand(e, m, self.horizon, 2).clone()
        cover = torch.zeros(e, m, self.horizon, w["veh"].shape[-1], dtype=torch.bool)
        planned = torch.zeros(e, m, dtype=torch.bool)
        out = torch.zeros(e, m, 4)
        for r in range(self.rounds * m):
            u = order[:, r % m]
            others = planned.clone()
            others[rows, u] = False
            value, path = self.search(pos[rows, u], plan, cover, others, w)
            out[rows, u] = value
            total = value + move_scores(pos[rows, u][:, None, None, :] + self.env.math.moves,
                                        w["veh"][0], w["present"][1], self.env.priority,
                                        p.r_b, p.n_beams)[:, 0]
            best = total.masked_fill(~allowed[rows, u], -math.inf).argmax(-1)
            plan[rows, u] = path[rows, best]
            cover[rows, u] = footprint_path(plan[rows, u], w["veh"], p.r_b, p.n_beams)
            planned[rows, u] = True
        return out

    def search(self, pos, plan, cover, others, w):
        p, geo, h = self.env.params, self.env.math.geometry, self.horizon
        e = pos.shape[0]
        oth_cover = (cover & others[:, :, None, None]).any(1)
        first = pos[:, None, :] + self.env.math.moves
        own = footprint(first, w["veh"][0], p.r_b, p.n_beams)
        prio = reference_next_priority(self.env.priority[:, None, :],
                                       own | oth_cover[:, None, 0], w["present"][1],
                                       w["present"][0], w["start"][0])
        beams = {"pos": first[:, :, None, :], "prio": prio[:, :, None, :],
                 "value": torch.zeros(e, 4, 1),
                 "path": first[:, :, None, None, :].expand(e, 4, 1, h, 2).clone()}
        for k in range(1, h):
            beams = self.expand(beams, k, plan, others, oth_cover, w, geo)
        value = beams["value"].amax(-1)
        path = beams["path"][:, :, 0]
        dead = torch.isinf(value)
        floor = value.masked_fill(dead, math.inf).amin(-1, keepdim=True) - 1.0
        value = torch.where(dead, torch.where(dead.all(-1, keepdim=True), 0.0, floor), value)
        return value, path

    def expand(self, beams, k, plan, others, oth_cover, w, geo):
        p = self.env.params
        e, a, b = beams["value"].shape
        cand = (beams["pos"][:, :, :, None, :] + self.env.math.moves).reshape(e, a, b * 4, 2)
        ok = geo.boundary_mask(beams["pos"]).reshape(e, a, b * 4) & torch.isfinite(
            beams["value"]).repeat_interleave(4, -1)
        near = (cand[:, :, :, None, :] - plan[:, None, None, :, k, :]).norm(dim=-1)
        ok &= ~((near < p.d_th) & others[:, None, None, :]).any(-1)
        veh, present = w["veh"][k], w["present"][k + 1]
        inside = footprint(cand, veh, p.r_b, p.n_beams)
        prio = beams["prio"].repeat_interleave(4, 2)
        weight = torch.where(present & ~oth_cover[:, k], 1.0, 0.0)[:, None, None, :]
        gain = (inside * prio.clamp_min(1.0) * weight).sum(-1) * w["live"][k][:, None, None]
        value = (beams["value"].repeat_interleave(4, -1) + gain).masked_fill(~ok, -math.inf)
        value, idx = value.sort(-1, descending=True)
        cand = cand.gather(2, idx[..., None].expand(-1, -1, -1, 2))
        key = torch.round(cand * 8.0).long()
        key = key[..., 0] * 1_000_003 + key[..., 1]
        same = key[..., :, None] == key[..., None, :]
        value = value.masked_fill(torch.tril(same, diagonal=-1).any(-1), -math.inf)
        value, top = value.topk(min(self.beam, value.shape[-1]), dim=-1)
        src = idx.gather(-1, top)
        new_pos = cand.gather(2, top[..., None].expand(-1, -1, -1, 2))
        served = inside.gather(2, src[..., None].expand(-1, -1, -1, inside.shape[-1]))
        served = served | oth_cover[:, None, None, k]
        prio = reference_next_priority(prio.gather(2, src[..., None].expand_as(served)),
                                       served, present, w["present"][k], w["start"][k])
        path = beams["path"].repeat_interleave(4, 2).gather(
            2, src[..., None, None].expand(-1, -1, -1, *beams["path"].shape[-2:])).clone()
        path[:, :, :, k:] = new_pos[:, :, :, None, :]
        return {"pos": new_pos, "prio": prio, "value": value, "path": path}


class Checked(TensorDictModuleBase):
    """The scores of ``fast`` at every step, checked equal (``torch.equal``) to those of
    ``reference`` (its own generator, seeded alike) on the same input."""

    def __init__(self, fast: PlannerScore, reference: PlannerScore):
        super().__init__()
        self.fast, self.reference, self.steps = fast, reference, 0
        self.in_keys, self.out_keys = fast.in_keys, fast.out_keys

    def forward(self, td):
        want = self.reference(td.clone()).get(ACTION_VALUE)
        td = self.fast(td)
        assert torch.equal(td.get(ACTION_VALUE), want), f"step {self.steps}"
        self.steps += 1
        return td


def spy_on_the_cut(monkeypatch) -> list[tuple[int, int]]:
    """Records each call of the planner's cut to the vehicles in reach
    (``planner.near_sets``) as ``(K, V)``: the vehicles kept per UABS (V where nothing is
    cut) and the vehicles there are."""
    from uabs_rl.evaluation import planner

    sizes, real = [], planner.near_sets

    def spy(keep, *args):
        out = real(keep, *args)
        sizes.append((keep.shape[-1] if out is None else out[0].shape[-1], keep.shape[-1]))
        return out

    monkeypatch.setattr(planner, "near_sets", spy)
    return sizes


@pytest.mark.parametrize("overrides, exact", [
    (("masking=rank",), True), (("masking=flat", "scenario.n_uabs=6"), True),
    (("masking=rank", "scenario.lattice=false"), False)])
def test_the_footprint_table_gives_the_first_searchs_scores_bit_for_bit(trace_cache,
                                                                          monkeypatch,
                                                                          overrides, exact):
    """The fast search (tables of footprint tests where the lattice is exact, each UABS
    over the vehicles it can reach: a few of the traffic here, the cut made at most
    steps) gives the scores of the search over every vehicle, tested one by one."""
    sizes = spy_on_the_cut(monkeypatch)
    cfg, env = eval_env(trace_cache, *overrides)
    base, h = env.base_env, 4
    env.set_seed(0)
    step = float(base.math.moves.abs().amax())
    # the lattice's points are exact floats (a table is made); off it, each candidate
    # is tested as before
    assert on_lattice(env.reset()[POSITION], step, h) is exact
    for pred in (ConstantVelocity(), TrueFuture()):
        gens = [torch.Generator().manual_seed(0) for _ in range(2)]
        checked = Checked(PlannerScore(base, h, gens[0], predictor=pred),
                          ReferencePlanner(base, h, gens[1], predictor=pred))
        rec, td = Evaluator(env, cfg.train.eval_seed).evaluate(
            TensorDictSequential(checked, make_selector(env)))
        assert checked.steps == cfg.scenario.episode_steps > 0
        assert rec["collisions"] == 0
    cut = [k < v for k, v in sizes]
    assert len(cut) == 2 * cfg.scenario.episode_steps and sum(cut) > len(cut) // 2


def test_the_cut_to_the_vehicles_in_reach_can_be_turned_off(trace_cache, monkeypatch):
    """``cut = False``: every UABS searches every vehicle (no sets made), the same moves."""
    cfg, env = eval_env(trace_cache, "masking=rank")
    actions = []
    for cut in (True, False):
        calls = spy_on_the_cut(monkeypatch)
        score = PlannerScore(env.base_env, 3, torch.Generator().manual_seed(0),
                             predictor=ConstantVelocity())
        score.cut = cut
        _, td = Evaluator(env, cfg.train.eval_seed).evaluate(
            TensorDictSequential(score, make_selector(env)))
        actions.append(td.get(ACTION))
        assert bool(calls) is cut
        monkeypatch.undo()
    assert torch.equal(*actions)


def test_a_table_over_its_budget_is_not_built_and_the_scores_stay(trace_cache, monkeypatch):
    """A footprint table larger than planner.TABLE_BYTES (a long horizon over a district)
    is not built: each candidate is tested, with the same scores as the reference."""
    from uabs_rl.evaluation import planner

    assert planner.table_bytes(22, 25, 5, 700) == 22 * 25 * 700 * (4 + 9 + 16 + 25 + 36)
    assert planner.table_bytes(22, 25, 30, 700) > planner.TABLE_BYTES  # Bologna at H = 30
    monkeypatch.setattr(planner, "TABLE_BYTES", 0)

    def refused(*args, **kwargs):
        raise AssertionError("a table over its budget was built")

    monkeypatch.setattr(planner, "footprint_table", refused)
    cfg, env = eval_env(trace_cache, "masking=rank")
    gens = [torch.Generator().manual_seed(0) for _ in range(2)]
    checked = Checked(PlannerScore(env.base_env, 4, gens[0], predictor=ConstantVelocity()),
                      ReferencePlanner(env.base_env, 4, gens[1], predictor=ConstantVelocity()))
    Evaluator(env, cfg.train.eval_seed).evaluate(TensorDictSequential(checked,
                                                                      make_selector(env)))
    assert checked.steps == cfg.scenario.episode_steps


def test_lattice_offsets_index_and_exactness_by_hand():
    for n in (1, 2, 5):
        off = lattice_offsets(n, torch.device("cpu"))
        assert off.shape == ((n + 1) ** 2, 2)
        # every offset n moves can reach, once: |i| + |j| <= n of n's parity
        assert off.abs().sum(-1).le(n).all() and (off.sum(-1) - n).remainder(2).eq(0).all()
        assert len({tuple(o) for o in off.tolist()}) == (n + 1) ** 2
        assert torch.equal(lattice_index(off, n), torch.arange((n + 1) ** 2))
    assert lattice_offsets(1, torch.device("cpu")).tolist() == [[-1, 0], [0, -1], [0, 1], [1, 0]]
    assert on_lattice(torch.tensor([[9.0, 1819.5]]), 20.0, 5)
    assert not on_lattice(torch.tensor([[9.1, 1819.5]]), 20.0, 5)  # 9.1 + 20 rounds
    assert not on_lattice(torch.tensor([[0.0, 1e8]]), 20.0, 1)  # float32 steps of 8 there
