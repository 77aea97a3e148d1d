"""The learners (uabs_rl.algorithms): the registry, the 3DQN's losses and update, and
the replay of env-step transitions."""

from __future__ import annotations

import contextlib
import copy

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from uabs_rl.algorithms import ALGORITHMS, Dims, make_algorithm
from uabs_rl.algorithms import dqn3 as dqn3_module
from uabs_rl.algorithms.model import DuelingQNet
from uabs_rl.algorithms.replay import TransitionReplay, upgrade_flat_replay
from uabs_rl.config import AlgoConfig, ConfigError, QmixConfig, algo_schema


def learner_config(name: str, **kw) -> AlgoConfig:
    """The settings of the learner ``name`` in its own schema (QMIX's mixer 8 wide)."""
    if name == "qmix":
        kw.setdefault("mixing_embed_dim", 8)
    return algo_schema(name)(name=name, **kw)


def dqn3(algo: AlgoConfig | None = None, obs_dim: int = 18, seeds=(0,), agents: int = 3):
    return make_algorithm(algo or AlgoConfig(), Dims(obs_dim, 4, agents), list(seeds),
                          torch.device("cpu"))


def seeded_net(seed: int, obs_dim: int = 18, hidden=(256, 256)) -> DuelingQNet:
    """The initial network of a run of seed ``seed`` (what DQN3 builds)."""
    torch.manual_seed(seed)
    return DuelingQNet(obs_dim, 4, list(hidden))


def batch(n=64, d=18, seed=0):
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(n, 4, generator=g) < 0.7
    mask[:, 0] = True
    return {"obs": torch.randn(n, d, generator=g), "action": torch.randint(0, 4, (n,), generator=g),
            "mask": torch.ones(n, 4, dtype=torch.bool), "reward": torch.randn(n, generator=g),
            "next_obs": torch.randn(n, d, generator=g), "next_mask": mask,
            "terminated": torch.rand(n, generator=g) < 0.2}


def test_dueling_head_is_v_plus_centred_advantage():
    net = DuelingQNet(5, 4, [8])
    x = torch.randn(3, 2, 5)  # [envs, agents, obs]: parameters shared across agents
    q = net(x)
    z = net.trunk(x)
    a = net.advantage(z)
    assert q.shape == (3, 2, 4)
    assert torch.allclose(q.mean(-1, keepdim=True), net.value(z), atol=1e-6)
    assert torch.allclose(q - q.mean(-1, keepdim=True), a - a.mean(-1, keepdim=True), atol=1e-6)


def test_registry_dispatches_algo_name_and_refuses_an_unknown_one():
    assert type(dqn3()).__name__ == "DQN3" and "dqn3" in ALGORITHMS
    with pytest.raises(ConfigError, match=r"algo.name='vdm' is not a registered.*dqn3"):
        make_algorithm(AlgoConfig(name="vdm"), Dims(18, 4, 3), [0], torch.device("cpu"))
    from uabs_rl.training.startup import validate_algo_name
    with pytest.raises(ConfigError, match=r"algo.loss=torchrl .* algo=vdn has its own"):
        validate_algo_name(AlgoConfig(name="vdn", loss="torchrl"))


def test_fused_and_torchrl_losses_agree():
    algo = dict(hidden=[32, 32], gamma=0.8)
    fused = dqn3(AlgoConfig(loss="fused", **algo))
    trl = dqn3(AlgoConfig(loss="torchrl", **algo))
    assert isinstance(trl.loss_module, dqn3_module.TorchRLDQN3Loss)
    # make the target differ from the online net, identically in both learners
    with torch.no_grad():
        for p in fused.loss_module.target_network.parameters():
            p.add_(0.1)
    # through the resume path: a learner state whose target differs from the online net
    trl.load_state_dict({**trl.state_dict(), "target": fused.state_dict()["target"]})
    assert all(torch.equal(v, fused.state_dict()["target"][k])
               for k, v in trl.state_dict()["target"].items())
    b = batch()
    lf, _ = fused.loss(b)
    lt, _ = trl.loss(b)
    assert lf.item() == pytest.approx(lt.item(), rel=1e-5)
    lf.backward()
    lt.backward()
    for pf, pt in zip(fused.policy.parameters(), trl.policy.parameters(), strict=True):
        assert torch.allclose(pf.grad, pt.grad, atol=1e-6)


