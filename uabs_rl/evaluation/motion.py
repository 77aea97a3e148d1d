"""A learned motion predictor for the mpc: ``uabs-eval --policy mpc --predictor learned``.

Constant velocity extrapolates each vehicle's last move; the road-aware predictor moves
it along its lane. Both miss what the vehicles' recent moves show of what they are about
to do: slowing for a junction or a red light, a turn under way, speeding up again.
:class:`MotionModel` is a small network that reads each vehicle's last
:data:`HISTORY` moves (metres per step, oldest first) and predicts its displacement
from now 1 … :data:`AHEAD` steps ahead. It is fit by least squares (:func:`fit_motion`)
on the moves of the scenario's own **training** traces (the split that training draws
its episodes from: recorded traffic of that city, never its validation or test
traces), once per traces' setting, and cached beside them
(:func:`learned_motion`). It sees what constant velocity sees, the vehicles' past
positions, and no route.

:class:`LearnedMotion` is the predictor: a vehicle present at each of the last
HISTORY + 1 steps of the window gets the network's prediction; one seen for fewer steps
falls back to constant velocity (one move) or stands (none); presence stays as now, as
for constant velocity. Beyond AHEAD steps a vehicle continues by its last predicted move.
It reads the traces at steps t − HISTORY … t only (tested, as for constant velocity).
"""

from __future__ import annotations

import hashlib
import json
import logging

import torch
from torch import nn

from uabs_rl.env.uabs_env import UABSEnv
from uabs_rl.evaluation.predict import ConstantVelocity, Predictor, observed

log = logging.getLogger(__name__)

HISTORY = 4  # the moves the network reads
AHEAD = 10  # the steps it predicts
HIDDEN = 128  # the width of its two hidden layers
# its fit: spans drawn per traces, Adam steps, batch, learning rate and seed (seconds on
# 2 cores; all of them name the cached model, model_key)
FIT = {"samples": 400_000, "steps": 6000, "batch": 1024, "lr": 1e-3, "seed": 0}


class MotionModel(nn.Module):
    """``[N, HISTORY, 2]`` last moves (oldest first) -> ``[N, AHEAD, 2]`` displacements
    from the current position at steps 1 … AHEAD. Inputs and outputs are scaled by the
    training data's spread (buffers, saved with the weights)."""

    def __init__(self, history: int = HISTORY, ahead: int = AHEAD, hidden: int = HIDDEN):
        super().__init__()
        self.history, self.ahead = history, ahead
        self.net = nn.Sequential(nn.Linear(2 * history, hidden), nn.ReLU(),
                                 nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, 2 * ahead))
        self.register_buffer("x_scale", torch.ones(2 * history))
        self.register_buffer("y_scale", torch.ones(2 * ahead))

    def forward(self, moves: torch.Tensor) -> torch.Tensor:
        x = moves.reshape(moves.shape[0], -1) / self.x_scale
        return (self.net(x) * self.y_scale).view(-1, self.ahead, 2)


