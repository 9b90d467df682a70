"""The paper's networks in torch: planner MLP (17 -> 9), controller MLP (12 -> 3), merged policy (29 -> 3).

``PlannerMLP`` / ``ControllerMLP`` are the bare layer stacks with the paper's shapes (83,509 and 17,043
parameters). The wrappers add fixed (parameter-free) input/output scaling so they take and return
physical units:
- ``PlannerNet``: the paper's s = T normalisation (t/s, v_bar s^2, dp s, v s^2, a s^3; outputs divided
  back), then a spatial scale m = |(dp', w_v v0', w_a a0', w_v vf', w_a af')| that divides every
  spatial input and multiplies the outputs back, and fixed per-group output weights. Time and space
  scaling are exact symmetries of the minimum-jerk primitive, so the MLP sees T = 1 and unit-size
  boundary states whatever the trajectory. The primitive is also odd in its boundary states (reverse
  dp, v0, a0, vf, af and the trajectory reverses): by default (``odd_symmetric``) the planner returns
  (mlp(z) - mlp(z reversed)) / 2, the MLP's odd part, which cancels the even part of its error (the
  paper-case worst position error of the shipped weights drops from 0.064 m to 0.035 m). Training
  fits the bare MLP (with the paper's sign-flip augmentation); only inference takes the odd part.
- ``ControllerNet``: inputs divided by per-feature spans, thrust output scaled around the hover thrust.
- ``EndToEndPolicy``: planner on inputs 12..28; the controller sees [planner_out - state(0:9), euler].
"""

from __future__ import annotations

import torch
from torch import nn

from policies.frames import GRAVITY_M_S2
from policies.learning.features import CONTROLLER_MASS_KG

_EPS = 1e-6
# Fixed planner scalings (dimensionless in normalised time T = 1). Velocity and acceleration boundary
# values move the position about VEL_WEIGHT and ACC_WEIGHT times as much as a displacement, so the
# spatial scale m weighs them so; OUT_WEIGHTS bring the normalised p, v, a outputs to about unit RMS
# over the paper's data set.
VEL_WEIGHT, ACC_WEIGHT = 0.25, 0.03
OUT_WEIGHTS = [3.0] * 3 + [1.2] * 3 + [0.22] * 3
IN_GAIN = 4.0  # spatial inputs (|.| <= 1, spread about 0.1-0.2 after m) to about unit spread


def _stack(n_in: int, width: int, n_hidden: int, n_out: int) -> nn.Sequential:
    layers: list[nn.Module] = [nn.Linear(n_in, width)]
    for _ in range(n_hidden):
        layers += [nn.Linear(width, width), nn.ReLU()]
    layers.append(nn.Linear(width, n_out))
    return nn.Sequential(*layers)


class PlannerMLP(nn.Sequential):
    """Linear 17->100 (no activation), 8 x (Linear 100->100 + ReLU), Linear 100->9."""

    def __init__(self) -> None:
        super().__init__(*_stack(17, 100, 8, 9))


class ControllerMLP(nn.Sequential):
    """Linear 12->40, 10 x (Linear 40->40 + ReLU), Linear 40->3."""

    def __init__(self) -> None:
        super().__init__(*_stack(12, 40, 10, 3))


