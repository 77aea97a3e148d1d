"""``UABSEnv``: a batched TorchRL environment replaying cached vehicle traces
(docs/model.md §1, §3-§5).

Batch ``[n_envs]``; one agent group ``"agents"`` with nested batch ``(n_envs, M)``.
The physics live in plain tensor code elsewhere: :mod:`uabs_rl.env.geometry` (lattice,
starts, boundary, distances), :class:`uabs_rl.env.links.LinkModel` (beams and service),
:mod:`uabs_rl.env.service` (priorities, windows, P_g). :class:`StepMath` composes them into
one step on plain tensors, so a benchmark can time it without any TensorDict and a test
can call it directly; ``UABSEnv`` only moves state in and out of TensorDicts.

Order inside a step (docs/model.md §5): agents move → vehicles advance to t+1 → served flags
at t+1 → priorities p_{t+1} → per-beam sums b_{t+1} → rewards and observations.
"""

from __future__ import annotations

from dataclasses import replace

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from uabs_rl import rng
from uabs_rl.config import ChannelConfig, ConfigError, ObsConfig, ScenarioConfig
from uabs_rl.env import observe, service
from uabs_rl.env._compile import compiled_or_eager
from uabs_rl.env.geometry import Geometry
from uabs_rl.env.links import LinkModel
from uabs_rl.env.params import EnvParams
from uabs_rl.env.state import empty_state
from uabs_rl.traces.cache import TraceSet

# Nested keys, in one place.
AGENTS = "agents"
OBS = (AGENTS, "observation")
ACTION = (AGENTS, "action")
MASK = (AGENTS, "action_mask")
REWARD = (AGENTS, "reward")
POSITION = (AGENTS, "position")
BEAM_PRIORITY = (AGENTS, "beam_priority")
FALLBACK = (AGENTS, "mask_fallback")
DIAG = "diagnostics"

N_ACTIONS = 4
ACTION_NAMES = ("up", "right", "down", "left")  # +y, +x, −y, −x

BACKUP = (AGENTS, "backup_action")
AGENT_OUT = ("observation", "action_mask", "position", "beam_priority", "backup_action",
             "reward")
DIAG_KEYS = (  # every one is a float [n_envs]
    "served_fraction", "collisions", "proximity", "fallbacks", "illegal_moves",
    "min_pair_distance", "closest_approach",
    "ep_return", "ep_collisions", "ep_proximity", "ep_fallbacks", "pg",
)
DIAG_ENTRIES = (*DIAG_KEYS, "pg_curve")  # [E, N]
DONE_KEYS = ("done", "terminated", "truncated")


class Outputs(dict):
    """The env's outputs as one flat dict keyed as in its TensorDict
    (``("agents", "observation")``, ``"done"``, ``("diagnostics", "pg")``, ...): what
    :meth:`UABSEnv.reset_direct` and :meth:`UABSEnv.step_direct` return to the training
    loop. ``get`` and ``set`` work as on a TensorDict, so the masking rules and the
    action selector read and write either."""

    def set(self, key, value) -> Outputs:
        self[key] = value
        return self