def test_flushing_denormal_adam_moments_keeps_parameters_bit_identical(monkeypatch):
    """Dead ReLU units get zero gradients, so their Adam moments decay into denormals;
    the update flushes those to zero (for speed) and must leave every parameter exactly
    as the unflushed update does."""
    flushed, plain = (dqn3(AlgoConfig(hidden=[32, 32], lr=1e-3)) for _ in range(2))
    for lrn in (flushed, plain):
        with torch.no_grad():
            lrn.policy.trunk[2].bias[:8] = -1e3  # units 0-7 of the second layer never fire
        lrn.update(batch(seed=99))
        st = lrn.optim.state[lrn.policy.trunk[2].weight]  # the dead units' rows
        st["exp_avg"][:8], st["exp_avg_sq"][:8] = 1e-39, 1e-41  # decayed moments
    start = copy.deepcopy(flushed.policy.trunk[2].weight)
    tiny = torch.finfo(torch.float32).tiny
    for i in range(30):
        b = batch(seed=i)
        flushed.update(b)
        with monkeypatch.context() as m:
            m.setattr(dqn3_module, "flush_denormals", contextlib.nullcontext)
            plain.update(b)
    moments = [lrn.optim.state[lrn.policy.trunk[2].weight]["exp_avg"][:8]
               for lrn in (flushed, plain)]
    assert (moments[0] == 0).all()  # flushed ...
    assert ((moments[1] != 0) & (moments[1].abs() < tiny)).all()  # ... where plain is denormal
    for pf, pp in zip(flushed.policy.parameters(), plain.policy.parameters(), strict=True):
        assert torch.equal(pf, pp)
    assert not torch.equal(flushed.policy.trunk[2].weight, start)  # it learned


def test_target_is_used_and_synced_every_target_update_updates():
    lrn = dqn3(AlgoConfig(hidden=[16], target_update=3, lr=1e-2))
    b = batch()
    before = copy.deepcopy(lrn.state_dict()["target"])
    for k in range(1, 7):
        lrn.update(b)
        target, online = lrn.state_dict()["target"], lrn.policy.state_dict()
        copied = all(torch.equal(online[n], v) for n, v in target.items())
        assert copied == (k % 3 == 0), k  # the 3rd and 6th updates copy the online net
        if k < 3:
            assert all(torch.equal(before[n], v) for n, v in target.items())
    # a resumed learner copies on the same schedule
    again = dqn3(AlgoConfig(hidden=[16], target_update=3, lr=1e-2))
    lrn.update(b)  # the 7th
    again.load_state_dict(copy.deepcopy(lrn.state_dict()))  # as a checkpoint holds it
    for _ in range(2):
        lrn.update(b)
        again.update(b)
    assert all(torch.equal(a, c) for a, c in zip(
        again.state_dict()["target"].values(), lrn.state_dict()["target"].values(), strict=True))


def test_terminal_transitions_do_not_bootstrap():
    lrn = dqn3(AlgoConfig(hidden=[8], gamma=0.9), obs_dim=4)
    b = batch(8, 4)
    b["terminated"][:] = True
    loss, q = lrn.loss(b)
    expected = torch.nn.functional.smooth_l1_loss(
        lrn.policy(b["obs"]).gather(1, b["action"][:, None]).squeeze(1), b["reward"])
    assert loss.item() == pytest.approx(expected.item(), rel=1e-6)


