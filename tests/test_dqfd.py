"""The teacher-guided 3DQN (``algo=dqfd``): the teacher's label is the move the
clairvoyant planner flies given the moves the higher-ranked UABS took; the large-margin
term by hand; a network trained on it alone learns the labels; with λ_E = 0 the run is
the 3DQN's, record for record; bad settings and a buffer of another learner refused."""

from __future__ import annotations

import json

import pytest
import torch
from tensordict import TensorDict

from tests.conftest import compose_cfg
from tests.test_planner import eval_env
from tests.test_train import records, smoke
from uabs_rl.algorithms import Dims, make_algorithm
from uabs_rl.algorithms.dqfd import TEACHER, margin_loss
from uabs_rl.algorithms.replay import TransitionReplay
from uabs_rl.config import ConfigError, DqfdConfig
from uabs_rl.env.uabs_env import ACTION, MASK, OBS
from uabs_rl.evaluation.planner import JITTER, PlannerScore
from uabs_rl.safety.make import make_selector
from uabs_rl.safety.rules import ACTION_VALUE
from uabs_rl.training.resume import run
from uabs_rl.training.startup import validate_run
from uabs_rl.training.teacher import NO_LABEL, Teacher


@pytest.mark.parametrize("mode", ["flat", "rank"])
def test_the_label_is_the_move_the_clairvoyant_planner_flies(trace_cache, mode):
    """Scores: the planner's before its tie-break. Label: under the mask that applied to
    the chosen moves, the move the masked selector takes on the teacher's scores (under
    rank masks, given the higher-ranked moves), over an episode's states."""
    cfg, env = eval_env(trace_cache, f"masking={mode}", windows=3)
    selector = make_selector(env)
    teacher = Teacher(env.base_env, 3)
    gen = torch.Generator().manual_seed(5)
    planner = PlannerScore(env.base_env, 3, gen)
    td = env.reset()
    for _ in range(env.base_env.params.episode_steps):
        scores = teacher.scores(td)
        draw = torch.Generator().manual_seed(5)
        draw.set_state(gen.get_state())
        jitter = torch.rand(scores.shape, generator=draw)
        planner(td)
        assert torch.equal(td.get(ACTION_VALUE), scores + JITTER * jitter)
        td.set(ACTION_VALUE, scores)  # the selector flies the teacher's own moves
        selector(td)
        label = Teacher.label(scores, td.get(MASK))
        assert td.get(MASK).any(-1).all()  # the selector leaves every agent a move
        assert torch.equal(label, td.get(ACTION))
        td = env.step(td)["next"]


@pytest.mark.parametrize("mode", ["flat", "rank"])  # rank's transitions wait a step
def test_each_stored_transition_holds_the_label_of_its_own_state(trace_cache, tmp_path, mode):
    """A teacher whose scores are a function of the observation: every stored transition
    (n-step returns, rank's deferred push) holds the label of its own observation under
    its own applied mask, not a neighbour's."""
    from uabs_rl.training.experiment import Experiment

    class ObsTeacher:
        def scores(self, td):
            return td.get(OBS)[..., :4].clone()

    exp = Experiment(smoke(trace_cache, "algo=dqfd", f"masking={mode}", "algo.n_step=3",
                           "algo.learning_starts=100000", "algo.buffer_size=100000",
                           "train.logger=none"), tmp_path)
    exp.collector.teacher = ObsTeacher()
    exp.collect()
    steps = exp.params.episode_steps
    d = {k: v[0, :steps] for k, v in exp.buffer.data.items()}
    want = d["obs"][..., :4].masked_fill(~d["mask"], -torch.inf).argmax(-1)
    assert torch.equal(d[TEACHER], want)
    assert len(set(d[TEACHER].flatten().tolist())) > 1  # not one label everywhere
    assert not torch.equal(d[TEACHER], d["action"])  # ε-greedy strays from the teacher


def test_no_legal_move_gets_no_label_and_the_best_set_keeps_ties():
    scores = torch.tensor([[[3.0, 1.0, 2.0, 0.0], [1.0, 2.0, 3.0, 4.0]]])
    mask = torch.tensor([[[False, True, True, False], [False, False, False, False]]])
    assert Teacher.label(scores, mask).tolist() == [[2, NO_LABEL]]
    tied = torch.tensor([[[2.0, 1.0, 2.0, 5.0]]])  # the best, 5, is not allowed
    allowed = torch.tensor([[[True, True, True, False]]])
    assert Teacher.best_moves(tied, allowed).tolist() == [[[True, False, True, False]]]
    assert not Teacher.best_moves(scores, mask)[0, 1].any()


