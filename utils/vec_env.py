"""Stable-Baselines3 ``VecEnv`` over PettingZoo ``ParallelEnv`` races: every agent of every race is one slot.

``K`` races of ``N`` agents each give ``K * N`` slots; slot ``k * N + j`` is agent ``possible_agents[j]``
of race ``k``. Each slot behaves like one SB3 sub-environment: a scalar reward and a boolean done per
step, with SB3's auto-reset conventions. What differs from a single-agent env is that an agent can be
out while its race goes on:

- The step an agent goes out (terminated or truncated), its slot reports ``done=True`` once, with
  ``infos[i]["terminal_observation"]`` (its last real observation) and
  ``infos[i]["TimeLimit.truncated"] = truncated and not terminated``. The returned observation is a
  zero observation (or, if the race ended with that step, the first observation of the next race).
- After that, until its race resets, the slot returns a zero observation, zero reward,
  ``done=False`` and ``infos[i]["alive"] = False``. Actions given for it are ignored.
- When the last agent of a race is out, the race resets at once (SB3 convention): the observations
  returned by that step are the first observations of the new race, the done slots carry
  ``terminal_observation``, and every slot of that race has ``infos[i]["is_first"] = True``.

Every info dict has the keys:

- ``"alive"``: the agent took part in this step, so its reward and done are real (True also on the
  step it goes out; False for slots whose agent was already out);
- ``"is_first"``: the returned observation is the first of a new race (after ``reset()`` or an
  auto-reset);
- ``"TimeLimit.truncated"``: as in SB3 (False unless the agent was truncated this step);

plus the env's own per-agent info, passed through. ``reset()`` returns only observations, as in SB3;
its infos (the env's reset infos with ``"alive"`` and ``"is_first": True``) are kept in
``reset_infos``, which auto-resets update too. A slot's returned observation is real exactly when
``(alive and not done) or is_first`` (after ``reset()``: for the agents the env has, ``alive``).

With ``num_agents=1`` each slot is exactly an SB3 sub-environment (every done ends the race), so SB3's
own algorithms train on it. With more agents, a slot is done only once per race (when its car goes out), so
``VecMonitor`` counts the steps its car then spends out in that slot's next episode.
"""

from __future__ import annotations

import importlib
import multiprocessing as mp
import traceback
import warnings
from collections.abc import Callable, Sequence
from copy import deepcopy
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn

#: Environment ids known to :func:`make_vec_env`, mapped to their ``"module:attribute"`` entry point.
ENV_IDS: dict[str, str] = {
    "multi_car_racing": "envs.multi_car_racing:MultiCarRacing",
    "highway-intersection": "envs.highway:HighwayIntersection",
}


class EnvFactory:
    """A picklable constructor: imports ``entry_point`` (``"module:attribute"``) and calls it with ``kwargs``.

    Worker processes receive the factory, not an env: pickling it sends only the entry-point string and
    the keyword arguments, and the worker imports the env module itself.

    :param entry_point: ``"package.module:ClassOrFunction"``
    :param kwargs: keyword arguments for the constructor
    """

    def __init__(self, entry_point: str, kwargs: dict[str, Any] | None = None):
        module, sep, attribute = entry_point.partition(":")
        if not sep or not module or not attribute:
            raise ValueError(f"entry_point must look like 'module:attribute', got {entry_point!r}")
        self.entry_point = entry_point
        self.kwargs = dict(kwargs or {})

    def __call__(self) -> ParallelEnv:
        module, _, attribute = self.entry_point.partition(":")
        return getattr(importlib.import_module(module), attribute)(**self.kwargs)

    def __repr__(self) -> str:
        return f"EnvFactory({self.entry_point!r}, {self.kwargs!r})"


def _shared_spaces(env: ParallelEnv) -> tuple[spaces.Space, spaces.Space]:
    """The observation and action space shared by all ``possible_agents`` of ``env``.

    :raises ValueError: if agents differ in their spaces, or observations have no fixed shape and dtype
    """
    agents = list(env.possible_agents)
    if not agents:
        raise ValueError(f"{env} has no possible_agents")
    observation_space, action_space = env.observation_space(agents[0]), env.action_space(agents[0])
    for agent in agents[1:]:
        if env.observation_space(agent) != observation_space or env.action_space(agent) != action_space:
            raise ValueError(
                f"every agent must share one observation space and one action space; {agent!r} has "
                f"{env.observation_space(agent)}, {env.action_space(agent)} but {agents[0]!r} has "
                f"{observation_space}, {action_space}"
            )
    if observation_space.shape is None or observation_space.dtype is None:
        raise ValueError(
            f"observation space {observation_space} has no fixed shape and dtype (Dict/Tuple spaces are not supported)"
        )
    return observation_space, action_space