def test_vdn_loss_equals_an_independent_computation():
    """Q_tot = Σ_i Q(o_i, a_i); y = Σ_i r_i + γ (1 − done) Σ_i Q_target(o'_i, argmax over
    mask'_i of Q(o'_i, ·)); the mean Huber loss over the steps, written out step by step."""
    vdn = make_algorithm(AlgoConfig(name="vdn", hidden=[16], gamma=0.9), Dims(5, 4, 3), [0],
                         torch.device("cpu"))
    assert vdn.buffer.unit == "step" and vdn.buffer.batch_size == 128 // 3
    with torch.no_grad():  # a target that differs from the online net
        for p in vdn.loss_module.target_network.parameters():
            p.add_(0.05 * torch.randn_like(p))
    b = steps(8, 3, seed=4, obs_dim=5)
    b["next_mask"][..., 0] = True  # at least one legal move
    b["terminated"][:3] = True
    b["team_reward"] = b["reward"].sum(-1)
    loss, _ = vdn.loss(b)
    online, target = (DuelingQNet(5, 4, [16]) for _ in range(2))
    online.load_state_dict(vdn.state_dict()["qnet"])
    target.load_state_dict(vdn.state_dict()["target"])
    terms = []
    for j in range(8):
        q_tot = sum(online(b["obs"][j, i])[b["action"][j, i]] for i in range(3))
        nxt = 0.0
        for i in range(3):
            q = online(b["next_obs"][j, i]).detach()
            legal = [a for a in range(4) if b["next_mask"][j, i, a]]
            best = max(legal, key=lambda a: q[a].item())
            nxt = nxt + target(b["next_obs"][j, i])[best].detach()
        y = b["reward"][j].sum() + 0.9 * (0.0 if b["terminated"][j].any() else 1.0) * nxt
        d = (q_tot - y).abs()
        terms.append(0.5 * d ** 2 if d < 1 else d - 0.5)
    assert loss.item() == pytest.approx(torch.stack(terms).mean().item(), rel=1e-5)


def steps(n, agents, seed, obs_dim=2):
    """``n`` env steps of ``agents`` agents' transitions, as the collector pushes them."""
    g = torch.Generator().manual_seed(seed)
    shape = (n, agents)
    return {"obs": torch.randn(*shape, obs_dim, generator=g),
            "action": torch.randint(0, 4, shape, generator=g),
            "mask": torch.rand(*shape, 4, generator=g) < 0.5,
            "reward": torch.randn(*shape, generator=g),
            "next_obs": torch.randn(*shape, obs_dim, generator=g),
            "next_mask": torch.rand(*shape, 4, generator=g) < 0.5,
            "terminated": torch.rand(*shape, generator=g) < 0.2}


class FlatRing:
    """The paper's shared buffer written out plainly: a ring of ``capacity`` per-agent
    transitions, sampled uniformly from its slots by a generator seeded ``seed``."""

    def __init__(self, capacity, seed):
        self.capacity, self.cursor, self.size, self.data = capacity, 0, 0, None
        self.gen = torch.Generator().manual_seed(seed)

    def push(self, tr):
        flat = {k: v.reshape(-1, *v.shape[2:]) for k, v in tr.items()}
        if self.data is None:
            self.data = {k: torch.zeros(self.capacity, *v.shape[1:], dtype=v.dtype)
                         for k, v in flat.items()}
        n = flat["obs"].shape[0]
        idx = (torch.arange(n) + self.cursor) % self.capacity
        for k, v in flat.items():
            self.data[k][idx] = v
        self.cursor = (self.cursor + n) % self.capacity
        self.size = min(self.size + n, self.capacity)

    def sample(self, b):
        idx = torch.randint(0, self.size, (b,), generator=self.gen)
        return {k: v[idx] for k, v in self.data.items()}


@pytest.mark.parametrize("capacity", [12, 13, 14])  # a multiple of M = 3 and two not
def test_agent_samples_are_the_flat_rings_through_its_wraps(capacity):
    """Storage in env-step slots, sampling per agent: the same transitions, draw for
    draw, as a flat ring of ``capacity`` per-agent transitions with the same seed."""
    buf = TransitionReplay(capacity, 2, 4, 3, seeds=[7], batch_size=5)
    ring = FlatRing(capacity, 7)
    for step in range(9):  # 2 env steps of 3 agents a push: wraps several times
        tr = steps(2, 3, step)
        buf.extend(tr)
        ring.push(tr)
        assert len(buf) == ring.size
        got, want = buf.sample(), ring.sample(5)
        for k in want:
            assert torch.equal(got[k], want[k]), (step, k)


