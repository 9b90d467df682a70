"""Inference-only equivalents of the trained networks, with the fixed scalings folded into the Linears.

What ``export`` writes to ONNX: the same functions as ``PlannerNet``, ``ControllerNet`` and
``EndToEndPolicy`` (exactly in real arithmetic; in float64 the outputs agree to about 1e-13), with fewer
graph nodes, which is what one-sample latency on onnxruntime pays for:
- consecutive Linears with no activation between them (each stack's first two) are merged into one;
- the fixed input gain/offset and output weights are folded into the first and last Linear;
- the normalisation uses slices instead of mask products;
- the planner's odd part (``PlannerNet.odd_symmetric``) runs the stack once on two stacked rows;
- optionally (``hidden_dtype=torch.float32``) the Linear+ReLU layers between the first input and the
  last Linear run in float32 while the normalisation, the last Linear of each stack and everything in
  physical units stay in float64: onnxruntime's float64 matrix products cost about three times its
  float32 ones, and the hidden activations are O(1) numbers where float32 is accurate to 1e-7
  relative, whereas the physical outputs reach hundreds of m.
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from policies.learning.networks import _EPS, ControllerNet, EndToEndPolicy, PlannerNet


def _linear(weight: torch.Tensor, bias: torch.Tensor) -> nn.Linear:
    lin = nn.Linear(weight.shape[1], weight.shape[0], dtype=weight.dtype)
    with torch.no_grad():
        lin.weight.copy_(weight)
        lin.bias.copy_(bias)
    return lin


def fold_stack(mlp: nn.Sequential, in_gain: torch.Tensor, in_bias: torch.Tensor, out_gain: torch.Tensor,
               out_bias: torch.Tensor) -> nn.Sequential:
    """``x -> out_gain * mlp(in_gain * x + in_bias) + out_bias`` as one stack (computed in float64):
    the first two Linears (no activation between them) merged, the affine maps folded in."""
    layers = [copy.deepcopy(m).double() if isinstance(m, nn.Linear) else m for m in mlp]
    first, second = layers[0], layers[1]
    if not (isinstance(first, nn.Linear) and isinstance(second, nn.Linear)):
        raise ValueError("fold_stack expects a stack starting with two Linears")
    g, b0 = in_gain.double(), in_bias.double()
    w0 = first.weight.detach() * g  # W0 diag(g)
    c0 = first.weight.detach() @ b0 + first.bias.detach()
    merged = _linear(second.weight.detach() @ w0, second.weight.detach() @ c0 + second.bias.detach())
    last = layers[-1]
    og, ob = out_gain.double(), out_bias.double()
    folded_last = _linear(last.weight.detach() * og[:, None], last.bias.detach() * og + ob)
    out = nn.Sequential(merged, *layers[2:-1], folded_last)
    return out.double()


class MixedStack(nn.Module):
    """A folded stack with its hidden layers in ``hidden_dtype`` and its last Linear in float64."""

    def __init__(self, folded: nn.Sequential, hidden_dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        self.hidden_dtype = hidden_dtype
        self.body = folded[:-1].to(hidden_dtype)
        self.last = folded[-1].double()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.body(x.to(self.hidden_dtype))
        return self.last(h.to(torch.float64))


class DeployPlanner(nn.Module):
    """``PlannerNet`` for inference: (..., 17) -> (..., 9) in float64, the same function, fewer
    operations (hidden layers in ``hidden_dtype``)."""

    def __init__(self, net: PlannerNet, hidden_dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        zero = torch.zeros(9, dtype=torch.float64)
        folded = fold_stack(net.mlp, net.in_gain, net.in_bias, 1.0 / net.out_weight.double(), zero)
        self.mlp = MixedStack(folded, hidden_dtype)
        self.register_buffer("in_pow", net.in_pow.double().clone(), persistent=False)
        self.register_buffer("in_weight", net.in_weight.double().clone(), persistent=False)
        self.register_buffer("out_pow", net.out_pow.double().clone(), persistent=False)
        self.odd_symmetric = net.odd_symmetric
        self.register_buffer("odd_flip", net.odd_flip.double().clone(), persistent=False)
        self.register_buffer("odd_half", net.odd_half.double().clone(), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        dp = x[..., 2:5]
        s = torch.sqrt((dp * dp).sum(-1, keepdim=True) + _EPS**2) / torch.clamp(x[..., 1:2], min=_EPS)
        z = x * (torch.pow(s, self.in_pow) * self.in_weight)
        st = z[..., 2:17]
        m = torch.sqrt((st * st).sum(-1, keepdim=True) + _EPS**2)
        inp = torch.cat([z[..., 0:1], z[..., 1:17] / m], -1)
        if self.odd_symmetric:
            out = (self.mlp(torch.stack([inp, inp * self.odd_flip], -2)) * self.odd_half).sum(-2)
        else:
            out = self.mlp(inp)
        return out * (m * torch.pow(s, self.out_pow))


class DeployController(nn.Module):
    """``ControllerNet`` for inference: (..., 12) -> (..., 3) in float64 (hidden layers in
    ``hidden_dtype``)."""

    def __init__(self, net: ControllerNet, hidden_dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        folded = fold_stack(net.mlp, net.in_scale, torch.zeros(12), net.out_scale, net.out_offset)
        self.mlp = MixedStack(folded, hidden_dtype)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.mlp(x)


class DeployEndToEnd(nn.Module):
    """``EndToEndPolicy`` for inference: (..., 29) -> (..., 3)."""

    def __init__(self, policy: EndToEndPolicy, hidden_dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        self.planner = DeployPlanner(policy.planner, hidden_dtype)
        self.controller = DeployController(policy.controller, hidden_dtype)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        plan = self.planner(x[..., 12:29])
        return self.controller(torch.cat([plan - x[..., 0:9], x[..., 9:12]], -1))


def deploy_module(model: nn.Module, hidden_dtype: torch.dtype = torch.float64) -> nn.Module:
    """The folded inference module (float64 in and out, hidden layers in ``hidden_dtype``) for a
    ``PlannerNet``, ``ControllerNet`` or ``EndToEndPolicy``."""
    if isinstance(model, PlannerNet):
        return DeployPlanner(model, hidden_dtype).eval()
    if isinstance(model, ControllerNet):
        return DeployController(model, hidden_dtype).eval()
    if isinstance(model, EndToEndPolicy):
        return DeployEndToEnd(model, hidden_dtype).eval()
    raise TypeError(f"no inference form for {type(model).__name__}")