def motion_samples(positions: torch.Tensor, present: torch.Tensor, n: int,
                   gen: torch.Generator, history: int = HISTORY, ahead: int = AHEAD
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Up to ``n`` (moves ``[N, history, 2]``, displacements ``[N, ahead, 2]``) drawn
    from traces ``positions [S, T, V, 2]`` / ``present [S, T, V]``: a vehicle at a
    step, kept where it is present at every step from ``history`` before to ``ahead``
    after."""
    s_n, t_n, v_n = present.shape
    if t_n <= history + ahead:
        raise ValueError(f"traces of {t_n} steps hold no {history} + {ahead} + 1-step span")
    s = torch.randint(s_n, (n,), generator=gen)
    t = torch.randint(history, t_n - ahead, (n,), generator=gen)
    v = torch.randint(v_n, (n,), generator=gen)
    span = t[:, None] + torch.arange(-history, ahead + 1)
    p = positions[s[:, None], span, v[:, None]]  # [n, history + ahead + 1, 2]
    ok = present[s[:, None], span, v[:, None]].all(1)
    p = p[ok]
    now = p[:, history]
    return p[:, 1:history + 1] - p[:, :history], p[:, history + 1:] - now[:, None]


def fit_motion(traces: list[tuple[torch.Tensor, torch.Tensor]], samples: int = FIT["samples"],
               steps: int = FIT["steps"], batch: int = FIT["batch"], lr: float = FIT["lr"],
               seed: int = FIT["seed"]) -> MotionModel:
    """A :class:`MotionModel` fit by mean squared error on ``samples`` draws from each
    of ``traces`` (``(positions [S, T, V, 2], present [S, T, V])``), with Adam."""
    gen = torch.Generator().manual_seed(seed)
    xs, ys = zip(*(motion_samples(pos, pres, samples, gen) for pos, pres in traces),
                 strict=True)
    x, y = torch.cat(xs), torch.cat(ys)
    if len(x) < batch:
        raise ValueError(f"the traces hold {len(x)} spans of {HISTORY + AHEAD + 1} steps "
                         f"with a vehicle present throughout: too few to fit the motion model")
    x, y = x.reshape(len(x), -1), y.reshape(len(y), -1)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = MotionModel()
    model.x_scale.copy_(x.std(0) + 1e-3)
    model.y_scale.copy_(y.std(0) + 1e-3)
    opt = torch.optim.Adam(model.net.parameters(), lr=lr)
    for _ in range(steps):
        i = torch.randint(len(x), (batch,), generator=gen)
        out = model.net(x[i] / model.x_scale)
        loss = ((out - y[i] / model.y_scale) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return model.eval()


class LearnedMotion(Predictor):
    """Each vehicle moved as :class:`MotionModel` ``model`` predicts from its last moves
    (module docstring)."""

    name = "learned"

    def __init__(self, model: MotionModel):
        self.model = model

    @torch.no_grad()
    def __call__(self, env: UABSEnv, horizon: int) -> dict[str, torch.Tensor]:
        world = ConstantVelocity()(env, horizon)  # the others' world, and the presence
        h = self.model.history
        past = [observed(env, b) for b in range(h + 1)]  # now, one step before, ...
        now, present = past[0]
        seen = present.clone()
        for _, there in past[1:]:
            seen &= there
        full = seen & (env.state["t"] >= h)[:, None]  # h distinct steps back in the window
        veh = world["veh"]  # [H, E, 2, V]
        if bool(full.any()):
            e_i, v_i = full.nonzero(as_tuple=True)
            pos = torch.stack([p[e_i, :, v_i] for p, _ in reversed(past)], 1)  # [N, h+1, 2]
            disp = self.model(pos[:, 1:] - pos[:, :-1])  # [N, AHEAD, 2]
            a = self.model.ahead
            if horizon > a:  # on by the last predicted move
                last = disp[:, -1] - (disp[:, -2] if a > 1 else 0.0)
                extra = torch.arange(1, horizon - a + 1, device=now.device, dtype=now.dtype)
                disp = torch.cat([disp, disp[:, -1:] + extra[None, :, None] * last[:, None]], 1)
            # (the indices apart from each other: the result's rows lead, [N, H, 2])
            veh[:, e_i, :, v_i] = now[e_i, :, v_i][:, None] + disp[:, :horizon]
        return world


def model_key(trace_key: str) -> str:
    """The cache name of the model fit on the training traces of key ``trace_key``: it
    and every setting of the model and its fit."""
    desc = json.dumps({"traces": trace_key, "history": HISTORY, "ahead": AHEAD,
                       "hidden": HIDDEN, "fit": FIT, "version": 1}, sort_keys=True)
    return hashlib.sha256(desc.encode()).hexdigest()[:16]


def learned_motion(scenario, traces_cfg, device: torch.device | str = "cpu") -> LearnedMotion:
    """The learned predictor of ``scenario``: its model fit on the scenario's training
    traces (built with SUMO if not cached yet), read from the traces' cache folder when
    fit before (``<scenario>-motion-<key>.pt``), else fit (seconds) and written there."""
    from uabs_rl.config import ConfigError, resolved_split
    from uabs_rl.paths import atomic_file, inside, safe_component
    from uabs_rl.traces.build import get_traces
    from uabs_rl.traces.cache import cache_dir, split_key

    if traces_cfg is None:
        raise ValueError("the learned predictor needs the traces' settings (its training "
                         "traces)")
    safe_component(scenario.name, "scenario.name")  # it names the cache file
    key, _ = split_key(scenario, resolved_split(scenario, traces_cfg, "train"), "train")
    d = cache_dir(traces_cfg)
    path = inside(d / f"{scenario.name}-motion-{model_key(key)}.pt", d, "scenario.name")
    model = MotionModel()
    if path.is_file():
        try:
            model.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
            return LearnedMotion(model.eval().to(device))
        except Exception as e:  # noqa: BLE001 (any damage: refit, it is only a cache)
            log.warning("motion model %s unreadable (%s): fitting it again", path,
                        str(e).splitlines()[0])
    ts = get_traces(scenario, traces_cfg, "train")
    log.info("fitting the learned predictor's motion model on %s's training traces", scenario.name)
    try:
        model = fit_motion([(ts.positions, ts.present)])
    except ValueError as e:  # traces too short or too sparse for one span
        raise ConfigError(f"--predictor learned: {e}; the scenario's training traces "
                          f"(traces.train.n_sims, traces.train.duration_s) are too small "
                          f"to fit the motion model on") from None
    try:
        d.mkdir(parents=True, exist_ok=True)
        with atomic_file(path) as f:
            torch.save(model.state_dict(), f)
    except OSError as e:  # only a cache: fly the model, fit it again next time
        log.warning("motion model not cached at %s (%s): it will be fit again next time",
                    path, e)
    return LearnedMotion(model.to(device))