class StepMath:
    """One env step on plain tensors: the state ``st`` is a dict of ``[E, ...]`` tensors."""

    def __init__(self, p: EnvParams, device: torch.device):
        self.p = p
        self.geometry = Geometry(p, device)
        self.links = LinkModel(p, device)
        self.moves = self.geometry.moves
        # the scored positions: the egocentric local map, or the lookahead observation's
        # 4 moves, then 2 steps in each direction
        self.look_offsets = (observe.map_offsets(p.map_radius, p.step_m, device)
                             if p.egocentric else
                             torch.cat([self.moves, 2 * self.moves])[: min(p.n_lookahead, 8)])

    def observe(self, st: dict[str, torch.Tensor], veh_pos: torch.Tensor,
                veh_present: torch.Tensor,
                gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """Service at step ``st["t"]`` for UABS at ``st["pos"]``: updates priorities, the
        window tallies and the beam sums ``st["b"]`` in place; returns the served flags
        and the presence of the vehicles ``[E, V]``."""
        veh, present = service.vehicles_at(st, veh_pos, veh_present)
        inside, beam, served = self.links.links(st["pos"], veh, present, gen)
        service.update_service(st, served, present, self.p.window_steps)
        st["b"] = service.beam_sums(inside, beam, st["priority"], self.p.n_beams)
        if self.p.n_lookahead:
            cand = st["pos"][:, :, None, :] + self.look_offsets  # [E, M, C, 2]
            look = service.move_scores(cand, veh, present, st["priority"], self.p.r_b,
                                       self.p.n_beams)
            if self.p.motion_obs:
                ahead = service.extrapolated(st, veh, present, veh_pos, veh_present,
                                             self.p.motion_steps)
                moved = cand if self.p.egocentric else st["pos"][:, :, None, :] + self.moves
                scores = [look, service.move_scores(
                    moved, ahead[0], present, st["priority"], self.p.r_b, self.p.n_beams)]
                for k in range(2, self.p.motion_steps + 1):  # k moves on, k steps ahead
                    scores.append(service.move_scores(
                        st["pos"][:, :, None, :] + k * self.moves, ahead[k - 1], present,
                        st["priority"], self.p.r_b, self.p.n_beams))
                look = torch.cat(scores, dim=-1)
            st["look"] = look
        return served, present

    # ------------------------------------------------------------------ reward
    def rewards(self, b: torch.Tensor, dist: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """r [E, M] (paper eq. 3) and per-env collision / proximity pair counts."""
        p = self.p
        coll = dist < p.collision_distance
        prox = dist < p.d_th
        r = b.sum(-1).masked_fill_(prox.any(-1), -p.lambda_s).masked_fill_(coll.any(-1),
                                                                          -p.lambda_c)
        return r, coll.flatten(1).sum(-1) / 2.0, prox.flatten(1).sum(-1) / 2.0

    def observation(self, pos: torch.Tensor, t: torch.Tensor, b: torch.Tensor,
                    look: torch.Tensor, bounds: torch.Tensor | None = None) -> torch.Tensor:
        """[E, M, obs_dim]: the paper's o = (x/W, y/H, t/T, L_t, b_t / scale[, lookahead /
        scale]) or the egocentric observation (:mod:`uabs_rl.env.observe`); ``bounds
        [E, 2]``: each env's own area (a family of cities)."""
        p = self.p
        area = self.geometry.area if bounds is None else bounds[:, None, :]
        if p.egocentric:
            return observe.egocentric_observation(
                pos, t, b, look, area, p.episode_steps, p.obs_scale, p.neighbours,
                p.neighbour_range * p.step_m, p.edge_range * p.step_m)
        return observe.fleet_observation(pos, t, b, look if p.lookahead_obs else None, area,
                                         p.episode_steps, p.obs_scale)

    # ------------------------------------------------------------------ one step
    def step(self, st: dict[str, torch.Tensor], action: torch.Tensor, veh_pos: torch.Tensor,
             veh_present: torch.Tensor, gen: torch.Generator,
             fallback: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Advance the state ``st`` in place by one step; return the flat outputs.
        ``action [E, M]``; ``fallback [E, M]`` flags agents whose mask was empty."""
        action = action.long()
        old = st["pos"]
        geo = self.geometry
        bounds = st.get("bounds")  # a family's per-env (W, H); None: the one area
        legal = geo.boundary_mask(old, bounds).gather(-1, action[..., None]).squeeze(-1)
        new = torch.where(legal[..., None], old + self.moves[action], old)
        st["pos"] = new
        st["t"] = st["t"] + 1
        st["backup"] = (action + 2) % 4  # the move back: up <-> down, right <-> left
        served, present = self.observe(st, veh_pos, veh_present, gen)
        dist = geo.pair_distances(new)
        reward, n_coll, n_prox = self.rewards(st["b"], dist)
        n_fb = (fallback.float().flatten(1).sum(-1) if fallback is not None
                else torch.zeros_like(n_coll))
        st["ep_return"] = st["ep_return"] + reward.sum(-1)
        st["ep_collisions"] = st["ep_collisions"] + n_coll
        st["ep_proximity"] = st["ep_proximity"] + n_prox
        st["ep_fallbacks"] = st["ep_fallbacks"] + n_fb
        step_diag = {"collisions": n_coll, "proximity": n_prox, "fallbacks": n_fb,
                     "illegal_moves": (~legal).float().sum(-1),
                     "min_pair_distance": dist.flatten(1).amin(-1).clamp_max(1e6),
                     "closest_approach": geo.closest_approach(old, new).clamp_max(1e6)}
        out = self.outputs(st, served, present, step_diag)
        out["reward"] = reward[..., None]
        return out

    def outputs(self, st: dict[str, torch.Tensor], served: torch.Tensor,
                present: torch.Tensor, diag: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Observation, masks, flags (``done [E, 1]``, ..., and each agent's copy,
        ``agent_done [E, M, 1]``, ...) and diagnostics of the current state."""
        p = self.p
        e, m = st["pos"].shape[:2]
        done = (st["t"] >= p.episode_steps)[:, None]  # [E, 1]
        never = torch.zeros_like(done)
        flags = dict(done=done, terminated=done if p.time_is_terminal else never,
                     truncated=never if p.time_is_terminal else done)
        pg_curve = service.pg_curve(st["n_windows"], st["ns_hist"])
        return dict(
            diag, **flags, **{f"agent_{k}": f[:, None, :].expand(e, m, 1)
                              for k, f in flags.items()},
            observation=self.observation(st["pos"], st["t"], st["b"], st["look"],
                                         st.get("bounds")),
            action_mask=self.geometry.boundary_mask(st["pos"], st.get("bounds")),
            position=st["pos"],
            beam_priority=st["b"], backup_action=st["backup"],
            served_fraction=served.float().sum(-1) / present.float().sum(-1).clamp_min(1.0),
            ep_return=st["ep_return"], ep_collisions=st["ep_collisions"],
            ep_proximity=st["ep_proximity"], ep_fallbacks=st["ep_fallbacks"],
            pg=pg_curve[:, p.nhat_s - 1], pg_curve=pg_curve)



# ----------------------------------------------------------------------------- set-up
def fleet_packing(geo: Geometry, margin: float) -> torch.Tensor:
    """Lattice points at least d_th + ``margin`` apart, at least M of them, or a
    ConfigError naming scenario.n_uabs and the largest fleet that fits."""
    p = geo.p
    spacing = p.d_th + margin
    packing = geo.packing(spacing)
    if p.n_uabs > packing.shape[0]:
        need = "" if margin == 0 else (
            f" (the {spacing:.1f} m = d_th + {margin:.0f} m that the recoverable masks "
            f"need at the start; masking.recoverable=false needs d_th only)")
        raise ConfigError(
            f"scenario.n_uabs={p.n_uabs} but the {p.width:g} m x {p.height:g} m area "
            f"holds at most {packing.shape[0]} UABS with every pair at least "
            f"{spacing:.1f} m apart{need}: lower scenario.n_uabs to "
            f"{packing.shape[0]} or enlarge scenario.area.")
    return packing


def check_traces(traces: TraceSet, p: EnvParams) -> None:
    """Refuse traces too short for an episode or sampled at another δt."""
    need = p.episode_steps + 1
    if traces.steps < need:
        raise ConfigError(
            f"the {traces.meta.get('split', '?')} traces hold {traces.steps} steps but an "
            f"episode needs scenario.episode_steps + 1 = {need}: raise "
            f"traces.<split>.duration_s or lower scenario.episode_steps.")
    if abs(float(traces.meta.get("dt", p.dt)) - p.dt) > 1e-9:
        raise ConfigError(f"the traces were sampled every {traces.meta['dt']} s but "
                          f"scenario.dt is {p.dt}: rebuild the traces.")


def window_count(n_sims: int, steps: int, episode_steps: int) -> int:
    """Non-overlapping windows of T + 1 steps in ``n_sims`` traces of ``steps`` steps."""
    return n_sims * (steps // (episode_steps + 1))


def fixed_windows(n_sims: int, steps: int, episode_steps: int, n: int | None,
                  device: torch.device) -> torch.Tensor:
    """[K, 2] (sim, start) of non-overlapping held-out windows, sims interleaved."""
    most = window_count(n_sims, steps, episode_steps)
    n = most if n is None else n
    if not 1 <= n <= most:
        raise ConfigError(
            f"n_eval_windows={n} but the held-out traces hold {most} "
            f"non-overlapping windows of {episode_steps} steps ({episode_steps + 1} "
            f"recorded instants each): lower it "
            f"or raise traces.eval.n_sims / traces.eval.duration_s.")
    k = torch.arange(n, device=device)
    return torch.stack([k % n_sims, (k // n_sims) * (episode_steps + 1)], dim=-1)


def env_specs(p: EnvParams, e: int, dev: torch.device) -> dict[str, Composite]:
    """Observation, action, reward and done specs of ``e`` envs."""
    m = p.n_uabs
    agents = Composite(
        observation=Unbounded((e, m, p.obs_dim), device=dev),
        action_mask=Binary(n=N_ACTIONS, shape=(e, m, N_ACTIONS), dtype=torch.bool,
                           device=dev),
        position=Unbounded((e, m, 2), device=dev),  # metres, for the masks
        beam_priority=Unbounded((e, m, p.n_beams), device=dev),  # raw b_t, for ranks
        # the move that retraces the last one (at reset: a boundary-legal one), for the
        # recoverable masks
        backup_action=Categorical(N_ACTIONS, shape=(e, m), device=dev),
        shape=(e, m), device=dev)
    diag = Composite({k: Unbounded((e,), device=dev) for k in DIAG_KEYS},
                     pg_curve=Unbounded((e, p.window_steps), device=dev),
                     shape=(e,), device=dev)
    flag = lambda *s: Categorical(2, shape=s, dtype=torch.bool, device=dev)  # noqa: E731
    return dict(
        observation=Composite(agents=agents, diagnostics=diag, shape=(e,), device=dev),
        action=Composite(agents=Composite(action=Categorical(N_ACTIONS, shape=(e, m),
                                                             device=dev),
                                          shape=(e, m), device=dev), shape=(e,), device=dev),
        reward=Composite(agents=Composite(reward=Unbounded((e, m, 1), device=dev),
                                          shape=(e, m), device=dev), shape=(e,), device=dev),
        done=Composite(done=flag(e, 1), terminated=flag(e, 1), truncated=flag(e, 1),
                       agents=Composite(done=flag(e, m, 1), terminated=flag(e, m, 1),
                                        truncated=flag(e, m, 1), shape=(e, m), device=dev),
                       shape=(e,), device=dev))


def direct_outputs(out: dict[str, torch.Tensor]) -> Outputs:
    """The step math's flat outputs under the env's keys (see :func:`pack_outputs`)."""
    entries = Outputs({(AGENTS, k): out[k] for k in AGENT_OUT if k in out})
    for k in DONE_KEYS:
        entries[k] = out[k]
        entries[AGENTS, k] = out[f"agent_{k}"]
    for k in DIAG_ENTRIES:
        entries[DIAG, k] = out[k]
    return entries


def pack_outputs(out: dict[str, torch.Tensor], e: int, m: int,
                 device: torch.device) -> TensorDict:
    """The step math's flat outputs as the env's TensorDict of ``e`` envs of ``m`` agents
    (see the specs)."""
    agents = {k: out[k] for k in AGENT_OUT if k in out}
    agents.update({k: out[f"agent_{k}"] for k in DONE_KEYS})
    return TensorDict({
        AGENTS: TensorDict(agents, batch_size=(e, m), device=device),
        **{k: out[k] for k in DONE_KEYS},
        DIAG: TensorDict({k: out[k] for k in DIAG_ENTRIES}, batch_size=(e,), device=device),
    }, batch_size=(e,), device=device)


def draw_windows(cursor: torch.Tensor, eval_windows: torch.Tensor | None,
                 trace_shape: tuple[int, int], episode_steps: int,
                 gen: torch.Generator | list[torch.Generator]) -> tuple[torch.Tensor, torch.Tensor]:
    """(simulation, start step) of each env's next episode: the fixed evaluation window
    its ``cursor`` points at, or (no ``eval_windows``, training) a random window of the
    ``trace_shape`` = (simulations, steps) traces."""
    if eval_windows is not None:
        w = eval_windows[cursor % eval_windows.shape[0]]
        return w[:, 0], w[:, 1]
    n, dev = cursor.shape[0], cursor.device
    sim = rng.randint(0, trace_shape[0], (n,), gen, dev)
    start = rng.randint(0, trace_shape[1] - episode_steps, (n,), gen, dev)
    return sim, start


def merge_where(state: dict[str, torch.Tensor], fresh: dict[str, torch.Tensor],
                mask: torch.Tensor, skip: str) -> None:
    """``state[k]`` takes ``fresh[k]`` in the envs of ``mask`` (every entry but ``skip``)."""
    for k, v in fresh.items():
        if k != skip:
            state[k] = torch.where(mask.view(-1, *([1] * (v.dim() - 1))), v, state[k])


class UABSEnv(EnvBase):
    """M UABS over replayed vehicle traces; see the module docstring for the step order.

    ``mode="train"`` draws a random T-step window of the traces at each reset;
    ``mode="eval"`` walks ``n_eval_windows`` fixed, non-overlapping windows: env ``i``
    gets window ``i``, then ``i + n_envs``, ... (mod the number of windows).
    ``compile_step=True`` runs the step math through ``torch.compile`` (``compile`` is
    TorchRL's own argument, which compiles ``step_and_maybe_reset`` as a whole).

    The episode state is :attr:`state`, a dict of ``[n_envs, ...]`` tensors; ``env.to()``
    moves it with the traces.
    """

    batch_locked = True

    def __init__(self, scenario: ScenarioConfig, channel: ChannelConfig, traces: TraceSet,
                 n_envs: int = 1, mode: str = "train", device: str | torch.device = "cpu",
                 n_eval_windows: int | None = None, seed: int | None = None,
                 compile_step: bool = False, obs: ObsConfig | None = None):
        if mode not in ("train", "eval"):
            raise ConfigError(f"mode must be 'train' or 'eval', got {mode!r}")
        if n_envs < 1:
            raise ConfigError(f"n_envs must be >= 1, got {n_envs}")
        device = torch.device(device)
        super().__init__(batch_size=torch.Size([n_envs]), device=device)
        self.params = EnvParams.from_config(scenario, channel, obs)
        self.mode = mode
        self.n_envs = n_envs
        self.compile_step = compile_step
        check_traces(traces, self.params)
        # planar layout [S, steps, 2, V]: x and y rows stay contiguous per step
        self.register_buffer("veh_pos", traces.positions.transpose(-1, -2).contiguous().to(device))
        self.register_buffer("veh_present", traces.present.to(device))  # [S, steps, V]
        # [K, 2] (sim, start) of the fixed evaluation windows; None in train mode
        self.register_buffer("eval_windows", fixed_windows(
            *self.veh_pos.shape[:2], self.params.episode_steps, n_eval_windows, device)
            if mode == "eval" else None)
        # one generator, or one per population member (a list of seeds; see uabs_rl.rng)
        self.rng = rng.make_generator(seed, device)
        # a family of cities (traces.build.stack_cities): each sim's city and their areas
        family = traces.meta.get("city_of_sim")
        self.register_buffer("city_of_sim", None if family is None else
                             torch.tensor(family, dtype=torch.long, device=device))
        self.register_buffer("city_bounds", None if family is None else
                             torch.tensor(traces.meta["city_area"], device=device))
        self._build_math(device)
        self.start_spacing: float | None = None  # see require_start_spacing
        self.packings: list[torch.Tensor] = []  # each city's [K, 2] start points
        self.state = self._empty_state()
        specs = env_specs(self.params, n_envs, device)
        self.observation_spec, self.action_spec = specs["observation"], specs["action"]
        self.reward_spec, self.done_spec = specs["reward"], specs["done"]

    def _build_math(self, device: torch.device) -> None:
        self.math = StepMath(self.params, device)
        # each city's geometry (lattice, starts), or the one area's
        self.cities = [self.math.geometry] if self.city_bounds is None else [
            Geometry(replace(self.params, width=float(w), height=float(h)), device)
            for w, h in self.city_bounds.tolist()]
        # torch.compile fuses the step's many small tensor ops: ~6x faster at n_envs = 1
        # on CPU (benchmarks/numpy_reference.py); ~10 s of compilation at the first step
        self._step_math = compiled_or_eager(self.math.step, "the env step", device) \
            if self.compile_step else self.math.step

    def _apply(self, fn, recurse: bool = True):
        """``env.to(device)`` moves the buffers (traces), the episode state, the step
        math's constants and the generator (re-seeded from a draw of the old one)."""
        out = super()._apply(fn, recurse)
        if self.veh_pos.device != self.math.geometry.device:
            dev = self.veh_pos.device
            self.state = {k: fn(v) for k, v in self.state.items()}
            self.rng = rng.reseeded(self.rng, dev)
            self.packings = [fn(k) for k in self.packings]
            self._build_math(dev)
        return out

    def require_start_spacing(self, margin: float) -> None:
        """Every episode starts with every pair at least d_th + ``margin`` apart (the
        paper's placement where it achieves that, else random points of a packing of
        the area). Refuses a fleet the area cannot hold that far apart."""
        self.start_spacing = self.params.d_th + margin
        self.packings = [fleet_packing(geo, margin) for geo in self.cities]

    def _empty_state(self) -> dict[str, torch.Tensor]:
        return empty_state(self.params, self.n_envs, self.veh_pos.shape[3], self.device,
                           family=self.city_bounds is not None)

    def _set_seed(self, seed: int | None) -> None:
        """Seeds start positions, windows and LoS draws; in eval mode it also rewinds to
        the first held-out windows, so every seeded evaluation sees the same episodes."""
        self.rng.manual_seed(int(seed) if seed is not None else 0)
        self.state["cursor"] = torch.arange(self.n_envs, device=self.device)

    # ------------------------------------------------------------------ reset / step
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict["_reset"].reshape(self.n_envs)
        return pack_outputs(self._reset_state(mask), self.n_envs, self.params.n_uabs,
                            self.device)

    def _reset_state(self, mask: torch.Tensor | None) -> dict[str, torch.Tensor]:
        """Start a new episode in the envs of ``mask [n_envs]`` (None: all); returns the
        step math's flat outputs of the new state."""
        st = self.state
        if mask is None:
            mask = torch.ones(self.n_envs, dtype=torch.bool, device=self.device)
        fresh = self._empty_state()
        fresh["sim"], fresh["start"] = draw_windows(st["cursor"], self.eval_windows,
                                                    self.veh_pos.shape[:2],
                                                    self.params.episode_steps, self.rng)
        city = None
        if self.city_bounds is not None:
            city = self.city_of_sim[fresh["sim"]]
            fresh["bounds"] = self.city_bounds[city]
        for c, geo in enumerate(self.cities):  # each city's starts, kept where it is drawn
            pos = geo.start_positions(self.n_envs, self.rng)
            if self.start_spacing is not None:
                pos = geo.spread_start(pos, self.packings[c], self.start_spacing, self.rng)
            fresh["pos"] = pos if city is None else torch.where(
                (city == c)[:, None, None], pos, fresh["pos"])
        fresh["backup"] = self.math.geometry.boundary_mask(
            fresh["pos"], fresh.get("bounds")).float().argmax(-1)
        served, present = self.math.observe(fresh, self.veh_pos, self.veh_present, self.rng)
        merge_where(st, fresh, mask, skip="cursor")
        if self.mode == "eval":  # the next reset of env i takes window i + n_envs, ...
            st["cursor"] = st["cursor"] + mask.long() * self.n_envs
        zeros = torch.zeros(self.n_envs, device=self.device)
        return self.math.outputs(st, served, present, {k: zeros for k in DIAG_KEYS})

    # ------------------------------------------------------------------ direct path
    def reset_direct(self) -> Outputs:
        """:meth:`reset` of every env, its outputs as :class:`Outputs` (no TensorDict,
        none of TorchRL's per-call work): entry for entry what ``reset()`` returns."""
        return direct_outputs(self._reset_state(None))

    def step_direct(self, action: torch.Tensor,
                    fallback: torch.Tensor | None = None) -> Outputs:
        """One step with ``action [n_envs, M]`` (and the selector's fallback flags), its
        outputs as :class:`Outputs`: entry for entry what ``step(td)["next"]`` holds."""
        return direct_outputs(self._step_math(self.state, action, self.veh_pos,
                                             self.veh_present, self.rng, fallback))

    # ------------------------------------------------------------------ public views
    def vehicles(self, lookahead: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """Vehicle positions ``[E, 2, V]`` and presence ``[E, V]`` of each env ``lookahead``
        steps after its current one (baselines look at them)."""
        st = dict(self.state)
        st["t"] = st["t"] + lookahead
        return service.vehicles_at(st, self.veh_pos, self.veh_present)

    @property
    def priority(self) -> torch.Tensor:
        """Current priority of every vehicle, ``[E, V]`` (0 where absent)."""
        return self.state["priority"]

    def window_trace(self, window: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Vehicle positions ``[T+1, 2, V]`` and presence ``[T+1, V]`` of eval window
        ``window`` (eval mode only)."""
        if self.eval_windows is None:
            raise ValueError("window_trace needs an env in eval mode")
        sim, start = self.eval_windows[window].tolist()
        sl = slice(start, start + self.params.episode_steps + 1)
        return self.veh_pos[sim, sl], self.veh_present[sim, sl]

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        fb = tensordict.get(FALLBACK, None)
        out = self._step_math(self.state, tensordict.get(ACTION), self.veh_pos,
                              self.veh_present, self.rng, fb)
        return pack_outputs(out, self.n_envs, self.params.n_uabs, self.device)
