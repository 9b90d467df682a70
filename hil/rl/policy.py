"""The TRPO policy: the actor's mean is the shipped imitation policy itself (`EndToEndPolicy`: planner and
controller networks with their fixed normalisation and the planner's odd part), a state-independent
Gaussian with a small initial standard deviation around it, and a separate critic (its own MLP on the
observation scaled to about unit spread). Before the first update the actor's mean action is exactly
the imitation policy's."""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.policies import ActorCriticPolicy
from torch import nn

from policies.learning.export import load_controller, load_planner
from policies.learning.networks import EndToEndPolicy

#: a typical size of each of the 29 inputs (m, m/s, m/s^2, rad, s, ...), for the critic's input scaling
OBS_SPAN = np.array([3.0] * 3 + [3.0] * 3 + [10.0] * 3 + [1.0] * 3 + [3.0, 3.0] + [3.0] * 3 + [3.0] * 6
                    + [10.0] * 6, dtype=np.float32)


def imitation_policy(weights_dir: str | Path | None = None) -> EndToEndPolicy:
    """The shipped imitation policy (``planner.pt`` and ``controller.pt`` of ``weights_dir``, by default
    policies/weights) as one torch module: (..., 29) -> (..., 3) [roll (rad), pitch (rad), thrust (N)]."""
    d = Path(weights_dir) if weights_dir is not None else Path(str(resources.files("policies") / "weights"))
    return EndToEndPolicy(load_planner(d / "planner.pt"), load_controller(d / "controller.pt"))


class _Extractor(nn.Module):
    """Latents of SB3's policy: the actor's is the imitation policy's action (3,), the critic's an MLP's.
    (TRPO leaves every parameter whose name holds "value" out of the actor's update: the critic's do.)"""

    def __init__(self, actor: EndToEndPolicy, hidden: tuple[int, ...]) -> None:
        super().__init__()
        self.actor = actor
        layers: list[nn.Module] = []
        width = len(OBS_SPAN)
        for h in hidden:
            layers += [nn.Linear(width, h), nn.Tanh()]
            width = h
        self.value_mlp = nn.Sequential(*layers)
        self.register_buffer("value_in_scale", torch.from_numpy(1.0 / OBS_SPAN), persistent=False)
        self.latent_dim_pi, self.latent_dim_vf = 3, width

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.forward_actor(features), self.forward_critic(features)

    def forward_actor(self, features: torch.Tensor) -> torch.Tensor:
        return self.actor(features)

    def forward_critic(self, features: torch.Tensor) -> torch.Tensor:
        return self.value_mlp(features * self.value_in_scale)


class ImitationInitPolicy(ActorCriticPolicy):
    """SB3 actor-critic whose actor mean is `imitation_policy()` (see the module doc). Extra keyword
    arguments: ``log_std_init_per_action`` (3,) the initial log standard deviations of roll, pitch (rad)
    and thrust (N); ``critic_hidden`` the critic's layer widths; ``weights_dir`` the imitation weights;
    ``train_planner`` whether TRPO also steps the planner network's weights (default: the controller's
    only, the planner part held as imitated)."""

    def __init__(self, *args: Any, log_std_init_per_action: tuple[float, float, float] = (-4.0, -4.0, -2.0),
                 critic_hidden: tuple[int, ...] = (256, 256), weights_dir: str | None = None,
                 train_planner: bool = False, **kwargs: Any) -> None:
        self._log_std0 = tuple(float(v) for v in log_std_init_per_action)
        self._train_planner = bool(train_planner)
        self._critic_hidden = tuple(int(h) for h in critic_hidden)
        self._weights_dir = weights_dir
        kwargs["ortho_init"] = False  # keep the imitation weights as they are
        kwargs.setdefault("share_features_extractor", False)
        super().__init__(*args, **kwargs)

    def _build_mlp_extractor(self) -> None:
        self.mlp_extractor = _Extractor(imitation_policy(self._weights_dir), self._critic_hidden)
        self.mlp_extractor.actor.planner.requires_grad_(self._train_planner)

    def _build(self, lr_schedule: Any) -> None:
        super()._build(lr_schedule)
        self.action_net = nn.Identity()  # the actor's latent is its mean action
        with torch.no_grad():
            self.log_std.copy_(torch.tensor(self._log_std0))
        self.optimizer = self.optimizer_class(self.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(log_std_init_per_action=self._log_std0, critic_hidden=self._critic_hidden,
                    weights_dir=self._weights_dir, train_planner=self._train_planner)
        return data

    def named_parameters(self, *args: Any, **kwargs: Any) -> Any:
        """The trainable parameters only: a held planner (``train_planner`` False) is part of the actor's
        function but no parameter of it (TRPO differentiates its objective by every parameter listed)."""
        return ((name, p) for name, p in super().named_parameters(*args, **kwargs) if p.requires_grad)

    def actor_module(self) -> EndToEndPolicy:
        """The actor's mean as the `EndToEndPolicy` it is (what ships as ``e2e_rl``)."""
        return self.mlp_extractor.actor