class _RaceSlots:
    """One ``ParallelEnv`` seen as ``N`` slots, with the per-slot bookkeeping of the module docstring.

    Lives in the main process, or in a worker process in subprocess mode, so that a step is one
    round trip there.
    """

    def __init__(self, env: ParallelEnv):
        self.env = env
        self.agents = list(env.possible_agents)
        self.observation_space, self.action_space = _shared_spaces(env)
        self.zero_obs = np.zeros(self.observation_space.shape, dtype=self.observation_space.dtype)
        self.alive = np.zeros(len(self.agents), dtype=bool)

    def _stack(self, observations: dict[str, Any], present: np.ndarray) -> np.ndarray:
        out = np.zeros((len(self.agents), *self.zero_obs.shape), dtype=self.zero_obs.dtype)
        for j, agent in enumerate(self.agents):
            if present[j]:
                out[j] = observations[agent]
        return out

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, list[dict]]:
        """Reset the race: stacked first observations (N, ...) and the reset infos of the N slots."""
        observations, env_infos = self.env.reset(seed=seed, options=options)
        live = set(self.env.agents)
        self.alive = np.array([agent in live for agent in self.agents], dtype=bool)
        infos = [
            {**env_infos.get(agent, {}), "alive": bool(alive), "is_first": True}
            for agent, alive in zip(self.agents, self.alive, strict=True)
        ]
        return self._stack(observations, self.alive), infos

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict], list[dict] | None]:
        """Step the race with the actions of its N slots (those of slots that are out are ignored).

        :return: observations (N, ...), rewards (N,) float32, dones (N,) bool, infos, and the reset
            infos of the new race if the race ended and was reset in this step (else ``None``)
        """
        live = set(self.env.agents)
        env_actions = {agent: actions[j] for j, agent in enumerate(self.agents) if agent in live}
        observations, env_rewards, terminations, truncations, env_infos = self.env.step(env_actions)
        still_in = set(self.env.agents)

        n = len(self.agents)
        rewards = np.zeros(n, dtype=np.float32)
        dones = np.zeros(n, dtype=bool)
        infos: list[dict] = []
        acted = self.alive.copy()
        for j, agent in enumerate(self.agents):
            info = dict(env_infos.get(agent, {}))
            info["alive"] = bool(acted[j])
            info["is_first"] = False
            info["TimeLimit.truncated"] = False
            if acted[j]:
                terminated, truncated = bool(terminations.get(agent, False)), bool(truncations.get(agent, False))
                if not (terminated or truncated) and agent not in still_in:
                    raise RuntimeError(f"agent {agent!r} left the race without being terminated or truncated")
                rewards[j] = env_rewards.get(agent, 0.0)
                info["TimeLimit.truncated"] = truncated and not terminated
                if terminated or truncated:
                    dones[j] = True
                    info["terminal_observation"] = np.array(observations[agent], dtype=self.zero_obs.dtype, copy=True)
                    self.alive[j] = False
            elif agent in still_in:
                raise RuntimeError(
                    f"agent {agent!r} is live in the env but its slot is out (done earlier, or absent at reset): "
                    "PettingZoo envs drop done agents, and slots do not support agents joining mid-race"
                )
            infos.append(info)

        if self.alive.any():
            return self._stack(observations, self.alive), rewards, dones, infos, None
        first_obs, reset_infos = self.reset()
        for info in infos:
            info["is_first"] = True
        return first_obs, rewards, dones, infos, reset_infos

    def render(self) -> Any:
        return self.env.render()

    def is_wrapped(self, wrapper_class: type) -> bool:
        """Whether ``wrapper_class`` is anywhere in the chain ``env, env.env, env.env.env, ...``."""
        env, seen = self.env, set()
        while env is not None and id(env) not in seen:
            if isinstance(env, wrapper_class):
                return True
            seen.add(id(env))
            env = getattr(env, "env", None)
        return False

    def execute(self, command: str, data: Any) -> Any:
        """Run one command of the worker protocol (also used in-process)."""
        if command == "step":
            return self.step(data)
        if command == "reset":
            return self.reset(*data)
        if command == "render":
            return self.render()
        if command == "get_attr":
            return getattr(self.env, data)
        if command == "set_attr":
            return setattr(self.env, data[0], data[1])
        if command == "env_method":
            name, args, kwargs = data
            return getattr(self.env, name)(*args, **kwargs)
        if command == "is_wrapped":
            return self.is_wrapped(data)
        if command == "spaces":
            return self.observation_space, self.action_space, self.agents
        if command == "close":
            return self.env.close()
        raise NotImplementedError(f"unknown command {command!r}")


