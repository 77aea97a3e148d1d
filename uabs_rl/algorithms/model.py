"""The shared dueling Q-network: one set of parameters for every agent."""

from __future__ import annotations

import torch
from torch import nn


class DuelingQNet(nn.Module):
    """Q(o, ·) = V(o) + A(o, ·) − mean_a A(o, a) over an MLP trunk.

    Maps the last dimension, so ``[..., M, obs_dim] -> [..., M, n_actions]``: applied to
    all agents at once it shares its parameters across them (parameter sharing)."""

    def __init__(self, obs_dim: int, n_actions: int, hidden: list[int] | tuple[int, ...]):
        super().__init__()
        layers: list[nn.Module] = []
        width = obs_dim
        for h in hidden:
            layers += [nn.Linear(width, h), nn.ReLU()]
            width = h
        self.trunk = nn.Sequential(*layers)
        self.value = nn.Linear(width, 1)
        self.advantage = nn.Linear(width, n_actions)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        z = self.trunk(obs)
        a = self.advantage(z)
        return self.value(z) + a - a.mean(-1, keepdim=True)


def linear_layers(net: DuelingQNet) -> list[nn.Linear]:
    """The affine layers of ``net`` in order: trunk, value head, advantage head."""
    return [*(m for m in net.trunk if isinstance(m, nn.Linear)), net.value, net.advantage]


class StackedQNet(nn.Module):
    """P dueling Q-networks of one shape, their parameters stacked ``[P, ...]``: the
    networks of a population (``train.population``), evaluated in one batched matrix
    product per layer.

    Input ``[P·k, ..., obs_dim]`` (member ``p``'s rows first-dimension block ``p``, as the
    population's env lays them out) or ``[P, B, obs_dim]`` (a replay batch per member);
    output the same with ``n_actions`` last. Member ``p`` computes what
    ``DuelingQNet`` computes with the weights of :meth:`member_state_dict` ``(p)``, up
    to the rounding of batched matrix products (float32 rounding, 1e-7 to 1e-6 relative)."""

    def __init__(self, nets: list[DuelingQNet]):
        super().__init__()
        self.members = len(nets)
        layers = [linear_layers(n) for n in nets]
        self.n_trunk = len(layers[0]) - 2
        # the trunk's weights stored transposed, [P, in, out], so each product reads them
        # as they lie: the update of a population of three paper networks about 10 %
        # faster than with [P, out, in] weights read through a transposed view
        # (train_bench.py, in turns), and bit-identical (MKL's products round the same
        # either way here). The value and advantage heads as one product, out = 1 + A,
        # their weights [P, out, in] as nn.Linear's, read through a transposed view:
        # MKL's product with 1 + 4 outputs is slow from an [in, out] matrix (3 members,
        # 128 rows, 2 threads: 65-67 µs against 21, the weights' gradient 71-72 µs
        # against 22-24): a population's update about 10 % faster, a whole run about as
        # much; it rounds otherwise (docs/performance.md, "A population's heads")
        self.weight = nn.ParameterList()
        self.bias = nn.ParameterList()
        for i in range(self.n_trunk):
            self.weight.append(nn.Parameter(torch.stack([ls[i].weight.detach().t()
                                                         for ls in layers]).contiguous()))
            self.bias.append(nn.Parameter(torch.stack([ls[i].bias.detach() for ls in layers])))
        self.weight.append(nn.Parameter(torch.stack([
            torch.cat([ls[-2].weight.detach(), ls[-1].weight.detach()])
            for ls in layers]).contiguous()))
        self.bias.append(nn.Parameter(torch.stack([
            torch.cat([ls[-2].bias.detach(), ls[-1].bias.detach()]) for ls in layers])))
        self.keys = list(nets[0].state_dict())  # a member's DuelingQNet state-dict keys

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        shape = obs.shape
        z = obs.reshape(self.members, -1, shape[-1])
        # plain lists: slicing a ParameterList builds a new module on every call (it was
        # a tenth of a population's training time)
        ws, bs = list(self.weight), list(self.bias)
        for w, b in zip(ws[:-1], bs[:-1], strict=True):
            z = torch.relu(member_products(b, z, w))
        h = member_products(bs[-1], z, ws[-1].mT)
        v, a = h[..., :1], h[..., 1:]
        q = v + a - a.mean(-1, keepdim=True)
        return q.reshape(*shape[:-1], q.shape[-1])

    def member_tensors(self, tensors: list[torch.Tensor], p: int) -> dict[str, torch.Tensor]:
        """Member ``p``'s slice of per-parameter tensors laid out like this net's
        parameters (the parameters, their gradients or optimiser moments), keyed as a
        ``DuelingQNet`` state dict."""
        n = self.n_trunk
        ws, bs = tensors[: n + 1], tensors[n + 1:]
        out = []
        for w, b in zip(ws[:-1], bs[:-1], strict=True):
            out += [w[p].t(), b[p]]
        out += [ws[-1][p, :1], bs[-1][p, :1], ws[-1][p, 1:], bs[-1][p, 1:]]
        return {k: v.detach().clone(memory_format=torch.contiguous_format)
                for k, v in zip(self.keys, out, strict=True)}

    def member_state_dict(self, p: int) -> dict[str, torch.Tensor]:
        """Member ``p`` as a ``DuelingQNet`` state dict (what a solo run's checkpoint holds)."""
        return self.member_tensors(list(self.parameters()), p)

    @torch.no_grad()
    def write_member(self, tensors: list[torch.Tensor], p: int,
                     values: dict[str, torch.Tensor]) -> None:
        """The inverse of :meth:`member_tensors`: write member ``p``'s ``values`` (keyed
        as a ``DuelingQNet`` state dict) into ``tensors``."""
        n = self.n_trunk
        vals = [values[k] for k in self.keys]
        ws, bs = tensors[: n + 1], tensors[n + 1:]
        for i in range(n):
            ws[i][p].copy_(vals[2 * i].t())
            bs[i][p].copy_(vals[2 * i + 1])
        ws[n][p].copy_(torch.cat([vals[2 * n], vals[2 * n + 2]]))
        bs[n][p].copy_(torch.cat([vals[2 * n + 1], vals[2 * n + 3]]))

    def load_member(self, p: int, state: dict[str, torch.Tensor]) -> None:
        """Set member ``p`` from a ``DuelingQNet`` state dict."""
        self.write_member(list(self.parameters()), p, state)


