"""Networks and losses: the paper's shapes and parameter counts, the planner's normalisation as an exact
symmetry, the merged policy's wiring, and the paper's loss definitions."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from policies.frames import euler_to_matrix
from policies.learning.data import PlannerDataConfig, PlannerSampler, planner_data
from policies.learning.losses import controller_loss, geodesic_angle, paper_rotation, planner_loss
from policies.learning.networks import (
    ControllerMLP,
    ControllerNet,
    EndToEndPolicy,
    PlannerMLP,
    PlannerNet,
    n_parameters,
)

torch.set_num_threads(2)


def _planner_inputs(n: int = 2000) -> torch.Tensor:
    cfg = PlannerDataConfig(n_trajectories=200, samples_per_trajectory=100, seed=7)
    data = planner_data(cfg, use_cache=False)
    x, _ = PlannerSampler(data, np.random.default_rng(0)).batch(n)
    return torch.as_tensor(x, dtype=torch.float64)


def test_parameter_counts_and_layers_match_the_paper():
    assert n_parameters(PlannerMLP()) == 83_509
    assert n_parameters(ControllerMLP()) == 17_043
    planner = PlannerMLP()
    linears = [m for m in planner if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(17, 100)] + [(100, 100)] * 8 + [(100, 9)]
    assert not isinstance(planner[1], torch.nn.ReLU)  # the first layer has no activation
    assert sum(isinstance(m, torch.nn.ReLU) for m in planner) == 8
    ctrl = [m for m in ControllerMLP() if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in ctrl] == [(12, 40)] + [(40, 40)] * 10 + [(40, 3)]
    # the wrappers add no trainable parameters
    assert n_parameters(PlannerNet()) == 83_509 and n_parameters(ControllerNet()) == 17_043


def test_planner_normalisation_makes_the_net_respect_time_and_space_scaling():
    torch.manual_seed(0)
    net = PlannerNet().double().eval()
    x = _planner_inputs()
    with torch.no_grad():
        y = net(x)
        k = 3.7  # spatial scaling: v_bar, boundary states and outputs scale by k, times unchanged
        xs = x.clone()
        xs[:, 1:] *= k
        np.testing.assert_allclose(net(xs).numpy(), k * y.numpy(), rtol=1e-9, atol=1e-9)
        c = 0.6  # time scaling t -> c t with positions fixed: v_bar / c, v / c, a / c^2
        xt = x.clone()
        xt[:, 0] *= c
        xt[:, 1] /= c
        xt[:, 5:8] /= c
        xt[:, 11:14] /= c
        xt[:, 8:11] /= c * c
        xt[:, 14:17] /= c * c
        yt = net(xt).numpy()
        np.testing.assert_allclose(yt[:, 0:3], y[:, 0:3].numpy(), rtol=1e-8, atol=1e-8)
        np.testing.assert_allclose(yt[:, 3:6], y[:, 3:6].numpy() / c, rtol=1e-8, atol=1e-8)
        np.testing.assert_allclose(yt[:, 6:9], y[:, 6:9].numpy() / c**2, rtol=1e-8, atol=1e-8)
        inp, s, m = net.normalise(x)
        np.testing.assert_allclose(inp[:, 0].numpy(), 2 * x[:, 0].numpy() / s[:, 0].numpy() - 1)  # t / T
        assert torch.all(inp[:, 0].abs() <= 1 + 1e-12) and torch.all(inp[:, 1:].abs() <= 4 + 1e-12)
        np.testing.assert_allclose(net.normalise_outputs(net.denormalise(y, s, m), s, m).numpy(), y.numpy())


def test_end_to_end_policy_feeds_the_controller_the_planner_error():
    torch.manual_seed(1)
    planner, controller = PlannerNet().double(), ControllerNet().double()
    policy = EndToEndPolicy(planner, controller)
    x17 = _planner_inputs(64)
    state = torch.randn(64, 12, dtype=torch.float64)
    with torch.no_grad():
        out = policy(torch.cat([state, x17], 1))
        expected = controller(torch.cat([planner(x17) - state[:, 0:9], state[:, 9:12]], 1))
    assert out.shape == (64, 3)
    np.testing.assert_allclose(out.numpy(), expected.numpy(), rtol=1e-12)


def test_controller_net_output_is_centred_on_hover_thrust():
    net = ControllerNet()
    with torch.no_grad():
        for p in net.mlp.parameters():
            p.zero_()
        y = net(torch.randn(5, 12))
    np.testing.assert_allclose(y.numpy(), np.tile([0.0, 0.0, 0.9 * 9.8], (5, 1)), rtol=1e-6)


def test_planner_loss_weights_position_velocity_acceleration_4_2_1():
    label = torch.zeros(2, 9)
    for col, weight in ((0, 4.0), (4, 2.0), (8, 1.0)):
        pred = torch.zeros(2, 9)
        pred[:, col] = 1.0
        assert float(planner_loss(pred, label)) == pytest.approx(weight)


def test_paper_rotation_is_the_transpose_of_the_zyx_attitude():
    roll, pitch = torch.tensor([0.3, -1.0]), torch.tensor([-0.2, 0.7])
    expected = np.swapaxes(euler_to_matrix(roll.numpy(), pitch.numpy(), 0.0), -1, -2)
    np.testing.assert_allclose(paper_rotation(roll, pitch).numpy(), expected, atol=1e-6)


def test_geodesic_angle_and_controller_loss():
    r = torch.tensor([0.2, -0.4], dtype=torch.float64)
    p = torch.tensor([0.1, 0.5], dtype=torch.float64)
    assert geodesic_angle(r, p, r, p).abs().max() < 1e-6
    np.testing.assert_allclose(geodesic_angle(r, p, r, p + 0.25).numpy(), 0.25, rtol=1e-9)
    # pure roll difference at zero pitch is that angle
    zero = torch.zeros(1, dtype=torch.float64)
    assert float(geodesic_angle(zero, zero, zero + 1.0, zero)) == pytest.approx(1.0)
    label = torch.tensor([[0.1, 0.2, 9.0]], dtype=torch.float64)
    pred = label.clone()
    pred[0, 2] = 7.0
    assert float(controller_loss(pred, label)) == pytest.approx(2.0, abs=1e-5)
    pred = label.clone()
    pred[0, 1] += math.radians(1.0)
    assert float(controller_loss(pred, label)) == pytest.approx(57.3 * math.radians(1.0), rel=1e-6)
    pred = label.clone().requires_grad_(True)  # gradient at zero error stays finite
    controller_loss(pred, label).backward()
    assert torch.isfinite(pred.grad).all()
