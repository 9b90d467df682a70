"""The paper's losses: weighted planner MSE (w = 4, 2, 1), controller thrust error + 57.3 x geodesic angle."""

from __future__ import annotations

import torch

PLANNER_WEIGHTS = (4.0, 2.0, 1.0)  # position, velocity, acceleration
THRUST_WEIGHT, ANGLE_WEIGHT = 1.0, 57.3  # per N, per rad


def planner_loss(pred: torch.Tensor, label: torch.Tensor,
                 weights: tuple[float, float, float] = PLANNER_WEIGHTS) -> torch.Tensor:
    """Mean over the batch of w_p |dp|^2 + w_v |dv|^2 + w_a |da|^2 on (B, 9) tensors."""
    err = (pred - label) ** 2
    wp, wv, wa = weights
    return (wp * err[..., 0:3].sum(-1) + wv * err[..., 3:6].sum(-1) + wa * err[..., 6:9].sum(-1)).mean()


def paper_rotation(roll: torch.Tensor, pitch: torch.Tensor) -> torch.Tensor:
    """The paper's eq. (1): R_d(phi, theta) = Rx(phi)^T Ry(theta)^T (world -> body, yaw 0); (..., 3, 3).

    The product is taken as written in the paper's first line; its printed result has sin(phi) cos(theta)
    where the product gives sin(phi) sin(theta) (entry 2, 1), a typo (that matrix is no rotation).
    """
    cr, sr, cp, sp = torch.cos(roll), torch.sin(roll), torch.cos(pitch), torch.sin(pitch)
    zero = torch.zeros_like(roll)
    rows = [torch.stack([cp, zero, -sp], -1), torch.stack([sr * sp, cr, sr * cp], -1),
            torch.stack([cr * sp, -sr, cr * cp], -1)]
    return torch.stack(rows, -2)


def geodesic_angle(roll_a: torch.Tensor, pitch_a: torch.Tensor, roll_b: torch.Tensor,
                   pitch_b: torch.Tensor) -> torch.Tensor:
    """Angle (rad) of R_d(a) R_d(b)^T, i.e. acos((tr - 1) / 2), computed as atan2(sin, cos) so its
    gradient stays finite at zero."""
    rel = paper_rotation(roll_a, pitch_a) @ paper_rotation(roll_b, pitch_b).transpose(-1, -2)
    cos = (rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0
    skew = torch.stack([rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0],
                        rel[..., 1, 0] - rel[..., 0, 1]], -1)
    sin = torch.sqrt((skew * skew).sum(-1) + 1e-14) / 2.0
    return torch.atan2(sin, cos)


def controller_loss(pred: torch.Tensor, label: torch.Tensor) -> torch.Tensor:
    """Mean of |thrust error| (N) + 57.3 x geodesic angle (rad) on (B, 3) [roll, pitch, thrust]."""
    angle = geodesic_angle(label[..., 0], label[..., 1], pred[..., 0], pred[..., 1])
    return (THRUST_WEIGHT * (pred[..., 2] - label[..., 2]).abs() + ANGLE_WEIGHT * angle).mean()