# A member's product gets threads of its own (when the members do not share out evenly
# among the threads: ``member_products``) from this many multiply-adds, with at least 64
# rows and 256 inputs: the paper network's 256 x 256 layer on a replay batch (8.4M) or a
# decision over 64 envs, not its first layer, its heads or a decision's few rows. Within
# these shapes a member's product alone was measured equal bit for bit to its slice of the
# batched one (this machine's MKL, 64 to 1024 rows, 2 to 4 threads, 1 to 5 members);
# outside them it was not always (an 18-wide input's gradient over 1024 rows at 3 threads,
# a 7-row product)
OWN_PRODUCT_MACS = 1 << 22
OWN_PRODUCT_ROWS = 64
OWN_PRODUCT_INPUTS = 256


@torch.compiler.assume_constant_result
def _threads() -> int:
    # read while tracing and kept in the program as a constant: a program is compiled
    # once per thread count (``uabs_rl.env._compile.AheadOfTime``'s key; a plain
    # ``torch.compile`` guards on the count too), and the grouping it sets changes the
    # speed, not the values
    return torch.get_num_threads()


def batched_members(members: int, rows: int, inputs: int, outputs: int) -> int:
    """How many of ``members`` products of ``[rows, inputs] @ [inputs, outputs]``
    :func:`member_products` runs as one batched product at this thread count (the rest
    one by one); ``members`` where it runs them all batched, as ``baddbmm`` does."""
    batched = members - members % _threads()
    if (rows < OWN_PRODUCT_ROWS or inputs < OWN_PRODUCT_INPUTS
            or rows * inputs * outputs < OWN_PRODUCT_MACS):
        return members
    return batched


def _grouped(batched: int, members: int, product) -> torch.Tensor:
    """``product(s)`` over the members ``[:batched]`` at once, then over each one left,
    concatenated in member order."""
    parts = [product(slice(0, batched))] if batched else []
    parts += [product(slice(p, p + 1)) for p in range(batched, members)]
    return torch.cat(parts)


class _MemberProducts(torch.autograd.Function):
    """``baddbmm(b[:, None], z, w)`` and its gradients, each product grouped by
    :func:`_grouped`. The backward is written out because, left to autograd (slices and
    a concatenation), torch 2.13's Inductor compiled a wrong weight gradient for the
    batched members inside the whole update program (two Adam steps off after one
    update; eager was right, and so was the layer compiled alone):
    ``tests/test_compiled_update.py`` compares the compiled population update with the
    ungrouped one bit for bit, and fails on autograd's version."""

    @staticmethod
    def forward(b, z, w, batched):
        return _grouped(batched, z.shape[0], lambda s: torch.baddbmm(b[s, None], z[s], w[s]))

    @staticmethod
    def setup_context(ctx, inputs, output):
        _, z, w, batched = inputs
        ctx.save_for_backward(z, w)
        ctx.batched = batched

    @staticmethod
    def backward(ctx, g):
        z, w = ctx.saved_tensors
        n = z.shape[0]
        gz = (_grouped(ctx.batched, n, lambda s: torch.bmm(g[s], w[s].transpose(1, 2)))
              if ctx.needs_input_grad[1] else None)
        gw = _grouped(ctx.batched, n, lambda s: torch.bmm(z[s].transpose(1, 2), g[s]))
        return g.sum(1), gz, gw, None


def member_products(b: torch.Tensor, z: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """``baddbmm(b[:, None], z, w)``: each member's affine layer ``z[p] @ w[p] + b[p]``,
    computed so that every thread works.

    PyTorch's CPU batched product gives each thread whole members: three members on two
    threads take two rounds, as four do (the paper network's 256 x 256 layer on a
    128-row replay batch: 340 µs for three members, 342 for four, 173 for two). So the
    largest multiple of the thread count runs batched and each member left over as a
    product of its own on every thread (267 µs for three). Small products (where the
    extra calls cost more than the idle thread, and where a member's product alone may
    round otherwise: ``OWN_PRODUCT_*``), one thread, and members that share out evenly
    run as one batched product, as before. Values and gradients are then those of the
    batched product bit for bit (measured, not guaranteed by MKL: the test of the
    population's update checks it on the machine that runs it)."""
    members, rows, width = z.shape
    batched = batched_members(members, rows, width, w.shape[-1])
    # (a GPU's batched product is not shared out by member among CPU threads)
    if batched == members or z.device.type != "cpu":
        return torch.baddbmm(b[:, None], z, w)
    return _MemberProducts.apply(b, z, w, batched)
