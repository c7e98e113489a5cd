"""highway-env's ``intersection-multi-agent-v1`` behind the ParallelEnv interface of the racing env.

Id ``"highway-intersection"`` in :func:`utils.vec_env.make_vec_env`. Two controlled vehicles
(agents ``car_0``, ``car_1``) cross a four-way intersection among scripted traffic:

- observation per agent: ``Box(0, 255, (96, 96, 3), uint8)``, highway-env's ``GrayscaleObservation``
  (a 96x96 top-down view centred on the agent's own vehicle, ``stack_size`` 1) copied into 3 channels.
  highway-env stores that image as (W, H); it is transposed here to the usual (H, W), so it is
  oriented like ``render()``. The view is world-aligned (north up), not rotated with the car. By
  default it covers the same area as highway-env's own 600x600 ``render()`` frame;
- action per agent: ``Box(-1, 1, (2,), float32)``, highway-env's ``ContinuousAction`` in its order
  ``[acceleration, steering]`` (mapped to [-5, 5] m/s^2 and [-pi/4, pi/4] rad); out-of-range finite
  values are clipped;
- reward per agent: ``info["agents_rewards"][i]``, highway-env's per-vehicle reward;
- termination: highway-env's own rule for the whole episode (``IntersectionEnv._is_terminated``:
  any controlled vehicle crashed, or all arrived; with ``offroad_terminal`` set, also car_0 off the road) ends it
  for every agent at once; truncation at ``duration`` seconds likewise. A vehicle that arrives while the other
  still drives stays in the episode, as in highway-env.
- infos per agent: ``speed``, ``crashed``, ``arrived``, ``on_road`` of the agent's own vehicle, plus
  highway-env's ``agents_rewards``, ``agents_terminated`` and ``rewards`` (its averaged reward terms).

Policy frequency 5 Hz (3 simulation steps of 15 Hz per env step), ``duration`` 40 s: at most 200
steps. About 32 steps per second on one core here.

Rendering uses pygame. ``SDL_VIDEODRIVER`` defaults to ``"offscreen"`` (set on import if unset);
never use ``"dummy"``: highway-env then skips drawing and every frame and observation is blank.
``SDL_NO_SIGNAL_HANDLERS`` defaults to ``"1"`` so that ``pygame.init()`` leaves SIGINT and SIGTERM
alone (SDL would turn them into quit events and the process would survive Ctrl-C and ``kill``).
"""

from __future__ import annotations

import os

os.environ.setdefault("SDL_VIDEODRIVER", "offscreen")
os.environ.setdefault("SDL_NO_SIGNAL_HANDLERS", "1")

import warnings  # noqa: E402
from typing import Any  # noqa: E402

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
from gymnasium import spaces  # noqa: E402
from pettingzoo import ParallelEnv  # noqa: E402

#: gymnasium id, with the module prefix so that it resolves in a fresh (worker) process too:
#: highway-env registers its envs when ``highway_env`` is imported.
HIGHWAY_ENV_ID = "highway_env:intersection-multi-agent-v1"
#: RGB -> gray weights of ``GrayscaleObservation`` (ITU-R 601 luma, highway-env's documented example).
GRAYSCALE_WEIGHTS = (0.2989, 0.5870, 0.1140)
#: Size (px) and scaling (px per m) of highway-env's intersection ``render()`` frame.
RENDER_SIZE = 600
RENDER_SCALING = 5.5 * 1.3