def test_margin_loss_by_hand():
    q = torch.tensor([[1.0, 4.0, 2.0, 0.0],    # label 0: max(1, 4+m, 2+m) - 1 = 3 + m
                      [5.0, 1.0, 9.0, 2.0],    # label 0, move 2 illegal: max(5, 1+m, 2+m) - 5
                      [0.0, 0.0, 0.0, 0.0]])   # no label: left out
    label = torch.tensor([0, 0, NO_LABEL])
    legal = torch.tensor([[True, True, True, True], [True, True, False, True],
                          [False, False, False, False]])
    m = 2.0
    got = margin_loss(q, label, legal, m)
    assert got.item() == pytest.approx(((3 + m) + (max(5, 1 + m, 2 + m) - 5)) / 2)
    # one per member of a population, each over its own labelled items
    both = margin_loss(torch.stack([q, q + 1]), torch.stack([label, label]),
                       torch.stack([legal, legal]), m)
    assert both.tolist() == pytest.approx([got.item(), got.item()])
    # the teacher's move ahead by the margin: nothing to learn
    q_ok = torch.tensor([[9.0, 4.0, 2.0, 0.0]])
    assert margin_loss(q_ok, torch.tensor([0]), torch.ones(1, 4, dtype=torch.bool),
                       m).item() == 0.0


def test_the_margin_term_alone_teaches_the_labels():
    """λ_E large, rewards zero: the greedy legal move becomes the teacher's (a label that
    is a fixed function of the observation), the agreement the loss reports near 1."""
    torch.manual_seed(0)
    dims = Dims(obs_dim=8, n_actions=4, n_agents=2)
    lrn = make_algorithm(DqfdConfig(hidden=[32], lr=3e-3, batch_size=64, buffer_size=512,
                                    imitation_weight=10.0, teacher_margin=1.0),
                         dims, [0], torch.device("cpu"))
    n = 256
    obs = torch.randn(n, 2, 8)
    legal = torch.rand(n, 2, 4) > 0.2
    legal[..., 0] = True
    label = obs[..., :4].masked_fill(~legal, -torch.inf).argmax(-1)
    lrn.buffer.extend(TensorDict({
        "obs": obs, "action": torch.randint(0, 4, (n, 2)), "mask": legal,
        "reward": torch.zeros(n, 2), "next_obs": obs, "next_mask": legal,
        "terminated": torch.ones(n, 2, dtype=torch.bool), TEACHER: label}, batch_size=[n]))
    for _ in range(400):
        lrn.update(lrn.buffer.sample())
    out = lrn.loss_module(lrn.buffer.sample(256))
    assert out.get("agreement").item() > 0.9
    with torch.no_grad():
        greedy = lrn.policy(obs).masked_fill(~legal, -torch.inf).argmax(-1)
    assert (greedy == label).float().mean().item() > 0.9


def test_without_imitation_the_run_is_the_3dqns(trace_cache, tmp_path):
    """λ_E = 0: the teacher labels every state but draws no random number and the loss
    adds nothing: every record of the 3DQN's run, and its network."""
    args = ["train.logger=none", "train.trajectory_images=false", "train.episodes=4",
            "train.eval_every=2"]
    run(smoke(trace_cache, *args), tmp_path / "dqn3")
    run(smoke(trace_cache, *args, "algo=dqfd", "algo.imitation_weight=0"), tmp_path / "dqfd")
    assert records(tmp_path / "dqfd") == records(tmp_path / "dqn3")
    a, b = (torch.load(tmp_path / d / "checkpoints" / "last.pt", weights_only=False)
            for d in ("dqfd", "dqn3"))
    assert all(torch.equal(a["learner"]["qnet"][k], v) for k, v in b["learner"]["qnet"].items())
    assert json.loads(json.dumps(a["config"]["algo"]))["name"] == "dqfd"


@pytest.mark.parametrize("override,key", [("algo.teacher_horizon=0", "algo.teacher_horizon"),
                                          ("algo.teacher_horizon=21", "algo.teacher_horizon"),
                                          ("algo.teacher_margin=-1", "algo.teacher_margin"),
                                          ("algo.imitation_weight=-1", "algo.imitation_weight")])
def test_bad_teacher_settings_are_refused_naming_the_key(trace_cache, override, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        validate_run(smoke(trace_cache, "algo=dqfd", override))


def test_a_buffer_without_labels_is_refused():
    plain = TransitionReplay(40, 3, 4, 2, [0], 4)
    labelled = TransitionReplay(40, 3, 4, 2, [0], 4, extra={TEACHER: ((), torch.long)})
    with pytest.raises(ValueError, match="teacher"):
        labelled.load_state_dict(plain.state_dict())


def test_a_family_of_cities_is_refused(trace_cache):
    """The teacher plans over one area; a family's rows each have their own."""
    cfg = compose_cfg("config", ["experiment=generalist", "algo=dqfd",
                                 f"traces.cache_dir={trace_cache}"])
    with pytest.raises(ConfigError, match=r"^family must be empty with algo=dqfd"):
        validate_run(cfg)