def n_parameters(module: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


class PlannerNet(nn.Module):
    """Planner in physical units: (..., 17) raw inputs -> (..., 9) [p - p0 (m), v (m/s), a (m/s^2)]."""

    def __init__(self) -> None:
        super().__init__()
        self.mlp = PlannerMLP()
        one, zero = [1.0], [0.0]
        in_pow = [-1.0, 2.0] + [1.0] * 3 + [2.0] * 3 + [3.0] * 3 + [2.0] * 3 + [3.0] * 3
        self.register_buffer("in_pow", torch.tensor(in_pow), persistent=False)
        self.register_buffer("out_pow", torch.tensor([-1.0] * 3 + [-2.0] * 3 + [-3.0] * 3), persistent=False)
        w_v, w_a = [VEL_WEIGHT] * 3, [ACC_WEIGHT] * 3
        self.register_buffer("in_weight", torch.tensor(one * 5 + w_v + w_a + w_v + w_a), persistent=False)
        self.register_buffer("out_weight", torch.tensor(OUT_WEIGHTS), persistent=False)
        self.register_buffer("in_gain", torch.tensor([2.0] + [IN_GAIN] * 16), persistent=False)
        self.register_buffer("in_bias", torch.tensor([-1.0] + [0.0] * 16), persistent=False)
        self.register_buffer("dp_mask", torch.tensor(zero * 2 + one * 3 + zero * 12), persistent=False)
        self.register_buffer("state_mask", torch.tensor(zero * 2 + one * 15), persistent=False)
        self.register_buffer("time_mask", torch.tensor(one + zero * 16), persistent=False)
        self.register_buffer("spatial_mask", torch.tensor(zero + one * 16), persistent=False)
        # reversing the boundary states reverses the MLP's inputs but t/T and v_bar
        self.register_buffer("odd_flip", torch.tensor(one * 2 + [-1.0] * 15), persistent=False)
        self.register_buffer("odd_half", torch.tensor([[0.5], [-0.5]]), persistent=False)
        self.odd_symmetric = True  # inference returns the MLP's odd part (see the module docstring)

    def normalise(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """MLP inputs (..., 17), the time scale s = T (..., 1) and the spatial scale m (..., 1).

        Written with masks and powers instead of slices: fewer ONNX nodes, faster one-sample inference.
        """
        dp2 = (x * self.dp_mask) ** 2
        s = torch.sqrt(dp2.sum(-1, keepdim=True) + _EPS**2) / torch.clamp(x[..., 1:2], min=_EPS)
        z = x * torch.pow(s, self.in_pow) * self.in_weight  # t/s, v_bar s^2, dp s, w_v v s^2, w_a a s^3
        m = torch.sqrt(((z * self.state_mask) ** 2).sum(-1, keepdim=True) + _EPS**2)
        # every input but t is spatial and is divided by m (v_bar' = s^2 v_bar = |dp'| included); then a
        # fixed affine map to about unit spread: t/T in [0, 1] -> [-1, 1], spatial inputs x IN_GAIN
        return z * (self.time_mask + self.spatial_mask / m) * self.in_gain + self.in_bias, s, m

    def denormalise(self, out: torch.Tensor, s: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
        """Physical outputs from normalised MLP outputs."""
        return out * (m * torch.pow(s, self.out_pow) / self.out_weight)

    def normalise_outputs(self, y: torch.Tensor, s: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
        """Physical outputs (labels) in the MLP's output units (the inverse of ``denormalise``)."""
        return y * (torch.pow(s, -self.out_pow) * self.out_weight / m)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        inp, s, m = self.normalise(x)
        if self.odd_symmetric:
            out = (self.mlp(torch.stack([inp, inp * self.odd_flip], -2)) * self.odd_half).sum(-2)
        else:
            out = self.mlp(inp)
        return self.denormalise(out, s, m)


class ControllerNet(nn.Module):
    """Controller in physical units: (..., 12) -> (..., 3) [roll (rad), pitch (rad), thrust (N)]."""

    def __init__(self) -> None:
        super().__init__()
        self.mlp = ControllerMLP()
        span = torch.tensor([1.0] * 3 + [2.0] * 3 + [10.0] * 3 + [3.14159265] * 3)
        hover_n = CONTROLLER_MASS_KG * GRAVITY_M_S2
        self.register_buffer("in_scale", 1.0 / span, persistent=False)
        self.register_buffer("out_scale", torch.tensor([1.0, 1.0, hover_n]), persistent=False)
        self.register_buffer("out_offset", torch.tensor([0.0, 0.0, hover_n]), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.mlp(x * self.in_scale) * self.out_scale + self.out_offset


class EndToEndPolicy(nn.Module):
    """The merged policy: (..., 29) -> (..., 3) [roll (rad), pitch (rad), thrust (N)]."""

    def __init__(self, planner: PlannerNet, controller: ControllerNet) -> None:
        super().__init__()
        self.planner, self.controller = planner, controller

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        plan = self.planner(x[..., 12:29])
        return self.controller(torch.cat([plan - x[..., 0:9], x[..., 9:12]], -1))