def _worker(remote: Any, parent_remote: Any, env_fn: Callable[[], ParallelEnv]) -> None:
    """Worker process main loop: build the race from ``env_fn`` and serve commands until ``close``.

    Every answer is ``("ok", result)`` or ``("error", (exception, traceback text))``; the first answer
    reports whether the env could be built.
    """
    parent_remote.close()
    try:
        race = _RaceSlots(env_fn())
    except Exception as exc:  # report construction errors instead of dying silently
        _send_error(remote, exc)
        return
    remote.send(("ok", None))
    while True:
        try:
            command, data = remote.recv()
        except (EOFError, KeyboardInterrupt):
            break
        try:
            remote.send(("ok", race.execute(command, data)))
        except Exception as exc:
            _send_error(remote, exc)
        if command == "close":
            remote.close()
            break


def _send_error(remote: Any, exc: Exception) -> None:
    text = traceback.format_exc()
    try:
        remote.send(("error", (exc, text)))
    except Exception:  # the exception itself does not pickle
        remote.send(("error", (RuntimeError(str(exc)), text)))


class _LocalRace:
    """In-process race handle: ``request`` runs the command, ``result`` returns (or raises) its outcome."""

    def __init__(self, env_fn: Callable[[], ParallelEnv]):
        self.race = _RaceSlots(env_fn())
        self._outcome: tuple[bool, Any] = (True, None)

    def request(self, command: str, data: Any = None) -> None:
        try:
            self._outcome = (True, self.race.execute(command, data))
        except Exception as exc:
            self._outcome = (False, exc)

    def result(self) -> Any:
        ok, value = self._outcome
        self._outcome = (True, None)
        if not ok:
            raise value
        return value

    def stop(self) -> None:
        pass


class _WorkerRace:
    """Race handle served by a worker process: ``request`` sends a command, ``result`` waits for its answer."""

    def __init__(self, env_fn: Callable[[], ParallelEnv], context: Any, index: int):
        self.index = index
        self.remote, work_remote = context.Pipe()
        self.process = context.Process(target=_worker, args=(work_remote, self.remote, env_fn), daemon=True)
        self.process.start()
        work_remote.close()

    def request(self, command: str, data: Any = None) -> None:
        self.remote.send((command, data))

    def result(self) -> Any:
        try:
            status, payload = self.remote.recv()
        except EOFError as exc:
            raise RuntimeError(
                f"the worker process of race {self.index} died (exit code {self.process.exitcode})"
            ) from exc
        if status == "error":
            exc, text = payload
            exc.add_note(f"raised in the worker process of race {self.index}:\n{text}")
            raise exc
        return payload

    def stop(self) -> None:
        self.process.join(timeout=5)
        if self.process.is_alive():
            self.process.terminate()
        self.remote.close()


