"""Predictors of the vehicles' next positions for the receding-horizon planner.

A predictor turns what the controller knows at step t into the world the planner of
:mod:`uabs_rl.evaluation.planner` searches over: ``predictor(env, horizon)`` returns

* ``veh [H, E, 2, V]``: the vehicles' positions at steps t+1..t+H,
* ``present [H+1, E, V]``: their presence (index 0: now, the env's ``prev_present``),
* ``start [H, E]``: whether step t+k starts a service window, and ``live [H, E]``:
  whether it is still in the episode (the schedule, not the traffic: always known).

* :class:`TrueFuture`: the vehicles' true positions (the clairvoyant planner, the
  ceiling: ``uabs-eval --policy planner``).
* :class:`ConstantVelocity`: each vehicle present now and at t − 1 moves on by its last
  move, x_t + k (x_t − x_{t−1}) (what V2X awareness messages give a controller); one
  seen first now stands still; presence stays as now (no arrival is foreseen). It reads
  the traces at steps t and t − 1 of the window only (tested: a future replaced by
  garbage gives the same actions).
* :class:`~uabs_rl.evaluation.roads.RoadAware`: each moving vehicle along its lane of the
  scenario's SUMO network and the straightest successors after it, at its current speed
  (the map and the same two positions; no route).
* :class:`~uabs_rl.evaluation.motion.LearnedMotion`: each vehicle moved as a small network
  fit on the scenario's training traces predicts from its last moves (slowing, turning,
  speeding up; no route, no map).
* :class:`Within`: any predictor restricted to what the UABS see, the vehicles within
  ``radius`` metres (planar) of some UABS at step t; the others are absent to the plan.

The deployable planner is ``uabs-eval --policy mpc --predictor cv`` (or ``road``,
``learned``;
optionally ``--sees R``). :func:`prediction_error` measures a predictor's error k steps ahead.
"""

from __future__ import annotations

import math

import torch

from uabs_rl.env.service import vehicles_at
from uabs_rl.env.uabs_env import UABSEnv

# --predictor: constant velocity (default), along the roads (the scenario's SUMO network,
# uabs_rl.evaluation.roads), the true future, learned from the training traces' moves
# (uabs_rl.evaluation.motion)
PREDICTORS = ("cv", "road", "true", "learned")
REACH_M = 400.0  # how far along the roads the road-aware predictor looks (H · speed)


def schedule(env: UABSEnv, horizon: int) -> dict[str, torch.Tensor]:
    """``start [H, E]`` and ``live [H, E]`` of steps t+1..t+H (service windows and the
    episode's end: known in advance, whatever the traffic does)."""
    t = env.state["t"]
    k = torch.arange(1, horizon + 1, device=t.device)[:, None] + t  # [H, E]
    return {"start": k % env.params.window_steps == 0, "live": k <= env.params.episode_steps}


