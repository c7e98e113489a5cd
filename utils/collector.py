"""The collector of both dreamer scripts: the cars of a vectorized race as agents drive them (Algorithm 1's "act").

Every car of a ``MultiAgentVecEnv`` (utils/vec_env.py) is a slot; agent i drives car i of every race. What the
collector records of a car is what its agent's replay stores (``CarEpisode``: frames at the encoder's size, the
action that led to each, the summed reward of the held steps, terminal or not) and what a race reads of it
(``READINGS``). Training, evaluation (``drive_races``), race.py and the benchmarks all drive cars through ``Races``.

What it uses of a script's ``Args``: ``action_repeat``, ``image_size``, ``dead_zone_end`` (the edge at or below
which a pedal value brakes) and, in ``drive_races``, ``eval_policy``, ``eval_seed`` and ``eval_episodes``. What it
uses of an agent: ``action_dim``, ``initial_state(n)`` and ``act(obs, state, is_first, policy) -> (actions, state)``.
"""

from __future__ import annotations

import dataclasses
import itertools

import cv2
import numpy as np
import torch


def preprocess_frames(frames: np.ndarray, image_size: int) -> np.ndarray:
    """Camera frames (n, 96, 96, 3) uint8 -> what the encoder sees (n, S, S, 3) uint8 (area resize)."""
    frames = np.asarray(frames, dtype=np.uint8)
    if frames.shape[-3] == image_size and frames.shape[-2] == image_size:
        return frames
    return np.stack([cv2.resize(f, (image_size, image_size), interpolation=cv2.INTER_AREA) for f in frames])


class CarEpisode:
    """One car's episode as it is being driven: frames at the encoder's size, the action that led to
    each frame (zero for the first), the reward that came with it, and whether it is a terminal state."""

    def __init__(self, first_frame: np.ndarray, action_dim: int = 2):
        self.obs, self.action = [first_frame], [np.zeros(action_dim, dtype=np.float32)]
        self.reward, self.terminated = [0.0], [False]
        self.ret, self.final_info = 0.0, None

    def add(self, frame, action, reward, terminated) -> None:
        self.obs.append(frame)
        self.action.append(np.array(action, dtype=np.float32))  # (a copy: the caller's array is reused)
        self.reward.append(float(reward))
        self.terminated.append(bool(terminated))
        self.ret += float(reward)

    def arrays(self) -> tuple[np.ndarray, ...]:
        reward, terminated = np.asarray(self.reward, np.float32), np.asarray(self.terminated)
        return np.stack(self.obs), np.stack(self.action), reward, terminated


# What a race reads of each car: its return; as its race ended, its progress (fraction of tiles), lap_finished
# (within the time limit) and eliminated (off the road or stalled); over its decisions, abs_steer (mean |action[0]|:
# near 1 is bang-bang steering, the pursuit driver ~0.06), gas (mean max(action[1], 0)) and brake_share (share with
# action[1] at or below the dead zone's edge); speed (mean at the end of its decisions).
READINGS = ("return", "progress", "abs_steer", "gas", "brake_share", "speed", "lap_finished", "eliminated")


@dataclasses.dataclass
class Race:
    """A race that ended: its cars' episodes (in agent order) and their READINGS, each an (n,) array."""

    cars: list[CarEpisode]
    readings: dict[str, np.ndarray]


