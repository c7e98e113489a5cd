"""A tiny, fully scripted PettingZoo ``ParallelEnv`` used as the reference in the vec-env tests.

Everything it returns is a known function of (episode, step, agent), so a test can predict
every observation, reward and flag that :class:`utils.vec_env.MultiAgentVecEnv` must report.

Observation of agent ``i`` (``Box(0, 255, obs_shape, uint8)``, ``obs_shape[0] >= 2``):

- ``obs[0, 0, 0]`` = step count ``t`` of the episode (0 after ``reset``),
- ``obs[0, 0, 1]`` = agent index ``i``,
- ``obs[0, 0, 2]`` = ``tag`` (a constructor argument; the tests use it to identify the race),
- ``obs[1]`` = ``episode_noise`` + ``t``: noise drawn from the env's RNG at every reset, so that
  seeding is observable (the same seed gives the same noise).

Agent ``i`` terminates at step ``drop_steps[i]`` (``None``: never); at ``max_steps`` every agent
still present is truncated. Reward of agent ``i`` at step ``t`` is ``t + 0.5 * i``.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv


class ScriptedParallelEnv(ParallelEnv):
    """Deterministic multi-agent env; see the module docstring for what it returns.

    :param num_agents: number of agents, named ``agent_0 ... agent_{n-1}``
    :param drop_steps: per agent, the step at which it terminates (``None``: never)
    :param max_steps: the step at which every agent still present is truncated
    :param obs_shape: observation shape (H, W, C) with H >= 2 and C >= 3
    :param tag: written into every observation (identifies the env instance)
    :param render_mode: ``None`` or ``"rgb_array"`` (a 16x16 frame filled with the step count)
    """

    metadata = {"name": "scripted_v0", "render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        num_agents: int = 2,
        drop_steps: Sequence[int | None] | None = None,
        max_steps: int = 10,
        obs_shape: tuple[int, int, int] = (4, 4, 3),
        tag: int = 0,
        render_mode: str | None = None,
    ):
        self.possible_agents = [f"agent_{i}" for i in range(num_agents)]
        self.agents: list[str] = []
        self.drop_steps = list(drop_steps) if drop_steps is not None else [None] * num_agents
        assert len(self.drop_steps) == num_agents
        self.max_steps = max_steps
        self.obs_shape = tuple(obs_shape)
        self.tag = tag
        self.render_mode = render_mode
        self.dead_zone = -0.5
        self.dead_zone_calls = 0
        self.t = 0
        self.episode = -1
        self.last_actions: dict[str, Any] = {}
        self._rng: np.random.Generator | None = None
        self._noise = np.zeros(self.obs_shape[1:], dtype=np.uint8)

    @functools.lru_cache(maxsize=None)
    def observation_space(self, agent: str) -> spaces.Box:
        return spaces.Box(0, 255, self.obs_shape, np.uint8)

    @functools.lru_cache(maxsize=None)
    def action_space(self, agent: str) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, (2,), np.float32)

    def set_dead_zone(self, value: float) -> float:
        """Mimics the racing env's method of the same name; counts its calls, returns the new value."""
        self.dead_zone_calls += 1
        self.dead_zone = float(value)
        return self.dead_zone

    def expected_obs(self, agent_index: int, t: int | None = None) -> np.ndarray:
        """The observation agent ``agent_index`` receives at step ``t`` of the current episode."""
        t = self.t if t is None else t
        obs = np.zeros(self.obs_shape, dtype=np.uint8)
        obs[0, 0, :3] = (t % 256, agent_index, self.tag % 256)
        obs[1] = (self._noise.astype(np.int64) + t) % 256
        return obs

    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None or self._rng is None:
            self._rng = np.random.default_rng(seed)
        self._noise = self._rng.integers(0, 200, size=self.obs_shape[1:], dtype=np.uint8)
        self.t = 0
        self.episode += 1
        self.agents = list(self.possible_agents)
        self.last_actions = {}
        observations = {a: self.expected_obs(i) for i, a in enumerate(self.possible_agents)}
        infos = {a: {"agent_index": i, "episode_index": self.episode} for i, a in enumerate(self.possible_agents)}
        return observations, infos

    def step(self, actions: dict[str, Any]):
        if not self.agents:
            raise RuntimeError("step() called on a finished episode; call reset()")
        if set(actions) != set(self.agents):
            raise ValueError(f"actions for {sorted(actions)} but live agents are {self.agents}")
        self.last_actions = {a: np.array(v, copy=True) for a, v in actions.items()}
        self.t += 1
        observations, rewards, terminations, truncations, infos = {}, {}, {}, {}, {}
        for agent in self.agents:
            i = self.possible_agents.index(agent)
            observations[agent] = self.expected_obs(i)
            rewards[agent] = float(self.t + 0.5 * i)
            terminations[agent] = self.drop_steps[i] is not None and self.t >= self.drop_steps[i]
            truncations[agent] = self.t >= self.max_steps and not terminations[agent]
            infos[agent] = {"agent_index": i, "episode_index": self.episode, "t": self.t}
        self.agents = [a for a in self.agents if not (terminations[a] or truncations[a])]
        return observations, rewards, terminations, truncations, infos

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        return np.full((16, 16, 3), self.t % 256, dtype=np.uint8)
