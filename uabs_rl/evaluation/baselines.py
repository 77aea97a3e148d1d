"""Baselines beyond the paper (SPEC §9), acting through the same masked selector.

Each heuristic writes Q-like scores into ``("agents", "action_value")``; the masking
mode's :class:`~uabs_rl.safety.modules.MaskedActionSelector` (ε = 0) then picks the best legal
action, so baselines obey exactly the masks the learned policy obeys.

* ``random``: a uniformly random legal action (the selector with ε = 1).
* ``greedy``: the move that maximises the priority the UABS would cover at the next
  step, given the vehicles' current positions and priorities.
* ``oracle``: the same with the vehicles' true next positions: an optimistic reference
  no deployable policy can see.
* the coverage bound min(1, M·B·π·r_b² / (W·H)) is :func:`uabs_rl.env.channel.coverage_bound`.

Beyond these (:mod:`uabs_rl.evaluation.planner`): the ``kmeans`` and ``junctions`` heuristics,
the ``planner``, a receding-horizon plan over the vehicles' true future positions (the
clairvoyant ceiling), and ``mpc``, the same plan over the positions a predictor of
:mod:`uabs_rl.evaluation.predict` gives from the present and the past only (constant
velocity by default): a deployable policy.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.envs import TransformedEnv

from uabs_rl.env.service import move_scores
from uabs_rl.env.uabs_env import POSITION, UABSEnv
from uabs_rl.safety.modules import MaskedActionSelector
from uabs_rl.safety.rules import ACTION_VALUE

BASELINES = ("random", "greedy", "oracle")
HEURISTICS = ("kmeans", "junctions")  # classic heuristics (uabs_rl.evaluation.planner)
PLANNER = "planner"  # the receding-horizon planning reference (uabs_rl.evaluation.planner)
MPC = "mpc"  # the same planner fed by a predictor (uabs_rl.evaluation.predict): deployable


def passes_text(rounds: int) -> str:
    """``1 round``, ``3 rounds``: a search's passes over the fleet, in words."""
    return f"{rounds} round{'s' * (rounds != 1)}"


def policy_label(name: str, horizon: int | None = None, predictor: str | None = None,
                 sees: str | float = "all", coordinated: bool = True,
                 beam: int | None = None, rounds: int | None = None) -> str:
    """A baseline's name in the benchmarks' tables and per-window files, by which they
    are matched across runs: ``greedy``, ``mpc H=5 (cv)`` (with ``, sees 80 m`` where it
    sees only that far, ``, uncoordinated`` where each UABS plans alone, ``, beam 4``
    where its search keeps another number of paths than planner.BEAM, ``, 1 round``
    where it makes another number of passes over the fleet than planner.ROUNDS) or
    ``planner H=5 (clairvoyant)`` (the planner over the true future)."""
    from uabs_rl.evaluation.planner import BEAM, ROUNDS

    alone = "" if coordinated else ", uncoordinated"
    alone += "" if beam in (None, BEAM) else f", beam {beam}"
    if coordinated and rounds not in (None, ROUNDS):  # alone: one pass whatever it is set to
        alone += f", {passes_text(rounds)}"
    if name == MPC:
        seen = "" if sees == "all" else f", sees {float(sees):g} m"
        return f"mpc H={horizon} ({predictor}{seen}{alone})"
    if name == PLANNER:
        return f"planner H={horizon} (clairvoyant{alone})"
    return name


class CoverageScore(TensorDictModuleBase):
    """Scores each move by the priority under the UABS's footprints after it, with a
    tiny seeded jitter that breaks ties at random (no drift towards action 0)."""

    def __init__(self, env: UABSEnv, lookahead: int, generator: torch.Generator):
        super().__init__()
        self.env, self.lookahead, self.generator = env, lookahead, generator
        self.in_keys, self.out_keys = [POSITION], [ACTION_VALUE]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        env, p = self.env, self.env.params
        veh, present = env.vehicles(self.lookahead)  # [E, 2, V], [E, V]
        cand = td.get(POSITION)[:, :, None, :] + env.math.moves  # [E, M, 4, 2]
        score = move_scores(cand, veh, present, env.priority, p.r_b, p.n_beams)
        jitter = torch.rand(score.shape, generator=self.generator, device=score.device)
        td.set(ACTION_VALUE, score + 1e-3 * jitter)
        return td


def baseline_policy(name: str, env: TransformedEnv, selector: MaskedActionSelector,
                    seed: int = 0, horizon: int = 1,
                    sites: torch.Tensor | None = None,
                    predictor=None, coordinated: bool = True,
                    beam: int | None = None, rounds: int | None = None
                    ) -> TensorDictModuleBase:
    """The baseline ``name`` (one of BASELINES, HEURISTICS, PLANNER or MPC) as a policy
    for ``env`` (a transformed UABS env). ``horizon``: the planner's and the mpc's;
    ``sites [M, 2]``: the junctions heuristic's sites
    (:func:`uabs_rl.evaluation.planner.junction_sites`); ``predictor``: the mpc's
    (:mod:`uabs_rl.evaluation.predict`, default constant velocity seeing every vehicle);
    ``coordinated=False``: the planner's and the mpc's UABS plan alone; ``beam``: the
    paths their beam search keeps per first move, ``rounds`` its passes over the fleet
    (PlannerScore; default planner.BEAM and planner.ROUNDS)."""
    from uabs_rl.evaluation.planner import BEAM, ROUNDS, ClusterScore, PlannerScore, SiteScore
    from uabs_rl.evaluation.predict import ConstantVelocity

    names = (*BASELINES, *HEURISTICS, PLANNER, MPC)
    if name not in names:
        raise ValueError(f"unknown baseline {name!r}: choose from {names}")
    if name == "junctions" and sites is None:
        raise ValueError("the junctions baseline needs its sites (planner.junction_sites)")
    gen = torch.Generator(device=env.base_env.device)
    gen.manual_seed(seed)
    if name == "random":
        selector.eps.fill_(1.0)
        selector.generator = gen
        return selector
    base = env.base_env
    beam = BEAM if beam is None else beam
    rounds = ROUNDS if rounds is None else rounds
    if name == PLANNER:
        score = PlannerScore(base, horizon, gen, coordinated=coordinated, beam=beam,
                             rounds=rounds)
    elif name == MPC:
        score = PlannerScore(base, horizon, gen, coordinated=coordinated, beam=beam,
                             rounds=rounds,
                             predictor=predictor if predictor is not None else ConstantVelocity())
    elif name == "kmeans":
        score = ClusterScore(base, gen)
    elif name == "junctions":
        score = SiteScore(base, gen, sites)
    else:
        score = CoverageScore(base, lookahead=1 if name == "oracle" else 0, generator=gen)
    return TensorDictSequential(score, selector)
