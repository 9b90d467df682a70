"""Reinforcement learning of the gap crossing: the batched environment `CrossGap-v0` (`hil.rl.env`), the
randomised crossings it flies (`hil.rl.scenarios`), the TRPO actor initialised from the imitation policy
(`hil.rl.policy`) and its training (`hil.rl.train`). Needs the 'learn' extra (gymnasium, stable-baselines3,
sb3-contrib, torch). Importing this package registers `CrossGap-v0` with gymnasium."""

from __future__ import annotations

import gymnasium as gym

ENV_ID = "CrossGap-v0"

if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point="hil.rl.env:CrossGapEnv")
