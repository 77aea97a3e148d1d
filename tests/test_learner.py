"""The 3DQN update: fused and TorchRL losses agree; the network can learn."""

from __future__ import annotations

import contextlib
import copy

import pytest
import torch

from uabs_rl import learner as learner_module
from uabs_rl.config import AlgoConfig
from uabs_rl.learner import DQNLearner
from uabs_rl.model import DuelingQNet
from uabs_rl.replay import PopulationReplay, ReplayBuffer


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


def test_fused_and_torchrl_losses_agree():
    torch.manual_seed(0)
    net = DuelingQNet(18, 4, [32, 32])
    fused = DQNLearner(copy.deepcopy(net), AlgoConfig(loss="fused", gamma=0.8), 4)
    trl = DQNLearner(copy.deepcopy(net), AlgoConfig(loss="torchrl", gamma=0.8), 4)
    # make the target differ from the online net, identically in both learners
    with torch.no_grad():
        for p in fused.target.parameters():
            p.add_(0.1)
    # through the resume path: a learner state whose target differs from the online net
    trl.load_state_dict({**trl.state_dict(), "target": fused.target.state_dict()})
    b = batch()
    lf, _ = fused.fused_loss(b)
    lt, _ = trl.torchrl_loss(b)
    assert lf.item() == pytest.approx(lt.item(), rel=1e-5)
    lf.backward()
    lt.backward()
    for pf, pt in zip(fused.qnet.parameters(), trl.qnet.parameters(), strict=True):
        assert torch.allclose(pf.grad, pt.grad, atol=1e-6)


def test_flushing_denormal_adam_moments_keeps_parameters_bit_identical(monkeypatch):
    """Dead ReLU units get zero gradients, so their Adam moments decay into denormals;
    the update flushes those to zero (for speed) and must leave every parameter exactly
    as the unflushed update does."""
    torch.manual_seed(0)
    net = DuelingQNet(18, 4, [32, 32])
    with torch.no_grad():
        net.trunk[2].bias[:8] = -1e3  # units 0-7 of the second layer never fire
    flushed = DQNLearner(copy.deepcopy(net), AlgoConfig(lr=1e-3), 4)
    plain = DQNLearner(copy.deepcopy(net), AlgoConfig(lr=1e-3), 4)
    for lrn in (flushed, plain):
        lrn.update(batch(seed=99))
        st = lrn.optim.state[lrn.qnet.trunk[2].weight]  # the dead units' rows
        st["exp_avg"][:8], st["exp_avg_sq"][:8] = 1e-39, 1e-41  # decayed moments
    tiny = torch.finfo(torch.float32).tiny
    for i in range(30):
        b = batch(seed=i)
        flushed.update(b)
        with monkeypatch.context() as m:
            m.setattr(learner_module, "flush_denormals", contextlib.nullcontext)
            plain.update(b)
    moments = [lrn.optim.state[lrn.qnet.trunk[2].weight]["exp_avg"][:8]
               for lrn in (flushed, plain)]
    assert (moments[0] == 0).all()  # flushed ...
    assert ((moments[1] != 0) & (moments[1].abs() < tiny)).all()  # ... where plain is denormal
    for pf, pp in zip(flushed.qnet.parameters(), plain.qnet.parameters(), strict=True):
        assert torch.equal(pf, pp)
    assert not torch.equal(flushed.qnet.trunk[2].weight, net.trunk[2].weight)  # it learned


def test_target_is_used_and_synced():
    net = DuelingQNet(18, 4, [16])
    lrn = DQNLearner(net, AlgoConfig(target_update=3, lr=1e-2), 4)
    b = batch()
    before = copy.deepcopy(lrn.target.state_dict())
    lrn.update(b)
    lrn.update(b)
    assert all(torch.equal(before[k], v) for k, v in lrn.target.state_dict().items())
    lrn.update(b)  # the third update copies the online net
    assert all(torch.equal(lrn.qnet.state_dict()[k], v)
               for k, v in lrn.target.state_dict().items())


def test_terminal_transitions_do_not_bootstrap():
    net = DuelingQNet(4, 4, [8])
    lrn = DQNLearner(net, AlgoConfig(gamma=0.9), 4)
    b = batch(8, 4)
    b["terminated"][:] = True
    loss, q = lrn.fused_loss(b)
    expected = torch.nn.functional.smooth_l1_loss(
        net(b["obs"]).gather(1, b["action"][:, None]).squeeze(1), b["reward"])
    assert loss.item() == pytest.approx(expected.item(), rel=1e-6)