def observed(env: UABSEnv, back: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions ``[E, 2, V]`` and presence ``[E, V]`` ``back`` steps before the current
    one, never before the window's first step (the past a controller has heard)."""
    st = dict(env.state)
    st["t"] = (st["t"] - back).clamp_min(0)
    return vehicles_at(st, env.veh_pos, env.veh_present)


class Predictor:
    """``predictor(env, horizon)``: the world the planner searches (module docstring)."""

    name = "predictor"

    def __call__(self, env: UABSEnv, horizon: int) -> dict[str, torch.Tensor]:
        raise NotImplementedError


class TrueFuture(Predictor):
    """The vehicles' true positions and presence ahead (it knows the future)."""

    name = "true"

    def __call__(self, env: UABSEnv, horizon: int) -> dict[str, torch.Tensor]:
        ahead = [env.vehicles(k) for k in range(1, horizon + 1)]
        return {"veh": torch.stack([v for v, _ in ahead]),
                "present": torch.stack([env.state["prev_present"], *(q for _, q in ahead)]),
                **schedule(env, horizon)}


class ConstantVelocity(Predictor):
    """Every vehicle present now and one step before moves on by its last move; the
    others stand where they are; those present now stay present."""

    name = "cv"

    def __call__(self, env: UABSEnv, horizon: int) -> dict[str, torch.Tensor]:
        now, present = observed(env, 0)
        prev, prev_present = observed(env, 1)  # at the window's first step: now (no motion)
        v = torch.where((present & prev_present)[:, None, :], now - prev, 0.0)  # [E, 2, V]
        k = torch.arange(1, horizon + 1, device=now.device, dtype=now.dtype)
        veh = now[None] + k[:, None, None, None] * v[None]
        return {"veh": veh,
                "present": torch.stack([env.state["prev_present"],
                                        *([present] * horizon)]),
                **schedule(env, horizon)}


class Within(Predictor):
    """``inner``'s world with only the vehicles within ``radius`` metres (planar) of
    some UABS at step t present (the controller sees no others)."""

    def __init__(self, inner: Predictor, radius: float):
        self.inner, self.radius = inner, float(radius)
        self.name = f"{inner.name}, sees {radius:g} m"

    def __call__(self, env: UABSEnv, horizon: int) -> dict[str, torch.Tensor]:
        w = self.inner(env, horizon)
        now, present = observed(env, 0)
        d = (now[:, None, :, :] - env.state["pos"][:, :, :, None]).norm(dim=2)  # [E, M, V]
        seen = present & (d <= self.radius).any(1)  # [E, V]
        w["present"] = torch.cat([w["present"][:1], w["present"][1:] & seen[None]])
        return w


def make_predictor(name: str = "cv", sees: str | float = "all", scenario=None,
                   device: torch.device | str = "cpu", traces=None) -> Predictor:
    """The predictor ``name`` (one of PREDICTORS) seeing every vehicle (``sees="all"``)
    or those within ``sees`` metres of some UABS. ``road`` reads ``scenario``'s SUMO
    network (:mod:`uabs_rl.evaluation.roads`), onto ``device``; ``learned`` its model
    fit on ``scenario``'s training traces (``traces``: their settings;
    :func:`uabs_rl.evaluation.motion.learned_motion`)."""
    if name == "cv":
        pred: Predictor = ConstantVelocity()
    elif name == "true":
        pred = TrueFuture()
    elif name == "road":
        from uabs_rl.evaluation.roads import RoadAware, load_network

        if scenario is None:
            raise ValueError("the road-aware predictor needs the scenario (its network)")
        pred = RoadAware(load_network(scenario, REACH_M, device))
    elif name == "learned":
        from uabs_rl.evaluation.motion import learned_motion

        if scenario is None:
            raise ValueError("the learned predictor needs the scenario (its training traces)")
        pred = learned_motion(scenario, traces, device)
    else:
        raise ValueError(f"unknown predictor {name!r}: choose from {PREDICTORS}")
    if str(sees) == "all":
        return pred
    radius = float(sees)
    if not math.isfinite(radius) or radius < 0:
        raise ValueError(f"sees must be 'all' or a distance >= 0 in metres, got {sees!r}")
    return Within(pred, radius)


def parse_sees(text: str) -> str | float:
    """``--sees``: ``all`` or a radius in metres (>= 0)."""
    if text == "all":
        return "all"
    try:
        radius = float(text)
    except ValueError:
        radius = float("nan")
    if not math.isfinite(radius) or radius < 0:
        raise ValueError(f"--sees must be 'all' or a distance >= 0 in metres, got {text!r}")
    return radius


@torch.no_grad()
def prediction_error(env: UABSEnv, predictor: Predictor,
                     ks: tuple[int, ...] = (1, 2, 5)) -> dict[int, dict[str, float]]:
    """The predictor's error ``k`` steps ahead over the windows of an eval-mode ``env``
    (just reset): at every step t with t + k in the window, the distance in metres
    between each vehicle's predicted and true position at t + k, over the vehicles
    present at t + k and predicted present. ``{k: {mean_m, rmse_m, n}}``. The env's
    step counter is moved and put back; nothing is stepped."""
    h, steps = max(ks), env.params.episode_steps
    saved = env.state["t"].clone()
    sums = {k: [0.0, 0.0, 0] for k in ks}
    try:
        for t in range(steps):
            env.state["t"] = torch.full_like(saved, t)
            # present at t (the planner's "now"): as the env's prev_present after step t
            keep_prev = env.state["prev_present"]
            env.state["prev_present"] = observed(env, 0)[1]
            w = predictor(env, h)
            env.state["prev_present"] = keep_prev
            for k in ks:
                if t + k > steps:
                    continue
                true, there = env.vehicles(k)
                ok = there & w["present"][k]
                d = (w["veh"][k - 1] - true).norm(dim=1)[ok]
                sums[k][0] += float(d.sum())
                sums[k][1] += float((d * d).sum())
                sums[k][2] += int(d.numel())
    finally:
        env.state["t"] = saved
    return {k: {"mean_m": s / n if n else float("nan"),
                "rmse_m": math.sqrt(s2 / n) if n else float("nan"), "n": n}
            for k, (s, s2, n) in sums.items()}
