"""Seeded fuzzing of MultiCarRacing.step with bad input (docs/environment.md, bad input).

Every bad call (NaN, inf, wrong shape, wrong dtype such as strings, bytes, objects, complex numbers or
booleans, missing or unknown agents, an agent that is out, not a dict) must raise ValueError and leave
the race exactly as it was: after it, the next valid step continues the same race as a twin env that
only ever saw the valid actions (observations, rewards, terminations, truncations and infos equal).
Valid actions come in many forms (lists, tuples, int/float16/float32 arrays, huge finite values that
are clipped); the twin gets the same action as float64, clipped to the action space.
"""

from __future__ import annotations

import numpy as np
import pytest

from conftest import assert_same
from envs import MultiCarRacing


# --- bad actions for one agent (each must be refused) ------------------------------------------
def _nan(rng):
    a = rng.uniform(-1, 1, 2)
    a[rng.integers(2)] = np.nan
    return a


def _inf(rng):
    a = rng.uniform(-1, 1, 2).tolist()
    a[rng.integers(2)] = float(rng.choice([np.inf, -np.inf]))
    return a


BAD_ACTIONS = {
    "nan": _nan,
    "inf": _inf,
    "nan_float32": lambda rng: np.array([np.nan, 0.0], dtype=np.float32),
    "scalar": lambda rng: float(rng.uniform(-1, 1)),
    "0-d array": lambda rng: np.array(0.5),
    "too short": lambda rng: [0.1],
    "too long": lambda rng: rng.uniform(-1, 1, 3),
    "empty": lambda rng: [],
    "2-d": lambda rng: rng.uniform(-1, 1, (1, 2)),
    "ragged": lambda rng: [0.1, [0.2]],
    "string": lambda rng: "fast",
    "strings": lambda rng: ["0.5", "0.1"],
    "bytes": lambda rng: b"\x00\x01",
    "None": lambda rng: None,
    "Nones": lambda rng: [None, None],
    "object": lambda rng: object(),
    "object array": lambda rng: np.array([0.1, 0.2], dtype=object),
    "dict": lambda rng: {"steer": 0.1, "throttle": 0.5},
    "set": lambda rng: {0.1, 0.2},
    "complex": lambda rng: [0.1 + 1j, 0.5],
    "complex array": lambda rng: np.array([0.1, 0.5], dtype=np.complex128),
    "complex, zero imaginary": lambda rng: np.array([0.1 + 0j, 0.5 + 0j]),
    "bool array": lambda rng: np.array([True, False]),
    "bools in a list": lambda rng: [True, 0.5],
    "python int beyond float64": lambda rng: [10**400, 0],
    "datetime": lambda rng: np.array(["2024-01-01", "2024-01-02"], dtype="datetime64[D]"),
}

# --- bad calls as a whole -----------------------------------------------------------------------
UNKNOWN_AGENTS = ["car_9", "CAR_0", "car_-1", 0, None, ("car_0",), 1.5]
REFUSED_WHOLE = {"unknown agent": "unknown agent", "not a dict": "actions must be a dict"}  # named no live agent
NOT_A_DICT = [None, "car_0", [np.zeros(2), np.zeros(2)], (np.zeros(2),), np.zeros((2, 2)), 3, {("car_0", 0.0)}]


def valid_action(rng) -> tuple[object, np.ndarray]:
    """A valid action in a random form, and what the twin gets: the same values as float64, clipped."""
    values = rng.uniform(-1.2, 1.2, 2)
    form = rng.integers(7)
    if form == 0:
        action = values.tolist()
    elif form == 1:
        action = tuple(values.tolist())
    elif form == 2:
        action = values.astype(np.float32)
    elif form == 3:
        action = values.astype(np.float16)
    elif form == 4:
        action = np.array([rng.integers(-3, 4), rng.integers(-3, 4)])  # ints, clipped
    elif form == 5:
        action = values * rng.choice([1e6, 1e300])  # huge but finite: clipped
    else:
        action = values
    twin = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
    return action, twin


