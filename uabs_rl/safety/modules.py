"""The TorchRL modules that apply a masking rule (:mod:`uabs_rl.safety.rules`).

A rank mask needs the higher-ranked agents' *chosen* actions, so it cannot be computed
before the policy acts: the rule is applied in two places,

* :class:`SafetyTransform`, the env side: the rule's ``write`` after every reset and
  step;
* :class:`MaskedActionSelector`, the policy's last module: the rule's ``choose``;

and :class:`DirectEnv` steps the same env without TensorDicts for the training loop.
Nothing here tells masking modes apart.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.envs import TransformedEnv
from torchrl.envs.transforms import Transform

from uabs_rl.env._compile import compiled_or_eager
from uabs_rl.env.uabs_env import ACTION, FALLBACK, MASK, OBS, Outputs, direct_outputs
from uabs_rl.safety.rules import ACTION_VALUE, MaskingRule, uniforms


class SafetyTransform(Transform):
    """Applies a rule's :meth:`~MaskingRule.write` to every reset and step output."""

    def __init__(self, rule: MaskingRule):
        super().__init__(in_keys=[], out_keys=[])
        self.rule = rule

    def _call(self, td: TensorDictBase) -> TensorDictBase:
        self.rule.write(td)
        return td

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase):
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec):
        agents = observation_spec["agents"]
        e, m = agents.shape
        for name, spec in self.rule.specs(e, m, observation_spec.device).items():
            agents[name] = spec
        return observation_spec


def env_rule(env: TransformedEnv) -> MaskingRule:
    """The masking rule of an env built by :func:`uabs_rl.safety.make.make_env`: the rule of its
    :class:`SafetyTransform`, which the selector and the learner's target mask share."""
    transforms = getattr(env.transform, "transforms", [env.transform])
    for t in transforms:
        if isinstance(t, SafetyTransform):
            return t.rule
    raise TypeError(f"no SafetyTransform in {env.transform!r}: build the env with "
                    f"uabs_rl.safety.make.make_env, which adds the masking rule's transform")


class DirectEnv:
    """The training env without TensorDicts: ``reset()`` and ``step(td)`` of the
    ``TransformedEnv(UABSEnv, SafetyTransform)`` that :func:`uabs_rl.safety.make.make_env`
    builds, returning :class:`~uabs_rl.env.uabs_env.Outputs` (a flat dict keyed as the
    TensorDict), entry for entry equal to ``env.reset()`` and ``env.step(td)["next"]``
    (``tests/test_masking.py``). It runs the env's step math and the rule's :meth:`write`
    and skips what TorchRL does on every call (building nested TensorDicts, shape and
    done checks, the ``"next"`` entry). The training loop steps through it, and so does
    the evaluation of a Q-network's greedy policy
    (:meth:`uabs_rl.evaluation.evaluator.Evaluator.direct_rollout`, which returns what
    ``env.rollout`` returns); every other policy a user flies keeps the TorchRL env.
    With ``one_program`` False, a compiled step runs the env's own compiled step math
    (the program ``env.step`` calls) and the rule's write eagerly, sharing that program
    with the TorchRL env instead of compiling a second one for its shapes.

    Why a second path: measured on the 2-core development CPU
    (``benchmarks/env_bench.py --n-envs 1``, the paper's env), ``env.step`` takes
    0.51 ms where the step math alone takes 0.36 ms; the 0.14 ms more, at every env
    step, would be 8 % of the main job's training step (1.7 ms,
    ``benchmarks/train_bench.py``), above the 5 % that keeping two paths needs."""

    def __init__(self, env: TransformedEnv, one_program: bool = True):
        if not isinstance(env.transform, SafetyTransform):
            raise TypeError(f"DirectEnv needs the env of make_env(..., spec_mask=False): a "
                            f"UABSEnv with one SafetyTransform, got {env.transform!r}")
        self.base, self.rule = env.base_env, env.transform.rule
        # compiled (the env's compile_step), the step math and the rule's write are one
        # program: a compiled program's call costs about as much as the rule's few eager
        # ops (sort, cdist) it saves calling separately
        self._step = (compiled_or_eager(self._written_step, "the env step", self.base.device)
                      if self.base.compile_step and one_program else None)
        self._decided: dict[tuple[int, int, bool], Callable] = {}  # act_and_step programs

    def reset(self) -> Outputs:
        out = self.base.reset_direct()
        self.rule.write(out)
        return out

    def step(self, td: Outputs | TensorDictBase) -> Outputs:
        """The outputs after the action ``td`` holds (with the selector's fallback
        flags)."""
        action, fallback = td.get(ACTION), td.get(FALLBACK, None)
        if self._step is None:
            out = self.base.step_direct(action, fallback)
            self.rule.write(out)
            return out
        b = self.base
        return Outputs(self._step(b.state, action, b.veh_pos, b.veh_present, b.rng, fallback))

    def act_and_step(self, selector: MaskedActionSelector, qnet: nn.Module,
                     td: Outputs | TensorDictBase,
                     target: bool = False) -> tuple[torch.Tensor | None, Outputs]:
        """``selector.act(qnet, td, target)`` then :meth:`step`: the training loop's
        decision at ``td`` (written into it) and the outputs after it, with the target
        mask ``act`` returns. Compiled (the env's ``compile_step`` and the selector's
        ``compile``), the two are one program: one call per env step instead of two,
        each call's fixed cost (entering it, its output wrapping) being of the order of
        the small ops it runs. Results are those of the two calls, bit for bit
        (``tests/test_masking.py``)."""
        if self._step is None or not selector.compile:
            target_mask = selector.act(qnet, td, target)
            return target_mask, self.step(td)
        key = (id(selector), id(qnet), target)
        if key not in self._decided:
            self._decided[key] = compiled_or_eager(
                self._decided_step(selector._act_program(qnet, target)),
                "the action selection and env step", self.base.device, ahead=True)
        mask = td.get(MASK)
        u = uniforms(mask.shape[:-1], selector.generator, mask.device)
        b = self.base
        q, target_mask, action, applied, fallback, out = self._decided[key](
            b.state, b.veh_pos, b.veh_present, b.rng, td.get(FALLBACK, None), td.get(OBS),
            mask, *(td.get(k) for k in selector.rule.choice_keys), selector.eps, u)
        selector._write(td.set(ACTION_VALUE, q), action, applied, fallback)
        return target_mask, Outputs(out)

    def _decided_step(self, act: Callable) -> Callable:
        def program(state, veh_pos, veh_present, gen, prior_fallback, obs, mask, *extra):
            q, target_mask, action, applied, fallback = act(obs, mask, *extra)
            if fallback is None:  # as MaskedActionSelector._write fills it in
                fallback = prior_fallback if prior_fallback is not None else torch.zeros(
                    applied.shape[:-1], dtype=torch.bool, device=applied.device)
            out = self._written_step(state, action, veh_pos, veh_present, gen, fallback)
            return q, target_mask, action, applied, fallback, out

        return program

    def _written_step(self, state, action, veh_pos, veh_present, gen, fallback):
        out = direct_outputs(self.base.math.step(state, action, veh_pos, veh_present, gen,
                                                 fallback))
        self.rule.write(out)
        return dict(out)