class Races:
    """The one collector: the cars of a vec env's K races as they are driven, in training, evaluation and race.py.

    Agent i drives car i of every race (slots i, i + n, ...). A car decides when its race starts and then every
    `repeats[i]` env steps (default --action-repeat), holding its action; its transition sums the held steps'
    rewards and ends with the frame after them (its terminal frame if it went out), and once out it decides no more.
    `drive` steps until a race ends; K > 1 races go on side by side across calls. An agent needs `act(obs, state,
    is_first, policy) -> (actions, state)` and `action_dim`; the policy "random" draws uniform actions (prefill)."""

    def __init__(self, agents: list, args, envs, obs: np.ndarray, repeats: list[int] | None = None):
        cars = getattr(envs, "num_agents", len(agents))  # (a MultiAgentVecEnv's cars per race)
        if cars != len(agents) or envs.num_envs % len(agents):
            raise ValueError(f"{len(agents)} agents for races of {cars} cars ({envs.num_envs} vec-env slots): agent i "
                             "drives car i of every race, one agent per car")  # fmt: skip
        if repeats is not None and len(repeats) != len(agents):
            raise ValueError(f"{len(repeats)} action repeats for {len(agents)} agents: one per agent")
        self.agents, self.args, self.envs, self.n = agents, args, envs, len(agents)
        self.repeat = np.tile(repeats or [args.action_repeat] * self.n, envs.num_envs // self.n)  # per slot
        dims = sorted({a.action_dim for a in agents})
        if len(dims) > 1:
            raise ValueError(f"agents of action sizes {dims} in one race: its cars share one action space")
        self.actions = np.zeros((envs.num_envs, dims[0]), dtype=np.float32)
        self.states, slots = [None] * self.n, envs.num_envs  # agent i's recurrent state over its K cars
        self.is_first, self.racing = np.ones(slots, dtype=bool), np.ones(slots, dtype=bool)
        self.held, self.reward = np.zeros(slots, dtype=int), np.zeros(slots)  # since the car's last decision
        self.cars: list[CarEpisode] = [None] * slots
        # per slot, the race so far: sums of return, |steer|, gas, brake decisions and speed, with their counts
        # (decisions, speed_samples); progress, lap_finished and eliminated hold their latest value, not a sum
        self.sums = {key: np.zeros(slots) for key in READINGS + ("decisions", "speed_samples")}
        self.start(obs)

    def start(self, obs: np.ndarray, races=None) -> None:
        """New races (default: all) from their first observations in `obs` (after a reset or an auto-reset)."""
        self.obs = obs
        races = range(self.envs.num_envs // self.n) if races is None else races
        slots = np.array([k * self.n + i for k in races for i in range(self.n)])
        for slot, frame in zip(slots, preprocess_frames(obs[slots], self.args.image_size)):
            self.cars[slot] = CarEpisode(frame, self.agents[slot % self.n].action_dim)
        self.is_first[slots], self.racing[slots], self.held[slots], self.reward[slots] = True, True, 0, 0.0
        for sums in self.sums.values():
            sums[slots] = 0.0

    def decide(self, policies: list[str]) -> None:
        """Every racing car whose held action has run out gets a new one from its agent."""
        deciding = self.racing & (self.held == 0)
        for i, agent in enumerate(self.agents):
            mine = np.arange(i, len(deciding), self.n)
            rows = np.flatnonzero(deciding[mine])
            now = mine[rows]
            if len(now) == 0:
                continue
            if policies[i] == "random":
                self.actions[now] = np.random.uniform(-1, 1, size=(len(now), agent.action_dim))
            elif len(now) == len(mine):
                self.actions[now], self.states[i] = agent.act(self.obs[now], self.states[i], self.is_first[now],
                                                              policies[i])  # fmt: skip
            else:  # K > 1 races out of step: the deciding cars' rows of the agent's state
                state = self.states[i] if self.states[i] is not None else agent.initial_state(len(mine))
                self.actions[now], part = agent.act(self.obs[now], state_rows(state, rows), self.is_first[now],
                                                    policies[i])  # fmt: skip
                self.states[i] = state_rows(state, rows, part)
        steer, pedal = self.actions[deciding, 0], self.actions[deciding, 1]
        self.sums["abs_steer"][deciding] += np.abs(steer)
        self.sums["gas"][deciding] += np.maximum(pedal, 0.0)
        self.sums["brake_share"][deciding] += pedal <= self.args.dead_zone_end
        self.sums["decisions"][deciding] += 1
        self.is_first[deciding] = False

    def drive(self, policies: list[str], video: list | None = None) -> tuple[list[Race], int]:
        """Step until at least one race ends, each agent acting with its policy (EVAL_POLICIES or "random"); returns
        the races that ended and the env steps taken. `video` gets race 0's frame after every step but its last."""
        for steps in itertools.count(1):
            self.decide(policies)
            obs, rewards, dones, infos = self.envs.step(self.actions)
            if video is not None and not infos[0]["is_first"]:  # (race 0 ended: the env shows the next)
                video.append(self.envs.get_images()[0])
            self.sums["return"] += rewards  # (0 for cars that are out)
            for slot in np.flatnonzero(self.racing):  # (a car racing before this step is alive in it)
                info, done = infos[slot], bool(dones[slot])
                self.held[slot] += 1
                self.reward[slot] += rewards[slot]
                self.sums["progress"][slot] = info.get("progress", 0.0)
                self.sums["lap_finished"][slot] = bool(info.get("lap_finished"))
                self.sums["eliminated"][slot] = bool(info.get("eliminated"))
                if done or self.held[slot] == self.repeat[slot]:  # the decision's transition is complete
                    last = info["terminal_observation"] if done else obs[slot]
                    frame = preprocess_frames(last[None], self.args.image_size)[0]
                    terminated = done and not info["TimeLimit.truncated"]
                    self.cars[slot].add(frame, self.actions[slot], self.reward[slot], terminated)
                    self.held[slot], self.reward[slot] = 0, 0.0
                    if "speed" in info:
                        self.sums["speed"][slot] += info["speed"]
                        self.sums["speed_samples"][slot] += 1
                if done:
                    self.racing[slot] = False
                    self.cars[slot].final_info = info
            self.obs = obs
            ended = np.flatnonzero([info["is_first"] for info in infos[:: self.n]])  # races that ended (and reset)
            if len(ended):
                races = [self.race(k) for k in ended]
                self.start(obs, ended)  # their slots now hold the first observations of new races
                return races, steps

    def race(self, k: int) -> Race:
        """Race k's cars and readings (means over decisions and speed samples)."""
        slots, sums = slice(k * self.n, (k + 1) * self.n), self.sums
        readings = {key: sums[key][slots].copy() for key in READINGS}
        for key in ("abs_steer", "gas", "brake_share"):
            readings[key] /= np.maximum(sums["decisions"][slots], 1)
        readings["speed"] /= np.maximum(sums["speed_samples"][slots], 1)
        return Race(self.cars[slots], readings)


def state_rows(state, rows: np.ndarray, part=None):
    """Rows `rows` of a recurrent state (nested tuples of batch-first tensors); with `part`, the state with them
    replaced by `part`."""
    if isinstance(state, tuple):
        return tuple(state_rows(s, rows, None if part is None else p) for s, p in zip(state, part or state))
    if part is None:
        return state[torch.as_tensor(rows)]
    return state.index_put((torch.as_tensor(rows),), part)


def drive_races(agents: list, args, eval_envs, policy: str | None = None, seeds=None,
                records: list | None = None) -> dict:  # fmt: skip
    """Races with `policy` (default --eval-policy), one per track of `seeds` (default: the held-out eval_seed + i,
    i < eval_episodes): every reading (READINGS) per race and car, each an (E, N) array. `records`, if given,
    receives each race's cars as CarEpisodes, as training stores them."""
    if eval_envs.num_envs != len(agents):
        raise ValueError(f"drive_races drives one race at a time: eval_envs holds {eval_envs.num_envs} slots for "
                         f"{len(agents)} agents (one race of one car per agent)")  # fmt: skip
    policy = policy or args.eval_policy
    seeds = [args.eval_seed + e for e in range(args.eval_episodes)] if seeds is None else list(seeds)
    out = {key: np.zeros((len(seeds), len(agents))) for key in READINGS}
    for e, seed in enumerate(seeds):
        eval_envs.seed(seed)
        [race], _ = Races(agents, args, eval_envs, eval_envs.reset()).drive([policy] * len(agents))
        for key in READINGS:
            out[key][e] = race.readings[key]
        if records is not None:
            records.append(race.cars)
    return out