def test_step_samples_keep_the_agents_and_add_the_team_reward():
    buf = TransitionReplay(12, 2, 4, 3, seeds=[1], batch_size=6, unit="step")
    pushed = [steps(2, 3, s) for s in range(3)]
    for tr in pushed:
        buf.extend(tr)
    td, info = buf.sample(return_info=True)
    assert td.batch_size == (6,) and td["obs"].shape == (6, 3, 2)
    assert info["index"].max() < 4  # the 4 newest steps (capacity 12 / 3 agents)
    every = {k: torch.cat([tr[k] for tr in pushed]) for k in pushed[0]}  # steps 0..5
    for i, slot in enumerate(info["index"].tolist()):
        step = slot + 4 if slot < 2 else slot  # slots 0, 1 rewritten by steps 4, 5
        assert torch.equal(td["obs"][i], every["obs"][step])
    torch.testing.assert_close(td["team_reward"], td["reward"].sum(-1))
    with pytest.raises(NotImplementedError):
        buf.update_priority(info["index"], torch.ones(6))


@pytest.mark.parametrize("unit,agents", [("agent", 1), ("agent", 3), ("step", 3)])
def test_population_replay_equals_each_members_own_buffer(unit, agents):
    """Stacked storage, one push and one gather for all members: the same transitions,
    samples and saved state as each member's own buffer, through the ring's wrap."""
    seeds = [4, 5, 6]
    pop = TransitionReplay(7, 2, 4, agents, seeds, batch_size=5, unit=unit)
    solo = [TransitionReplay(7, 2, 4, agents, [s], batch_size=5, unit=unit) for s in seeds]
    for step in range(6):  # 3 transitions per member a step: wraps twice
        blocks = [steps(3, agents, 10 * step + p) for p in range(3)]
        pop.extend({k: torch.cat([b[k] for b in blocks]) for k in blocks[0]})
        for buf, b in zip(solo, blocks, strict=True):
            buf.extend(b)
        got = pop.sample()
        want = [buf.sample() for buf in solo]
        for k in want[0].keys():
            assert torch.equal(got[k], torch.stack([w[k] for w in want])), k
    for p, buf in enumerate(solo):
        a, b = pop.member_state_dict(p), buf.state_dict()
        assert a["written"] == b["written"] == 18
        assert all(torch.equal(a["data"][k], b["data"][k]) for k in b["data"])
    fresh = TransitionReplay(7, 2, 4, agents, seeds, batch_size=5, unit=unit)  # resumed
    for p, buf in enumerate(solo):
        fresh.load_member(p, buf.state_dict())
    assert all(torch.equal(fresh.data[k], pop.data[k]) for k in pop.data)
    assert torch.equal(fresh.sample()["obs"], pop.sample()["obs"])


@pytest.mark.parametrize("pushes", [2, 7])  # before and after the ring wraps
def test_a_format_1_flat_replay_converts_to_the_same_samples(pushes):
    """A checkpoint of format 1 held a flat ring (data in slot order, cursor, size);
    converted, it samples what the flat ring would have sampled."""
    ring = FlatRing(13, 3)
    for s in range(pushes):
        ring.push(steps(2, 3, s))
    ring.sample(4)  # the generator has moved on
    old = {"data": {k: v[: ring.size].clone() for k, v in ring.data.items()},
           "cursor": ring.cursor, "size": ring.size, "generator": ring.gen.get_state()}
    buf = TransitionReplay(13, 2, 4, 3, seeds=[0], batch_size=4)
    buf.load_state_dict(upgrade_flat_replay(old, 13, 3, total=pushes * 2 * 3))
    for s in range(3):
        got, want = buf.sample(), ring.sample(4)
        assert all(torch.equal(got[k], want[k]) for k in want), s
        buf.extend(steps(2, 3, 100 + s))
        ring.push(steps(2, 3, 100 + s))