class MultiAgentVecEnv(VecEnv):
    """SB3 ``VecEnv`` presenting every agent of ``len(env_fns)`` PettingZoo races as one slot.

    See the module docstring for the slot semantics. All agents of all races must share one
    observation space and one action space; every race must have the same ``possible_agents``.

    :param env_fns: one callable per race, each returning a new ``ParallelEnv``. With
        ``use_subprocess=True`` they are pickled to the workers, so they must be importable
        (a module-level class or function, a ``functools.partial`` of one, or an :class:`EnvFactory`);
        the worker then imports the env module itself.
    :param use_subprocess: run each race in its own worker process (one step is then one round trip
        per race, all races stepping in parallel)
    :param start_method: multiprocessing start method of the workers, ``"forkserver"`` (default where
        available) or ``"spawn"``; ``"fork"`` is refused (not thread-safe, see SB3's ``SubprocVecEnv``)
    """

    def __init__(
        self,
        env_fns: Sequence[Callable[[], ParallelEnv]],
        use_subprocess: bool = False,
        start_method: str | None = None,
    ):
        if len(env_fns) == 0:
            raise ValueError("env_fns is empty: need at least one race")
        self.use_subprocess = use_subprocess
        self.closed = False
        self.waiting = False
        if use_subprocess:
            if start_method is None:
                start_method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
            if start_method not in ("forkserver", "spawn"):
                raise ValueError(f"start_method must be 'forkserver' or 'spawn', got {start_method!r}")
            context = mp.get_context(start_method)
            if start_method == "forkserver":
                # The fork server imports this module (and so SB3 and torch) once; every worker forked
                # from it starts with it loaded. No effect if the fork server is already running.
                context.set_forkserver_preload([__name__])
            self._races: list[_LocalRace | _WorkerRace] = [_WorkerRace(fn, context, k) for k, fn in enumerate(env_fns)]
            try:
                for race in self._races:
                    race.result()  # construction outcome
            except BaseException:
                for race in self._races:
                    race.process.terminate()
                raise
        else:
            self._races = [_LocalRace(fn) for fn in env_fns]

        layouts = self._call("spaces", None, range(len(self._races)))
        observation_space, action_space, agents = layouts[0]
        for k, layout in enumerate(layouts[1:], start=1):
            if layout[2] != agents or layout[0] != observation_space or layout[1] != action_space:
                self.close()
                raise ValueError(f"race {k} has agents/spaces {layout}, race 0 has {layouts[0]}: all races must match")
        #: agent names of one race, in slot order
        self.agents: list[str] = list(agents)
        self.num_races = len(self._races)
        self.num_agents = len(self.agents)
        super().__init__(self.num_races * self.num_agents, observation_space, action_space)
        fps = 30
        try:
            fps = self._call("get_attr", "metadata", [0])[0].get("render_fps", 30)
        except AttributeError:
            pass
        self.metadata = {**self.metadata, "render_fps": fps}
        self._actions: np.ndarray | None = None

    # ----------------------------------------------------------------- slot <-> race
    def race_of(self, slot: int) -> int:
        """Index of the race that slot ``slot`` belongs to."""
        return slot // self.num_agents

    def slots_of(self, race: int) -> range:
        """Slot indices of race ``race``."""
        return range(race * self.num_agents, (race + 1) * self.num_agents)

    def _races_of(self, indices: VecEnvIndices) -> tuple[list[int], list[int]]:
        """The requested slots and the distinct races they belong to (in first-seen order)."""
        slots = [int(i) for i in self._get_indices(indices)]
        for slot in slots:
            if not 0 <= slot < self.num_envs:
                raise IndexError(f"slot {slot} out of range for {self.num_envs} slots")
        races = list(dict.fromkeys(self.race_of(slot) for slot in slots))
        return slots, races

    def _call(self, command: str, data: Any, races: Sequence[int] | range) -> list[Any]:
        """Send ``command`` to the given races (all at once), then collect their results in order."""
        for k in races:
            self._races[k].request(command, data)
        results, error = [], None
        for k in races:
            try:
                results.append(self._races[k].result())
            except Exception as exc:  # collect every answer first, so the pipes stay in sync
                error = error or exc
                results.append(None)
        if error is not None:
            raise error
        return results

    # ----------------------------------------------------------------- VecEnv API
    def seed(self, seed: int | None = None) -> Sequence[int | None]:
        """Seeds for the next ``reset()``: race ``k`` is reset with ``seed + k`` (SB3: used once, at the next reset).

        :param seed: base seed; ``None`` draws one at random (as SB3 does)
        :return: the seed of every slot (the seed of its race)
        """
        if seed is None:
            seed = int(np.random.randint(0, np.iinfo(np.uint32).max, dtype=np.uint32))
        self._seeds = [seed + self.race_of(i) for i in range(self.num_envs)]
        return list(self._seeds)

    def set_options(self, options: list[dict] | dict | None = None) -> None:
        """Options for the next ``reset()``: one dict for every race, or a list with one dict per race."""
        if options is None:
            options = {}
        if isinstance(options, dict):
            options = [options] * self.num_races
        if len(options) != self.num_races:
            raise ValueError(f"expected one options dict per race ({self.num_races}), got {len(options)}")
        self._options = [deepcopy(options[self.race_of(i)]) for i in range(self.num_envs)]

    def reset(self) -> VecEnvObs:
        """Reset every race (with the seeds of :meth:`seed` and options of :meth:`set_options`, used once).

        :return: observations of all slots; infos are in ``reset_infos``
        """
        if self.waiting:
            for race in self._races:  # drain the pending step so the pipes stay in sync
                race.result()
            self.waiting = False
        for k, race in enumerate(self._races):
            first = k * self.num_agents
            race.request("reset", (self._seeds[first], self._options[first] or None))
        results = [race.result() for race in self._races]
        self._reset_seeds()
        self._reset_options()
        self.reset_infos = [info for _, infos in results for info in infos]
        return np.concatenate([obs for obs, _ in results])

    def step_async(self, actions: np.ndarray) -> None:
        """Send the actions of all slots (``len(actions) == num_envs``; actions of slots that are out are ignored)."""
        if len(actions) != self.num_envs:
            raise ValueError(f"expected actions for {self.num_envs} slots, got {len(actions)}")
        n = self.num_agents
        for k, race in enumerate(self._races):
            race.request("step", np.asarray(actions[k * n : (k + 1) * n]))
        self.waiting = True

    def step_wait(self) -> VecEnvStepReturn:
        """Wait for the races: observations, rewards (float32), dones (bool) and infos of all slots."""
        results, error = [], None
        for race in self._races:
            try:
                results.append(race.result())
            except Exception as exc:
                error = error or exc
        self.waiting = False
        if error is not None:
            raise error
        infos: list[dict] = []
        for k, (_, _, _, race_infos, reset_infos) in enumerate(results):
            infos.extend(race_infos)
            if reset_infos is not None:
                self.reset_infos[k * self.num_agents : (k + 1) * self.num_agents] = reset_infos
        observations = np.concatenate([r[0] for r in results])
        rewards = np.concatenate([r[1] for r in results])
        dones = np.concatenate([r[2] for r in results])
        return observations, rewards, dones, infos

    def close(self) -> None:
        """Close every race (and stop the worker processes)."""
        if self.closed:
            return
        if self.waiting:
            for race in self._races:
                try:
                    race.result()
                except Exception:
                    pass
        for race in self._races:
            try:
                race.request("close")
                race.result()
            except Exception:
                pass
            race.stop()
        self.closed = True

    def get_images(self) -> Sequence[np.ndarray | None]:
        """One ``render()`` frame per race (not per slot), in race order.

        ``VecEnv.render()`` tiles them, so ``VecVideoRecorder`` records every race exactly once, and a
        single race (``num_races=1``) as its own frame.
        """
        if self.render_mode != "rgb_array":
            warnings.warn(f"The render mode is {self.render_mode}, but get_images() needs 'rgb_array'.")
            return [None for _ in range(self.num_races)]
        return self._call("render", None, range(self.num_races))

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """Attribute of the env behind each requested slot (each race is asked once; its slots share the value)."""
        slots, races = self._races_of(indices)
        values = dict(zip(races, self._call("get_attr", attr_name, races), strict=True))
        return [values[self.race_of(slot)] for slot in slots]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        """Set an attribute on the env of every race that has a requested slot (once per race)."""
        _, races = self._races_of(indices)
        self._call("set_attr", (attr_name, value), races)

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs) -> list[Any]:
        """Call a method of the env of every race that has a requested slot, once per race.

        E.g. ``venv.env_method("set_dead_zone", -0.8)`` schedules the racing env's dead zone.

        :return: per requested slot, the return value of its race's call
        """
        slots, races = self._races_of(indices)
        results = self._call("env_method", (method_name, method_args, method_kwargs), races)
        values = dict(zip(races, results, strict=True))
        return [values[self.race_of(slot)] for slot in slots]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        """Whether the env behind each requested slot is (or wraps) an instance of ``wrapper_class``."""
        slots, races = self._races_of(indices)
        values = dict(zip(races, self._call("is_wrapped", wrapper_class, races), strict=True))
        return [values[self.race_of(slot)] for slot in slots]