class HighwayIntersection(ParallelEnv):
    """Two (or up to four) cars crossing highway-env's intersection; see the module docstring.

    :param num_agents: controlled vehicles (highway-env puts vehicle ``i`` on approach ``i % 4``); 2 by default
    :param render_mode: ``None`` or ``"rgb_array"`` (highway-env's 600x600 frame, centred on ``car_0``)
    :param duration: episode length in seconds (truncation)
    :param policy_frequency: env steps per second
    :param simulation_frequency: physics steps per second (a multiple of ``policy_frequency``)
    :param obs_size: side of the square observation in pixels
    :param obs_scaling: observation pixels per metre; default ``RENDER_SCALING * obs_size / RENDER_SIZE``,
        the area of the ``render()`` frame
    :param config: further highway-env config entries, applied last (e.g. ``{"spawn_probability": 0.3}``)
    """

    metadata = {"name": "highway_intersection_v0", "render_modes": ["rgb_array"], "is_parallelizable": True}

    def __init__(
        self,
        num_agents: int = 2,
        render_mode: str | None = None,
        duration: float = 40.0,
        policy_frequency: int = 5,
        simulation_frequency: int = 15,
        obs_size: int = 96,
        obs_scaling: float | None = None,
        config: dict[str, Any] | None = None,
    ):
        if not 1 <= num_agents <= 4:
            raise ValueError(f"num_agents must be in 1..4 (one per approach), got {num_agents}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if simulation_frequency % policy_frequency:
            raise ValueError(
                f"simulation_frequency ({simulation_frequency}) must be a multiple of "
                f"policy_frequency ({policy_frequency})"
            )
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": policy_frequency}  # real time
        self.obs_scaling = RENDER_SCALING * obs_size / RENDER_SIZE if obs_scaling is None else float(obs_scaling)
        self.highway_config = {
            "controlled_vehicles": num_agents,
            "action": {"type": "MultiAgentAction", "action_config": {"type": "ContinuousAction"}},
            "observation": {
                "type": "MultiAgentObservation",
                "observation_config": {
                    "type": "GrayscaleObservation",
                    "observation_shape": (obs_size, obs_size),
                    "stack_size": 1,
                    "weights": list(GRAYSCALE_WEIGHTS),
                    "scaling": self.obs_scaling,
                },
            },
            "policy_frequency": policy_frequency,
            "simulation_frequency": simulation_frequency,
            "duration": duration,
            **(config or {}),
        }
        with warnings.catch_warnings():  # "intersection-multi-agent-v1 is out of date": v1 is the spec
            warnings.simplefilter("ignore", DeprecationWarning)
            self._env = gym.make(HIGHWAY_ENV_ID, config=self.highway_config, render_mode=render_mode)
        self._core = self._env.unwrapped  # highway_env's MultiAgentIntersectionEnv

        self.possible_agents = [f"car_{i}" for i in range(num_agents)]
        self.agents: list[str] = []
        observation_space = spaces.Box(0, 255, (obs_size, obs_size, 3), np.uint8)
        action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.observation_spaces = {a: observation_space for a in self.possible_agents}
        self.action_spaces = {a: action_space for a in self.possible_agents}

    def observation_space(self, agent: str) -> spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Box:
        return self.action_spaces[agent]

    @staticmethod
    def _to_rgb(gray_wh: np.ndarray) -> np.ndarray:
        """highway-env's (1, W, H) grayscale stack -> (H, W, 3) uint8."""
        return np.ascontiguousarray(np.repeat(gray_wh[-1].T[:, :, None], 3, axis=2))

    def _infos(self, info: dict[str, Any]) -> dict[str, dict[str, Any]]:
        shared = {
            "agents_rewards": tuple(float(r) for r in info["agents_rewards"]),
            "agents_terminated": tuple(bool(t) for t in info["agents_terminated"]),
            "rewards": {k: float(v) for k, v in info.get("rewards", {}).items()},
        }
        infos = {}
        for agent, vehicle in zip(self.possible_agents, self._core.controlled_vehicles, strict=True):
            infos[agent] = {
                "speed": float(vehicle.speed),
                "crashed": bool(vehicle.crashed),
                "arrived": bool(self._core.has_arrived(vehicle)),
                "on_road": bool(vehicle.on_road),
                **shared,
            }
        return infos

    def reset(self, seed: int | None = None, options: dict | None = None):
        """Reset highway-env (``options={"config": {...}}`` reconfigures it, as highway-env allows)."""
        observations, info = self._env.reset(seed=seed, options=options)
        self.agents = list(self.possible_agents)
        return {a: self._to_rgb(o) for a, o in zip(self.possible_agents, observations, strict=True)}, self._infos(info)

    def _validate_actions(self, actions: dict[str, Any]) -> tuple[np.ndarray, ...]:
        if not isinstance(actions, dict):
            raise ValueError(f"actions must be a dict agent -> action, got {type(actions).__name__}")
        for agent in actions:
            if agent not in self.agents:
                raise ValueError(f"action for {agent!r}, which is not a live agent ({self.agents})")
        controls = []
        for agent in self.possible_agents:
            if agent not in actions:
                raise ValueError(f"no action for {agent} (every live agent needs one)")
            try:
                a = np.asarray(actions[agent], dtype=np.float32)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"action for {agent} is not numeric: {actions[agent]!r}") from exc
            if a.shape != (2,):
                raise ValueError(f"action for {agent} has shape {a.shape}, expected (2,)")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"action for {agent} is not finite: {a.tolist()}")
            controls.append(np.clip(a, -1.0, 1.0))
        return tuple(controls)

    def step(self, actions: dict[str, Any]):
        """Step all agents; the episode ends for every agent at once (see the module docstring)."""
        if not self.agents:
            raise RuntimeError("the episode is over: call reset() before step()")
        observations, _, _, truncated, info = self._env.step(self._validate_actions(actions))
        # MultiAgentWrapper replaces the env's scalar `terminated` by per-vehicle flags; the
        # episode-level rule (a crash ends it for everyone) is IntersectionEnv._is_terminated.
        terminated = bool(self._core._is_terminated())
        truncated = bool(truncated) and not terminated
        obs = {a: self._to_rgb(o) for a, o in zip(self.possible_agents, observations, strict=True)}
        rewards = {a: float(r) for a, r in zip(self.possible_agents, info["agents_rewards"], strict=True)}
        terminations = dict.fromkeys(self.possible_agents, terminated)
        truncations = dict.fromkeys(self.possible_agents, truncated)
        infos = self._infos(info)
        if terminated or truncated:
            self.agents = []
        return obs, rewards, terminations, truncations, infos

    def render(self) -> np.ndarray | None:
        """highway-env's RGB frame (600x600, centred on ``car_0``'s vehicle) with ``render_mode="rgb_array"``."""
        if self.render_mode is None:
            gym.logger.warn("render() called with render_mode=None; pass render_mode='rgb_array'")
            return None
        return self._env.render()

    def close(self) -> None:
        self._env.close()