@pytest.mark.parametrize("mode", ["flat", "rank"])  # rank's target mask waits a step
def test_n_step_transitions_sum_the_next_rewards(trace_cache, tmp_path, mode):
    """algo.n_step=3 stores r_i + γ r_{i+1} + γ² r_{i+2} with the state 3 steps on (cut
    at the episode's end, where the transition is terminal), beside the one-step
    transitions of the same episodes."""
    from tests.test_train import smoke
    from uabs_rl.training.experiment import Experiment

    args = [f"masking={mode}", "algo.learning_starts=100000", "algo.buffer_size=100000",
            "train.logger=none"]
    one = Experiment(smoke(trace_cache, *args), tmp_path / "one")
    three = Experiment(smoke(trace_cache, *args, "algo.n_step=3"), tmp_path / "three")
    one.collect()
    three.collect()
    steps, m, g = one.params.episode_steps, one.params.n_uabs, one.cfg.algo.gamma
    assert len(one.buffer) == len(three.buffer) == steps * m
    d1 = {k: v[0, :steps] for k, v in one.buffer.data.items()}
    d3 = {k: v[0, :steps] for k, v in three.buffer.data.items()}
    assert torch.equal(d1["obs"], d3["obs"]) and torch.equal(d1["action"], d3["action"])
    for i in range(steps):
        last = min(i + 3, steps) - 1
        want = sum(g ** k * d1["reward"][i + k] for k in range(last - i + 1))
        torch.testing.assert_close(d3["reward"][i], want)
        assert torch.equal(d3["next_obs"][i], d1["next_obs"][last])
        assert torch.equal(d3["terminated"][i], d1["terminated"][last])
        if last == i + 2:  # bootstrapped: the target mask of s_{i+3}
            assert torch.equal(d3["next_mask"][i], d1["next_mask"][i + 2])
    assert d3["terminated"][-3:].all() and not d3["terminated"][:-3].any()
    assert three.learner.loss_module.gamma == pytest.approx(g ** 3)


# ----------------------------------------------------------------------------- QMIX
def qmix(seeds=(0,), **kw):
    return make_algorithm(QmixConfig(hidden=[16], mixing_embed_dim=8, **kw),
                          Dims(5, 4, 3), list(seeds), torch.device("cpu"))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), members=st.sampled_from([1, 2]))
def test_qmix_mixing_is_monotonic_in_every_agent_value(seed, members):
    """The mixing weights are non-negative, so dQ_tot / dQ_i >= 0 for every agent, every
    state and every member (the agents' greedy actions are the team's)."""
    lrn = qmix(seeds=range(seed % 1000, seed % 1000 + members))
    g = torch.Generator().manual_seed(seed)
    for m in lrn.mixers:
        q = (10 * torch.randn(64, 3, 1, generator=g)).requires_grad_()
        state = 10 * torch.randn(64, 15, generator=g)
        (grad,) = torch.autograd.grad(m(q, state).sum(), q)
        assert (grad >= 0).all()
        assert (torch.abs(m.hyper_w_1(state)) >= 0).all()  # the weights QMixer uses