def test_replay_buffer_ring_and_state():
    buf = ReplayBuffer(5, 2, 4, seed=0)
    for i in range(3):
        n = 2
        buf.push(obs=torch.full((n, 2), float(i)), action=torch.zeros(n, dtype=torch.long),
                 mask=torch.ones(n, 4, dtype=torch.bool), reward=torch.full((n,), float(i)),
                 next_obs=torch.zeros(n, 2), next_mask=torch.ones(n, 4, dtype=torch.bool),
                 terminated=torch.zeros(n, dtype=torch.bool))
    assert len(buf) == 5 and buf.cursor == 1
    assert buf.data["reward"].tolist() == [2.0, 0.0, 1.0, 1.0, 2.0]  # slot 0 overwritten
    other = ReplayBuffer(5, 2, 4)
    other.load_state_dict(buf.state_dict())
    assert torch.equal(other.sample(7)["reward"], buf.sample(7)["reward"])


def transitions(n, seed):
    g = torch.Generator().manual_seed(seed)
    return {"obs": torch.randn(n, 2, generator=g), "action": torch.randint(0, 4, (n,), generator=g),
            "mask": torch.rand(n, 4, generator=g) < 0.5, "reward": torch.randn(n, generator=g),
            "next_obs": torch.randn(n, 2, generator=g),
            "next_mask": torch.rand(n, 4, generator=g) < 0.5,
            "terminated": torch.rand(n, generator=g) < 0.2}


def test_population_replay_equals_each_members_own_buffer():
    """Stacked storage, one push and one gather for all members: the same transitions,
    samples and saved state as each member's solo buffer, through the ring's wrap."""
    seeds = [4, 5, 6]
    pop = PopulationReplay(7, 2, 4, "cpu", seeds)
    solo = [ReplayBuffer(7, 2, 4, seed=s) for s in seeds]
    for step in range(6):  # 3 transitions per member a step: wraps twice
        blocks = [transitions(3, 10 * step + p) for p in range(3)]
        pop.push(**{k: torch.cat([b[k] for b in blocks]) for k in blocks[0]})
        for buf, b in zip(solo, blocks, strict=True):
            buf.push(**b)
        got = pop.sample(5)
        want = [buf.sample(5) for buf in solo]
        for k in got:
            assert torch.equal(got[k], torch.stack([w[k] for w in want])), k
    for pb, buf in zip(pop.buffers, solo, strict=True):
        a, b = pb.state_dict(), buf.state_dict()
        assert (a["cursor"], a["size"]) == (b["cursor"], b["size"]) == (4, 7)
        assert all(torch.equal(a["data"][k], b["data"][k]) for k in b["data"])
    fresh = PopulationReplay(7, 2, 4, "cpu", seeds)  # a resumed population's buffers
    for pb, buf in zip(fresh.buffers, solo, strict=True):
        pb.load_state_dict(buf.state_dict())
    assert all(torch.equal(fresh.data[k], pop.data[k]) for k in pop.data)


@pytest.mark.parametrize("mode", ["flat", "rank"])  # rank's target mask waits a step
def test_n_step_transitions_sum_the_next_rewards(trace_cache, tmp_path, mode):
    """algo.n_step=3 stores r_i + γ r_{i+1} + γ² r_{i+2} with the state 3 steps on (cut
    at the episode's end, where the transition is terminal), beside the one-step
    transitions of the same episodes."""
    from tests.test_train import smoke
    from uabs_rl.experiment import Experiment

    args = [f"masking={mode}", "algo.learning_starts=100000", "algo.buffer_size=100000",
            "train.logger=none"]
    one = Experiment(smoke(trace_cache, *args), tmp_path / "one")
    three = Experiment(smoke(trace_cache, *args, "algo.n_step=3"), tmp_path / "three")
    one.collect()
    three.collect()
    steps, m, g = one.params.episode_steps, one.params.n_uabs, one.cfg.algo.gamma
    assert len(one.buffer) == len(three.buffer) == steps * m
    d1 = {k: v[: steps * m].view(steps, m, *v.shape[1:]) for k, v in one.buffer.data.items()}
    d3 = {k: v[: steps * m].view(steps, m, *v.shape[1:]) for k, v in three.buffer.data.items()}
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
    assert three.learner.gamma == pytest.approx(g ** 3)
