"""The shipped `e2e_rl` network: present, small, its ONNX file the shipped state dict's function (the
parity the other networks have), near the imitation policy it was fine-tuned from on the states it
flies, and flown by the `e2e_rl` pilot of the onboard program through onnxruntime."""

from __future__ import annotations

import numpy as np
import torch

from hil.rl.env import CrossGapCore, EnvConfig
from policies.learning.export import EXPORT_DTYPES, EXPORT_HIDDEN, inference_module, load_e2e
from policies.learning.learned_pilots import EndToEndPilot
from policies.learning.onnx_runtime import load_shipped, shipped_path
from policies.onboard.pilots import make_pilot, pilot_names

torch.set_num_threads(2)


def _inputs(n: int = 10_000) -> np.ndarray:
    """The 29 inputs over the env's range: states near an approach, planner inputs of short crossings."""
    rng = np.random.default_rng(3)
    x = np.empty((n, 29))
    x[:, 0:3] = rng.uniform(-1, 4, (n, 3))
    x[:, 3:6] = rng.uniform(-4, 4, (n, 3))
    x[:, 6:9] = rng.uniform(-10, 10, (n, 3))
    x[:, 9:12] = rng.uniform(-1.2, 1.2, (n, 3))
    x[:, 12] = rng.uniform(0, 3, n)
    dp = rng.uniform(-3, 3, (n, 3))
    x[:, 14:17] = dp
    x[:, 13] = np.linalg.norm(dp, axis=1) / rng.uniform(1.1, 4.1, n)
    x[:, 17:29] = rng.uniform(-4, 4, (n, 12))
    return x


def test_shipped_e2e_rl_onnx_matches_its_state_dict_within_1e_5():
    path = shipped_path("e2e_rl")
    assert path.stat().st_size < 1_000_000
    net = load_e2e(path.with_suffix(".pt"))
    x = _inputs()
    with torch.no_grad():
        ref = inference_module(net, EXPORT_DTYPES["e2e"], EXPORT_HIDDEN["e2e"])(
            torch.as_tensor(x, dtype=EXPORT_DTYPES["e2e"])).double().numpy()
    out = load_shipped("e2e_rl").predict(x)
    assert np.abs(out - ref).max() <= 1e-5


def test_e2e_rl_is_a_fine_tuning_of_the_imitation_policy():
    # on what it flies (the environment's states along imitation-flown crossings): changed, and near
    core = CrossGapCore(16, EnvConfig(pool_size=16, seed=9))
    imitation_net, seen = load_shipped("e2e"), []
    for _ in range(250):
        obs = core.observations().astype(np.float64)
        seen.append(obs)
        core.step(imitation_net.run(obs))
    x = np.concatenate(seen)
    rl, imitation = load_shipped("e2e_rl").predict(x), imitation_net.predict(x)
    assert not np.array_equal(rl, imitation)  # it was trained
    diff = np.median(np.abs(rl - imitation), axis=0)
    assert diff[0] < 0.02 and diff[1] < 0.02 and diff[2] < 0.2  # rad, rad, N: it stays near its start


def test_the_e2e_rl_pilot_flies_the_shipped_network():
    assert "e2e_rl" in pilot_names()
    pilot = make_pilot("e2e_rl")
    assert isinstance(pilot, EndToEndPilot)
    assert pilot.flies["approach"] == "end-to-end network (e2e_rl)"
    x = _inputs(5)
    np.testing.assert_array_equal(pilot.model.predict(x), load_shipped("e2e_rl").predict(x))