def test_qmix_loss_equals_an_independent_computation():
    """Q_tot = f_s(Q(o_i, a_i)) with f the two-layer mixer whose weights are |W(s)|,
    s the joint observation; y with the target mixer at s' over each agent's best legal
    action; the mean Huber loss, written out step by step."""
    lrn = qmix(gamma=0.9)
    assert lrn.buffer.unit == "step"
    with torch.no_grad():  # targets that differ from the online networks
        for p in [*lrn.loss_module.target_network.parameters(),
                  *lrn.loss_module.target_mixers.parameters()]:
            p.add_(0.05 * torch.randn_like(p))
    b = steps(8, 3, seed=5, obs_dim=5)
    b["next_mask"][..., 0] = True
    b["terminated"][:3] = True
    b["team_reward"] = b["reward"].sum(-1)
    loss, _ = lrn.loss(b)
    st_ = lrn.state_dict()
    online, target = (DuelingQNet(5, 4, [16]) for _ in range(2))
    online.load_state_dict(st_["qnet"])
    target.load_state_dict(st_["target"])

    def f(w, q, s):  # the QMIX mixer, from its state dict
        lin = lambda k, x: x @ w[k + ".weight"].T + w[k + ".bias"]  # noqa: E731
        w1 = lin("hyper_w_1", s).abs().view(3, 8)
        h = torch.nn.functional.elu(q @ w1 + lin("hyper_b_1", s))
        v = lin("V.2", torch.relu(lin("V.0", s)))
        return h @ lin("hyper_w_final", s).abs() + v[0]

    terms = []
    for j in range(8):
        q = torch.stack([online(b["obs"][j, i])[b["action"][j, i]] for i in range(3)])
        q_tot = f(st_["mixer"], q, b["obs"][j].flatten())
        nxt = []
        for i in range(3):
            qn = online(b["next_obs"][j, i]).detach()
            best = max((a for a in range(4) if b["next_mask"][j, i, a]), key=lambda a: qn[a])
            nxt.append(target(b["next_obs"][j, i])[best].detach())
        next_tot = f(st_["target_mixer"], torch.stack(nxt), b["next_obs"][j].flatten())
        y = b["reward"][j].sum() + 0.9 * (0.0 if b["terminated"][j].any() else 1.0) * next_tot
        d = (q_tot - y).abs()
        terms.append(0.5 * d ** 2 if d < 1 else d - 0.5)
    assert loss.item() == pytest.approx(torch.stack(terms).mean().item(), rel=1e-5)


@settings(max_examples=25, deadline=None)
@given(name=st.sampled_from(sorted(ALGORITHMS)), seed=st.integers(0, 2**31 - 1),
       members=st.sampled_from([1, 2]), legal=st.floats(0.05, 0.95))
def test_the_target_never_maximises_over_a_masked_action(name, seed, members, legal):
    """Every algorithm's target at s' takes Q_target at the best action *of the stored
    mask* (a masked action is never the target's argmax, even when it has the highest
    online value), for random states and masks, single runs and populations."""
    m = 3
    lrn = make_algorithm(learner_config(name, hidden=[16]), Dims(5, 4, m),
                         list(range(members)), torch.device("cpu"))
    with torch.no_grad():
        for p in lrn.loss_module.target_network.parameters():
            p.add_(0.1)
    g = torch.Generator().manual_seed(seed)
    lead = (members, 6, m) if members > 1 else (6, m)
    next_obs = torch.randn(*lead, 5, generator=g)
    mask = torch.rand(*lead, 4, generator=g) < legal
    mask[..., int(torch.randint(0, 4, (), generator=g))] = True  # at least one legal
    b = {"obs": torch.randn(*lead, 5, generator=g), "next_obs": next_obs, "next_mask": mask,
         "action": torch.randint(0, 4, lead, generator=g)}
    _, q_next = lrn.loss_module.agent_values(b)
    with torch.no_grad():
        online, target = lrn.policy(next_obs), lrn.loss_module.target_network(next_obs)
    best = online.masked_fill(~mask, -torch.inf).argmax(-1, keepdim=True)
    assert mask.gather(-1, best).all()
    assert torch.equal(q_next, target.gather(-1, best).squeeze(-1))