def make_vec_env(
    env_id: str,
    num_races: int,
    seed: int | None,
    use_subprocess: bool = False,
    start_method: str | None = None,
    **env_kwargs: Any,
) -> MultiAgentVecEnv:
    """Build a :class:`MultiAgentVecEnv` of ``num_races`` races of a known environment.

    :param env_id: a key of :data:`ENV_IDS`: ``"multi_car_racing"`` builds
        ``envs.multi_car_racing.MultiCarRacing(**env_kwargs)``, ``"highway-intersection"`` builds
        ``envs.highway.HighwayIntersection(**env_kwargs)``
    :param num_races: number of races ``K`` (the env has ``K * num_agents`` slots)
    :param seed: race ``k`` is reset with ``seed + k`` at the first ``reset()``; ``None``: unseeded
    :param use_subprocess: one worker process per race (each worker imports the env module itself)
    :param start_method: ``"forkserver"`` (default where available) or ``"spawn"``
    :param env_kwargs: keyword arguments of the env constructor
    :raises ValueError: for an unknown ``env_id`` or ``num_races < 1``
    """
    if env_id not in ENV_IDS:
        raise ValueError(f"unknown env_id {env_id!r}; known ids: {', '.join(sorted(ENV_IDS))}")
    if num_races < 1:
        raise ValueError(f"num_races must be >= 1, got {num_races}")
    factory = EnvFactory(ENV_IDS[env_id], env_kwargs)
    venv = MultiAgentVecEnv([factory] * num_races, use_subprocess=use_subprocess, start_method=start_method)
    if seed is not None:
        venv.seed(seed)
    return venv
