"""`CrossGap-v0`: the gap crossing as an RL environment, batched natively over N vehicles.

One process, N vehicles as rows of arrays: the emulator's own code flies them (`BatchPhysics` rows, the
FC's inner loop, physics and the world's compiled check in one parallel call,
`emulator.loops.batched_steps.fly_targets`), nothing re-written.

Episode (as in the paper's release): a hover at a drawn start facing the crossing, the onboard program's
plan of a drawn gap (`hil.rl.scenarios`), then the approach and the traverse; it ends at approach time
+ 2 x the traverse's time to the gap centre (truncated), or on a collision with the wall, the floor or
the lab's faces (terminated; the world is checked once a control step, or after every physics step with
``EnvConfig.world_check = "physics"``, as the runner does).

Action (3,) at the control rate (100 Hz): the N3 attitude-thrust setpoint as the end-to-end policy gives
it, roll and pitch (rad, ZYX of body FLU -> world ENU relative to the plan's yaw) and thrust (N, for the
policy's 0.9 kg vehicle: scaled by the vehicle's mass / 0.9 kg, as the `e2e` pilot does). The FC takes it
as a command through the link would arrive: NED Euler angles with the plan's heading, the tilt limited and
the thrust clipped to 0..100 %. As the `e2e` pilot, the policy flies the approach; the traverse is flown
by the expert controller on the plan's reference (the action is then ignored).

Observation (29,): the end-to-end policy's inputs exactly as the `e2e` pilot builds them
(`policies.learning.learned_pilots`): the state predicted ``lead_s`` ahead (the onboard program's control
lead), acceleration input zero (the pilot's default), mission time + lead. The state is the true one by
default; with ``EnvConfig.link`` (a `hil.rl.link_observe.LinkModel`) it is what the onboard program
would estimate from the mocap frames as the radio delivers them (noise, latency, jitter, loss, its
filter's prediction; the latest frame's attitude), so that the policy sees what it will see through the
link. (The first observation of an episode is the true state's either way: the filter has settled on
the hover by then.)

Reward: the release's (`RewardWeights()`; the paper's text: `RewardWeights.paper()`), each term kept
apart (`hil.rl.reward`, compiled over the rows).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv

from emulator.loops.batched_steps import fly_targets
from emulator.physics.native import BatchPhysics, hover_state
from emulator.profile import load_profile
from emulator.vehicle import EmulatedVehicle
from hil.rl.link_observe import DRAWS, LinkModel, LinkRows, link_observe_rows
from hil.rl.observe import observe_rows
from hil.rl.reward import REWARD_TERMS, pack_weights, score_rows
from hil.rl.scenarios import CrossingPool, CrossingRanges, draw_crossings
from hil.rl.targets import fc_targets
from policies.controller import ExpertGains, expert_command_batch
from policies.learning.features import CONTROLLER_MASS_KG, E2E_IN
from policies.onboard.program import ProgramConfig


@dataclass(frozen=True)
class RewardWeights:
    """The reward's constants and switches (`hil.rl.reward`): by default the release's reward
    (cross_grap_env_v2.py), `paper()` the paper's (section V-B). Units per step of ``step_unit_s``."""

    position_per_m: float = 1000.0  # w_r
    active_distance_m: float = 0.2  # d_a: the release's 0.2 m (paper: 0.15 m)
    position_scaled: bool = False  # the release pays the position reward per step; the paper x dt
    arrival: float = 5e5  # S, once
    rate_per_rad_s: float = 2 * 57.3  # w_w
    rate_offset_rad_s: float = 2.0  # the release's (2 - |w|) (paper: 0, a pure penalty)
    angular_acceleration_per_rad_s2: float = 10 * 57.3  # w_alpha: the release's 10 x 57.3 (paper: 5 x 57.3)
    angular_acceleration_offset_rad_s2: float = 2.0  # the release's (2 - |alpha|) (paper: 0)
    jerk_per_m_s2: float = 10.0  # w_j
    jerk_as_difference: bool = True  # the release: |a_t - a_{t-1}|; the paper: |da/dt|
    #: the shaping terms are scaled by dt / step_unit_s: the release's 0.005 s; the paper's dt in s: 1.0
    step_unit_s: float = 0.005
    collision: float = 1e6  # C: the release's 1e6 (paper: 1e9)
    collision_replaces: bool = True  # the release: a collision's step pays -C alone (paper: added)
    end_step_zero: bool = True  # the release: the last step of an episode without collision pays 0

    @classmethod
    def paper(cls) -> RewardWeights:
        """The paper's reward as its text gives it: Delta t in seconds, no offsets, w_alpha 5 x 57.3,
        d_a 0.15 m, C 1e9."""
        return cls(active_distance_m=0.15, position_scaled=True, rate_offset_rad_s=0.0,
                   angular_acceleration_per_rad_s2=5 * 57.3, angular_acceleration_offset_rad_s2=0.0,
                   jerk_as_difference=False, step_unit_s=1.0, collision=1e9, collision_replaces=False,
                   end_step_zero=False)