# ----------------------------------------------------------------------------- prioritized
def test_prioritized_replay_draws_in_proportion_to_priority_and_weights_undo_the_bias():
    """On a small buffer with known priorities p_i: draws in proportion to (p_i + 1e-8)^α
    (the closed form, to Monte-Carlo error), importance weights (p_i / p_min)^-β, and
    with β = 1 the weighted sample mean of any f is its uniform mean over the buffer."""
    alpha, beta = 0.7, 1.0
    rb = TransitionReplay(8, 2, 4, 1, [3], batch_size=4096, unit="agent",
                          priority_alpha=alpha, priority_beta=beta)
    rb.extend(steps(8, 1, seed=0))
    pri = torch.tensor([0.1, 0.5, 1.0, 2.0, 4.0, 0.3, 0.7, 8.0])
    rb.update_priority(torch.arange(8), pri)
    share = (pri + 1e-8) ** alpha
    share = share / share.sum()
    counts = torch.zeros(8)
    f = torch.randn(8)
    num = den = 0.0
    for _ in range(25):
        b = rb.sample()
        counts += torch.bincount(b["index"], minlength=8)
        w = b["weight"]
        p_i = (pri[b["index"]] + 1e-8) ** alpha
        assert torch.allclose(w, (p_i / (pri.min() + 1e-8) ** alpha) ** -beta, rtol=1e-4)
        num += float((w * f[b["index"]]).sum())
        den += float(w.sum())
    n = counts.sum()
    se = (share * (1 - share) / n).sqrt()
    assert ((counts / n - share).abs() <= 5 * se + 1e-4).all()
    assert num / den == pytest.approx(float(f.mean()), abs=0.05)
    # the sampled rows are the transitions at those positions
    b = rb.sample(16)
    assert torch.equal(b["obs"], rb.data["obs"].flatten(1, 2)[0, b["index"]])


def test_new_transitions_get_the_highest_priority_and_uniform_refuses_priorities():
    rb = TransitionReplay(6, 2, 4, 2, [0], batch_size=4, priority_alpha=1.0)
    rb.extend(steps(1, 2, seed=0))
    rb.update_priority(torch.tensor([0, 1]), torch.tensor([3.0, 0.5]))
    rb.extend(steps(1, 2, seed=1))  # positions 2, 3 at the highest priority so far: 3
    assert rb.member_state_dict(0)["priority"].tolist() == pytest.approx(
        [3.0, 0.5, 3.0, 3.0], rel=1e-6)
    with pytest.raises(NotImplementedError, match="uniformly"):
        TransitionReplay(6, 2, 4, 2, [0], batch_size=4).update_priority(
            torch.tensor([0]), torch.tensor([1.0]))


def test_a_prioritized_update_weights_the_loss_and_sets_the_td_errors_as_priorities():
    lrn = make_algorithm(AlgoConfig(hidden=[8], replay="prioritized", batch_size=4,
                                    buffer_size=12, learning_starts=4),
                         Dims(2, 4, 2), [0, 1], torch.device("cpu"))
    tr = steps(6, 2, seed=2)
    tr["next_mask"][..., 0] = True
    lrn.buffer.extend({k: torch.cat([v, v]) for k, v in tr.items()})  # [P·n, M, ...]
    b = lrn.buffer.sample()
    out = lrn.loss_module(b)
    plain = lrn.loss_module(b.exclude("weight"))
    assert "td_error" not in plain.keys()
    q_taken, q_next = lrn.loss_module.agent_values(b)
    y = b["reward"] + lrn.loss_module.gamma * (~b["terminated"]).float() * q_next
    elem = torch.nn.functional.smooth_l1_loss(q_taken, y, reduction="none")
    assert torch.allclose(out["loss"], (b["weight"] * elem).mean(-1))
    lrn.update(b)
    for p in range(2):
        leaves = lrn.buffer.member_state_dict(p)["priority"]
        assert torch.allclose(leaves[b["index"][p]].float(),
                              (out["td_error"][p] + 1e-8) ** 0.6, rtol=1e-5)


def test_prioritized_replay_refuses_the_reference_loss():
    from uabs_rl.training.startup import validate_algo_name
    with pytest.raises(ConfigError, match=r"algo.replay=prioritized needs the fused loss"):
        validate_algo_name(AlgoConfig(loss="torchrl", replay="prioritized"))