class MaskedActionSelector(TensorDictModuleBase):
    """ε-greedy action choice under a rule's masks: the policy's last module.

    Reads ``("agents", "action_value")`` when present (absent: a uniformly random legal
    policy), the mask and the rule's :attr:`~MaskingRule.choice_keys`. Writes the
    action, the mask that applied and the fallback flags. ``eps`` is a buffer the
    trainer anneals; ``generator`` makes exploration reproducible."""

    def __init__(self, rule: MaskingRule, eps: float = 0.0,
                 generator: torch.Generator | None = None, compile: bool = False):
        super().__init__()
        self.rule, self.generator = rule, generator
        self.in_keys = [ACTION_VALUE, MASK, *rule.choice_keys]
        self.out_keys = [("agents", "action"), MASK, FALLBACK]
        self.register_buffer("eps", torch.tensor(float(eps)))
        self.compile = compile
        self._choose = compiled_or_eager(rule.choose, "the action selection",
                                          rule.moves.device) if compile \
            else rule.choose
        self._acts: dict[tuple[int, bool], Callable] = {}  # compiled act programs

    def forward(self, td: TensorDictBase | Outputs) -> TensorDictBase | Outputs:
        mask = td.get(MASK)
        u = uniforms(mask.shape[:-1], self.generator, mask.device)
        action, mask, fallback = self._choose(
            td.get(ACTION_VALUE, None), mask, *(td.get(k) for k in self.rule.choice_keys),
            eps=self.eps, u=u)
        return self._write(td, action, mask, fallback)

    @staticmethod
    def _write(td, action: torch.Tensor, mask: torch.Tensor,
               fallback: torch.Tensor | None) -> TensorDictBase | Outputs:
        """The choice into ``td``: the action, the mask that applied and the fallback
        flags (the rule's; else those ``td`` holds; else none)."""
        if fallback is None:
            fallback = td.get(FALLBACK, None)
            if fallback is None:
                fallback = torch.zeros(mask.shape[:-1], dtype=torch.bool, device=mask.device)
        td.set(("agents", "action"), action)
        td.set(MASK, mask)
        td.set(FALLBACK, fallback)
        return td

    def act(self, qnet: nn.Module, td: TensorDictBase | Outputs,
            target: bool = False) -> torch.Tensor | None:
        """The training loop's decision at ``td``: the Q-values of ``qnet`` (written under
        ``("agents", "action_value")``), then, with ``target``, the rule's target mask at
        this state (returned; None otherwise), then the ε-greedy choice (:meth:`forward`).
        Compiled (``compile``), the three are one program: the network's forward, the
        greedy choice the target mask needs and the ε-greedy one with one call."""
        if not self.compile:
            with torch.no_grad():
                td.set(ACTION_VALUE, qnet(td.get(OBS)))
            mask = self.target_mask(td) if target else None
            self(td)
            return mask
        key = (id(qnet), target)
        if key not in self._acts:
            self._acts[key] = compiled_or_eager(self._act_program(qnet, target),
                                                "the action selection", self.rule.moves.device)
        mask = td.get(MASK)
        u = uniforms(mask.shape[:-1], self.generator, mask.device)
        q, target_mask, action, applied, fallback = self._acts[key](
            td.get(OBS), mask, *(td.get(k) for k in self.rule.choice_keys), self.eps, u)
        self._write(td.set(ACTION_VALUE, q), action, applied, fallback)
        return target_mask

    def _act_program(self, qnet: nn.Module, target: bool) -> Callable:
        rule = self.rule

        def program(obs, mask, *extra):
            *extra, eps, u = extra
            with torch.no_grad():
                q = qnet(obs)
                target_mask = rule.target_mask_of(q, mask, *extra) if target else None
                action, applied, fallback = rule.choose(q, mask, *extra, eps=eps, u=u)
            return q, target_mask, action, applied, fallback

        return program

    def target_mask(self, td: TensorDictBase | Outputs) -> torch.Tensor:
        """The rule's double-DQN target mask at ``td`` (s' with its Q-values), computed
        with this selector's (possibly compiled) choice."""
        return self.rule.target_mask(td, self._choose)