@dataclass(frozen=True)
class EnvConfig:
    """The environment's settings (SI units)."""

    vehicle: str = "n3_tx2"
    rate_hz: float = 100.0  # control rate (the onboard program's)
    physics_dt_s: float = 0.001
    lead_s: float = ProgramConfig().control_lead_s
    pool_size: int = 256  # crossings drawn once; each episode takes one of them at random
    seed: int = 0
    ranges: CrossingRanges = field(default_factory=CrossingRanges)
    reward: RewardWeights = field(default_factory=RewardWeights)
    #: when the world is checked: "control" once a control step (fast, training), "physics" after every
    #: physics step as the runner does (a graze shorter than a control step counts; about 2x slower)
    world_check: str = "control"
    #: the observation through the mocap/UWB link and the onboard filter (None: the true state)
    link: LinkModel | None = None

    def __post_init__(self) -> None:
        if self.world_check not in ("control", "physics"):
            raise ValueError(f"world_check must be 'control' or 'physics', got {self.world_check!r}")
        steps = 1.0 / (self.rate_hz * self.physics_dt_s)
        whole = abs(steps - round(steps)) < 1e-9 and steps >= 1
        if not (self.rate_hz > 0 and self.physics_dt_s > 0 and whole):
            raise ValueError(f"the control period must be a whole number of physics steps, got rate "
                             f"{self.rate_hz} Hz and physics step {self.physics_dt_s} s")
        if self.pool_size < 1:
            raise ValueError(f"pool_size must be >= 1, got {self.pool_size}")
        if not (0.0 <= self.lead_s <= 0.2):
            raise ValueError(f"lead_s must be in [0, 0.2] s, got {self.lead_s}")

    @property
    def dt_s(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def physics_steps(self) -> int:
        return round(1.0 / (self.rate_hz * self.physics_dt_s))


def observation_space() -> gym.spaces.Box:
    return gym.spaces.Box(-np.inf, np.inf, (E2E_IN,), np.float32)


def action_space(full_thrust_n: float) -> gym.spaces.Box:
    """Roll, pitch (rad) within +-90 deg, thrust (N) within the N3's full thrust."""
    return gym.spaces.Box(np.array([-math.pi / 2, -math.pi / 2, 0.0], np.float32),
                          np.array([math.pi / 2, math.pi / 2, full_thrust_n], np.float32), dtype=np.float32)


class CrossGapCore:
    """The batch of N vehicles without resets of its own: `step` reports terminated/truncated rows, the
    caller resets them (`reset_rows`). Shared by the VecEnv and the one-vehicle gymnasium view."""

    def __init__(self, n: int, config: EnvConfig | None = None, pool: CrossingPool | None = None) -> None:
        if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
            raise ValueError(f"the number of vehicles must be a positive integer, got {n!r}")
        self.n = int(n)
        self.config = cfg = config or EnvConfig()
        self.profile = load_profile(cfg.vehicle)
        self.rng = np.random.default_rng(cfg.seed)
        self.pool = pool or CrossingPool(draw_crossings(cfg.pool_size, self.rng, cfg.ranges), self.profile,
                                         cfg.dt_s, cfg.lead_s)
        self.physics = BatchPhysics(self.profile, self.n, cfg.physics_dt_s)
        inner = EmulatedVehicle(self.profile).fc.inner
        self._gains, self._mix_inv = inner.params, inner.mix_inv
        self._outs = np.zeros((self.n, 4))
        self._targets = np.zeros((self.n, 4))
        self._hover = hover_state(self.profile).to_vector()
        self._max_tilt = math.radians(self.profile.max_tilt_deg)
        self._full = self.profile.n3_full_thrust_n
        self._mass_scale = self.profile.mass_kg / CONTROLLER_MASS_KG
        self._expert = ExpertGains(tilt_max_rad=math.radians(ProgramConfig().max_tilt_deg))
        self.which = np.zeros(self.n, np.int64)  # the pool crossing each row flies
        self.tick = np.zeros(self.n, np.int64)  # control steps since the episode began
        self.arrived = np.zeros(self.n, bool)
        #: whether each row's last action flew its vehicle (False: the expert flew the traverse, the action
        #: had no effect)
        self.policy_flew = np.ones(self.n, bool)
        self._prev_w = np.zeros((self.n, 3))
        self._prev_a = np.zeros((self.n, 3))
        self._pred_pos = np.zeros((self.n, 3))
        self._pred_vel = np.zeros((self.n, 3))
        self._weights = pack_weights(cfg.reward, cfg.dt_s)
        self._terms = np.zeros((self.n, len(REWARD_TERMS)))
        self._reward = np.zeros(self.n)
        self._terminated = np.zeros(self.n, bool)
        self._truncated = np.zeros(self.n, bool)
        self._success = np.zeros(self.n, bool)
        self._obs = np.zeros((self.n, E2E_IN))
        self._all = np.arange(self.n)
        self._codes = np.zeros(self.n, np.int64)
        self.clearance_m = np.zeros(self.n)
        # each row's crossing, copied from the pool at its reset (no gather per step)
        self._row_yaw = np.zeros(self.n)  # plan yaw (ENU, rad)
        self._row_ned_yaw = np.zeros(self.n)  # the FC target's yaw (NED, rad)
        self._row_start = np.zeros((self.n, 3))
        self._row_centre = np.zeros((self.n, 3))
        self._row_dir = np.zeros((self.n, 3))
        self._row_t_approach = np.zeros(self.n)
        self._row_steps = np.zeros(self.n, np.int64)
        self.link = None if cfg.link is None else LinkRows(self.n, cfg.link)
        self._exposures = 0 if cfg.link is None else cfg.link.exposures_per_step(cfg.dt_s)
        self.reset_rows(np.arange(self.n))

    # --- episodes -------------------------------------------------------------------------------------
    def reset_rows(self, rows: np.ndarray, which: np.ndarray | None = None) -> None:
        """Start new episodes in ``rows``: crossings ``which`` (default drawn from the seeded Generator)."""
        rows = np.asarray(rows, np.int64)
        if rows.size == 0:
            return
        n_pool = len(self.pool)
        k = self.rng.integers(n_pool, size=rows.size) if which is None else np.asarray(which, np.int64)
        if k.shape != rows.shape or k.min() < 0 or k.max() >= len(self.pool):
            raise ValueError(f"crossings {k} do not fit rows {rows} of a pool of {len(self.pool)}")
        self.which[rows] = k
        pool = self.pool
        self._row_yaw[rows] = pool.yaw_rad[k]
        self._row_ned_yaw[rows] = (math.pi / 2 - pool.yaw_rad[k] + math.pi) % (2 * math.pi) - math.pi
        self._row_start[rows] = pool.start_m[k]
        self._row_centre[rows] = pool.gap_centre_m[k]
        self._row_dir[rows] = pool.crossing_dir[k]
        self._row_t_approach[rows] = pool.t_approach_s[k]
        self._row_steps[rows] = pool.steps[k]
        self._obs[rows, 12:] = pool.x17[k]  # the planner inputs at t = 0; column 12 (time) moves
        self.tick[rows] = 0
        self.arrived[rows] = False
        x, aux, _ = self.physics.kernel_arrays
        x[rows] = self._hover
        x[rows, 0:3] = self.pool.start_m[k]
        half = 0.5 * self.pool.yaw_rad[k]  # facing the crossing (ENU yaw)
        x[rows, 6], x[rows, 7], x[rows, 8], x[rows, 9] = np.cos(half), 0.0, 0.0, np.sin(half)
        aux[rows] = 0.0
        self._prev_w[rows] = 0.0
        self._prev_a[rows] = 0.0
        if self.link is not None:
            self.link.reset(rows, x, 0.0)
        self._observe(rows)

    def observations(self, rows: np.ndarray | None = None) -> np.ndarray:
        """The current observations (N, 29) of ``rows`` (None: all), float32."""
        return (self._obs if rows is None else self._obs[rows]).astype(np.float32)

    def _observe(self, rows: np.ndarray | None = None) -> None:
        """The policy's inputs of ``rows`` (None: all) from their state (see the module doc)."""
        x, aux, _ = self.physics.kernel_arrays
        observe_rows(x, aux, self._all if rows is None else rows, self.config.lead_s, self._row_start,
                     self._row_yaw, self.tick, self.config.dt_s, self._row_t_approach, self._pred_pos,
                     self._pred_vel, self._obs)

    def _observe_link(self) -> None:
        """Every row's inputs through the link (`hil.rl.link_observe`), its draws from the Generator."""
        n, rng, lk, cfg = self.n, self.rng, self.link, self.config
        assert lk is not None
        k = self._exposures
        draws = np.empty((n, k, DRAWS))  # each exposure's (`link_observe.DRAWS`)
        draws[..., 0:6] = rng.standard_normal((n, k, 6))
        draws[..., 6] = rng.standard_exponential((n, k))
        draws[..., 7] = rng.standard_normal((n, k))
        draws[..., 8:11] = rng.random((n, k, 3))
        x, _, _ = self.physics.kernel_arrays
        link_observe_rows(x, lk.before, self.tick * cfg.dt_s, cfg.dt_s, draws.reshape(n, k * DRAWS),
                          lk.consts, cfg.lead_s, self._row_start, self._row_yaw, self._row_t_approach, lk.kx,
                          lk.kp, lk.kt, lk.quat, lk.bad, lk.next_exposure_s, lk.q_stamp, lk.q_arrival,
                          lk.q_values, lk.q_head, lk.q_count, lk.lost, self._pred_pos, self._pred_vel,
                          self._obs)

    # --- one control step -----------------------------------------------------------------------------
    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Fly one control period under ``actions`` (N, 3); returns (reward (N,), terminated (N,),
        truncated (N,), reward terms (N, 6) in `REWARD_TERMS` order, success (N,): crossed the gap plane
        with no collision, at the episode's end). ValueError for a wrong shape or a non-finite action."""
        a = np.asarray(actions, np.float64)
        if a.shape != (self.n, 3):
            a = a.reshape(self.n, 3) if a.size == self.n * 3 else a
            if a.shape != (self.n, 3):
                raise ValueError(f"actions must have shape ({self.n}, 3), got {np.shape(actions)}")
        if not np.isfinite(a).all():
            raise ValueError("actions must be finite (roll, pitch in rad, thrust in N)")
        cfg = self.config
        roll, pitch, thrust = a[:, 0].copy(), a[:, 1].copy(), a[:, 2] * self._mass_scale  # (contiguous)
        flown_by_expert = self.tick * cfg.dt_s + cfg.lead_s >= self._row_t_approach  # the traverse
        np.logical_not(flown_by_expert, out=self.policy_flew)
        expert = np.flatnonzero(flown_by_expert)
        if expert.size:  # the expert flies the traverse
            ref = self.pool.ref[self.which[expert], self.tick[expert]]
            er, ep, _, et = expert_command_batch(ref[:, 0:3], ref[:, 3:6], ref[:, 6:9], self._row_yaw[expert],
                                                 self._pred_pos[expert], self._pred_vel[expert],
                                                 self.profile.mass_kg, self._expert)
            roll[expert], pitch[expert], thrust[expert] = er, ep, et
        tg = self._targets  # (the command link's SET_ATTITUDE_TARGET, as the FC reads it)
        fc_targets(roll, pitch, thrust, self._row_ned_yaw, self._full, self._max_tilt, tg)
        x, aux, p = self.physics.kernel_arrays
        if self.link is not None:
            self.link.save(x)
        fly_targets(x, aux, p, tg, self._gains, self._mix_inv, self._outs, cfg.physics_steps,
                    self.pool.worlds, self.which, cfg.world_check == "physics", self._codes, self.clearance_m)
        self.physics.advance_clock(cfg.physics_steps)
        self.tick += 1
        score_rows(x, aux, self._weights, self._row_centre, self._row_dir, self.tick, self._row_steps,
                   self._codes, self.arrived, self._prev_w, self._prev_a, self._terms, self._reward,
                   self._terminated, self._truncated, self._success)
        if self.link is None:
            self._observe()
        else:
            self._observe_link()
        return (self._reward.copy(), self._terminated.copy(), self._truncated.copy(), self._terms.copy(),
                self._success.copy())


class CrossGapVecEnv(VecEnv):
    """`CrossGapCore` as an SB3 VecEnv: finished rows restart at once (their last observation in
    ``infos[i]["terminal_observation"]``). At an episode's end its info holds ``episode`` (return,
    length, wall time since the env was built, as SB3's Monitor writes it), ``reward_terms`` (each
    term's episode sum), ``success``, ``arrived`` (within d_a of the gap centre) and
    ``TimeLimit.truncated``; other rows' infos are one shared empty dict (read, never written)."""

    def __init__(self, num_envs: int = 64, config: EnvConfig | None = None, pool: CrossingPool | None = None
                 ) -> None:
        self.core = CrossGapCore(num_envs, config, pool)
        self.render_mode = None
        super().__init__(self.core.n, observation_space(), action_space(self.core.profile.n3_full_thrust_n))
        self._actions: np.ndarray | None = None
        self._ret = np.zeros(self.num_envs)
        self._terms = np.zeros((self.num_envs, len(REWARD_TERMS)))
        self._start = time.time()
        self._empty: dict[str, Any] = {}

    def reset(self) -> np.ndarray:
        self.core.reset_rows(np.arange(self.num_envs))
        self._ret[:] = 0.0
        self._terms[:] = 0.0
        return self.core.observations()

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        if self._actions is None:
            raise RuntimeError("step_wait without step_async")
        core = self.core
        reward, terminated, truncated, terms, success = core.step(self._actions)
        self._actions = None
        self._ret += reward
        self._terms += terms
        done = terminated | truncated
        infos: list[dict[str, Any]] = [self._empty] * self.num_envs
        rows = np.flatnonzero(done)
        if rows.size:
            final = core.observations(rows)
            elapsed = round(time.time() - self._start, 6)
            for j, i in enumerate(rows.tolist()):
                infos[i] = {"terminal_observation": final[j], "TimeLimit.truncated": bool(truncated[i]),
                            "episode": {"r": float(self._ret[i]), "l": int(core.tick[i]), "t": elapsed},
                            "reward_terms": dict(zip(REWARD_TERMS, self._terms[i].tolist(), strict=True)),
                            "success": bool(success[i]), "arrived": bool(core.arrived[i]),
                            "crossing": int(core.which[i])}
            self._ret[rows] = 0.0
            self._terms[rows] = 0.0
            core.reset_rows(rows)
        return core.observations(), reward.astype(np.float32), done, infos

    def close(self) -> None:
        """Nothing to release."""

    def seed(self, seed: int | None = None) -> Sequence[int | None]:
        """Re-seed the Generator that picks each episode's crossing."""
        self.core.rng = np.random.default_rng(seed)
        return [seed] * self.num_envs

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        return [getattr(self, attr_name)] * len(self._indices(indices))

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *args: Any, indices: Any = None, **kwargs: Any) -> list[Any]:
        return [getattr(self, method_name)(*args, **kwargs)] * len(self._indices(indices))

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        return [False] * len(self._indices(indices))

    def _indices(self, indices: Any) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        return [indices] if isinstance(indices, int) else list(indices)


class CrossGapEnv(gym.Env):
    """One vehicle of `CrossGapCore` as a gymnasium Env (`CrossGap-v0`): ``reset(seed=...)`` re-seeds the
    Generator that picks the crossing; ``info`` holds the step's reward terms, ``success`` and ``arrived``."""

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012

    def __init__(self, config: EnvConfig | None = None, pool: CrossingPool | None = None) -> None:
        self.core = CrossGapCore(1, config, pool)
        self.observation_space = observation_space()
        self.action_space = action_space(self.core.profile.n3_full_thrust_n)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        if seed is not None:
            self.core.rng = np.random.default_rng(seed)
        which = None if not options or "crossing" not in options else np.array([int(options["crossing"])])
        self.core.reset_rows(np.zeros(1, np.int64), which)
        return self.core.observations()[0], {"crossing": int(self.core.which[0])}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        reward, terminated, truncated, terms, success = self.core.step(np.asarray(action).reshape(1, 3))
        info = {"reward_terms": dict(zip(REWARD_TERMS, terms[0].tolist(), strict=True)),
                "success": bool(success[0]), "arrived": bool(self.core.arrived[0])}
        return self.core.observations()[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), info