def test_a_qmix_update_trains_each_members_mixer_and_the_target_copies_it():
    lrn = qmix(seeds=(0, 1), batch_size=6, buffer_size=30, learning_starts=6,
               target_update=2)
    tr = steps(8, 3, seed=1, obs_dim=5)  # 4 env steps of each of the 2 members
    tr["next_mask"][..., 0] = True
    lrn.buffer.extend(tr)
    before = [copy.deepcopy(m.state_dict()) for m in lrn.mixers]
    for _ in range(2):
        lrn.update(lrn.buffer.sample())
    for p, m in enumerate(lrn.mixers):
        assert all(not torch.equal(v, before[p][k]) for k, v in m.state_dict().items())
        target = lrn.loss_module.target_mixers[p].state_dict()
        assert all(torch.equal(v, target[k]) for k, v in m.state_dict().items())  # update 2
    # a member's state is a single run's: its own mixer, target mixer and Adam
    solo = qmix(seeds=(1,), batch_size=6, buffer_size=30, learning_starts=6)
    solo.load_state_dict(lrn.member_state_dict(1))
    assert all(torch.equal(v, lrn.mixers[1].state_dict()[k])
               for k, v in solo.mixers[0].state_dict().items())


@pytest.mark.parametrize("members", [1, 2])
def test_qmix_clips_each_members_network_and_mixer_by_their_joint_norm(members):
    """algo.grad_clip on QMIX: each member's gradient over its Q-network and its mixer
    together is scaled to norm grad_clip, as clip_grad_norm_ over both in a single run."""
    lrn = qmix(seeds=range(members), grad_clip=1e-3, batch_size=6, buffer_size=30,
               learning_starts=6)
    tr = steps(4 * members, 3, seed=2, obs_dim=5)
    tr["next_mask"][..., 0] = True
    lrn.buffer.extend(tr)
    loss, _ = lrn.loss(lrn.buffer.sample())
    loss.sum().backward()
    lrn.clip_gradients()
    grads = [q.grad for q in lrn.policy.parameters()]
    for p in range(members):
        net = (torch.stack([g.pow(2).sum() for g in grads]) if members == 1 else
               torch.stack([g.pow(2).sum() for g in lrn.policy.member_tensors(grads, p).values()]))
        mixer = torch.stack([q.grad.pow(2).sum() for q in lrn.mixers[p].parameters()])
        assert (net.sum() + mixer.sum()).sqrt().item() == pytest.approx(1e-3, rel=1e-4)


def test_qmix_settings_are_its_own():
    """``algo.mixing_embed_dim`` is QMIX's own setting (QmixConfig, selected with
    algo=qmix): another learner has no such key, ``algo.name`` alone cannot pair one
    learner with another's settings, and a run stored before the split (every learner's
    algo held the key) loads with it only for QMIX."""
    from hydra.errors import ConfigCompositionException

    from uabs_rl.config import compose
    from uabs_rl.runs.checkpoint import config_dict, config_from_checkpoint
    from uabs_rl.training.startup import validate_algo_name

    cfg = compose("config", ["algo=qmix", "algo.mixing_embed_dim=8", "experiment=smoke"])
    assert type(cfg.algo) is QmixConfig and cfg.algo.mixing_embed_dim == 8
    assert cfg.algo.hidden == [32, 32]  # the preset still sizes the network
    with pytest.raises(ConfigCompositionException):
        compose("config", ["algo.mixing_embed_dim=8"])
    for wrong in (AlgoConfig(name="qmix"), QmixConfig(name="dqn3")):
        with pytest.raises(ConfigError, match=r"select the learner with algo="):
            validate_algo_name(wrong)
    stored = config_dict(compose("config"))
    stored["algo"]["mixing_embed_dim"] = 32
    assert type(config_from_checkpoint({"config": stored}).algo) is AlgoConfig
    stored["algo"].update(name="qmix", mixing_embed_dim=16)
    assert config_from_checkpoint({"config": stored}).algo == QmixConfig(mixing_embed_dim=16)