def bad_call(rng, env, good: dict) -> tuple[str, object, str | None]:
    """One call that must be refused: (kind, actions, the agent its message must name or None)."""
    live = list(env.agents)
    victim = live[rng.integers(len(live))]
    kind = rng.choice(["action", "missing", "unknown", "out", "not a dict"], p=[0.6, 0.1, 0.1, 0.1, 0.1])
    if kind == "out":
        out = [a for a in env.possible_agents if a not in env.agents]
        if not out:
            kind = "action"
        else:
            return "agent out", {**good, out[0]: np.zeros(2)}, out[0]
    if kind == "action":
        name = list(BAD_ACTIONS)[rng.integers(len(BAD_ACTIONS))]
        return name, {**good, victim: BAD_ACTIONS[name](rng)}, victim
    if kind == "missing":
        return "missing agent", {a: v for a, v in good.items() if a != victim}, victim
    if kind == "unknown":
        key = UNKNOWN_AGENTS[rng.integers(len(UNKNOWN_AGENTS))]
        return "unknown agent", {**good, key: np.zeros(2)}, None
    return "not a dict", NOT_A_DICT[rng.integers(len(NOT_A_DICT))], None


@pytest.mark.parametrize("seed", [0, 1])
def test_bad_calls_never_change_the_race(seed):
    rng = np.random.default_rng(seed)
    fuzzed = MultiCarRacing(num_agents=2, max_steps=120, stall_steps=60)
    twin = MultiCarRacing(num_agents=2, max_steps=120, stall_steps=60)
    track = 100 * seed
    assert_same(fuzzed.reset(seed=track), twin.reset(seed=track), "reset")
    kinds, races, steps = set(), 1, 0
    while steps < 400:
        actions, twin_actions = {}, {}
        for agent in fuzzed.agents:
            actions[agent], twin_actions[agent] = valid_action(rng)
        for _ in range(rng.integers(0, 4)):  # up to three refused calls before the valid one
            kind, bad, named = bad_call(rng, fuzzed, actions)
            with pytest.raises(ValueError) as refused:
                fuzzed.step(bad)
            expected = named if named is not None else REFUSED_WHOLE[kind]
            assert expected in str(refused.value), (kind, str(refused.value))
            kinds.add(kind)
        assert_same(fuzzed.step(actions), twin.step(twin_actions), f"race {races} step {fuzzed.step_count}")
        steps += 1
        if not fuzzed.agents:
            assert not twin.agents
            with pytest.raises(RuntimeError, match="race is over"):  # a finished race refuses steps, and
                fuzzed.step({})  # that refusal changes nothing either: the race as recorded is the twin's
            assert fuzzed.step_count == twin.step_count
            assert all(fuzzed.trajectory(a) == twin.trajectory(a) for a in fuzzed.possible_agents)
            races += 1
            track += 1
            assert_same(fuzzed.reset(seed=track), twin.reset(seed=track), "reset")
    # the fuzz really covered the ground: most bad kinds, several races, a car that was out early
    assert races >= 3
    assert {"missing agent", "unknown agent", "not a dict", "agent out"} <= kinds
    assert len(kinds & set(BAD_ACTIONS)) >= len(BAD_ACTIONS) - 4


@pytest.mark.parametrize("name", sorted(BAD_ACTIONS))
def test_every_bad_action_kind_is_refused_naming_the_agent(name):
    env = MultiCarRacing(num_agents=2, max_steps=50)
    env.reset(seed=3)
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="action for car_1"):
        env.step({"car_0": np.zeros(2), "car_1": BAD_ACTIONS[name](rng)})
    assert env.step_count == 0  # refused before anything moved


def test_valid_forms_are_the_clipped_float_action():
    """Ints, float16/float32, lists and tuples, huge finite values: all drive exactly like the clipped float64."""
    rng = np.random.default_rng(5)
    a, b = MultiCarRacing(num_agents=1), MultiCarRacing(num_agents=1)
    assert_same(a.reset(seed=9), b.reset(seed=9))
    for _ in range(60):
        action, twin = valid_action(rng)
        assert_same(a.step({"car_0": action}), b.step({"car_0": twin}))
