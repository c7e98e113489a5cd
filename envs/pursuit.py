"""A scripted pure-pursuit driver for ``MultiCarRacing`` (docs/environment.md).

It steers towards a point on the track centre line a fixed distance ahead (pure pursuit:
curvature ``2 * lateral / distance^2``) and holds a target speed, slowing for sharp bends
ahead. It reads the car's true state from the env, so it is an oracle, not an agent: the
tests use it to produce laps, ranks and ghosts with known outcomes, ``race.py`` uses it as
a baseline opponent, and the learning benchmark uses it as the "competent driver" score.
"""

from __future__ import annotations

import math

import numpy as np

from envs.multi_car_racing import MultiCarRacing

WHEELBASE = (80 + 82) * 0.02  # gymnasium car_dynamics: front and rear axle at +80 / -82 * SIZE
MAX_STEER_ANGLE = 0.4  # the wheel joints' limit (radians). An action s asks gymnasium's car for a wheel angle of s
# radians (full lock from |s| = 0.4), so steering with angle / MAX_STEER_ANGLE is a gain of 2.5 on pure pursuit's
# angle: the constants below were tuned with that gain, and the reference scores measured with it.
PLAN_POINTS = 30  # how far ahead the driver looks (points)
LOOKAHEAD_MIN = 4.0  # pure-pursuit lookahead, world units ...
LOOKAHEAD_PER_SPEED = 0.12  # ... plus this many seconds of travel
LATERAL_ACCELERATION = 100.0  # bend speed limit: v^2 * curvature (measured grip ~100)
DECELERATION = 60.0  # planned braking, world units / s^2 (measured ~120 above 50)
SPEED_GAIN = 0.1  # throttle per unit of speed error
BRAKE = 0.6  # brake strength (0.9 and above locks the wheels)
BRAKE_MARGIN = 3.0  # brake when this much faster than the plan
LANE_BEND_SHRINK = 20.0  # lane offset divided by 1 + this x heading change per point
MAX_LANE = 2.0  # lane_of's bound: at 70, +-2 finished seeds 0-29 (+-3 failed 3 on the inside)


class PursuitDriver:
    """Drives ``agent`` of ``env`` along the centre line (shifted sideways by ``lane``
    world units, positive to the right) at up to ``target_speed``.

    ``act()`` returns an action for the env's action mode; call it once per step while the
    car is racing. The speed plan slows for bends ahead within braking distance; in
    throttle-brake mode it brakes with a ``u`` inside the braking range of any dead zone.
    """

    def __init__(self, env: MultiCarRacing, agent: str, target_speed: float = 70.0, lane: float = 0.0):
        if target_speed <= 0:
            raise ValueError(f"target_speed must be positive, got {target_speed}")
        self.env = env
        self.agent = agent
        self.target_speed = float(target_speed)
        self.lane = float(lane)

    def act(self) -> np.ndarray:
        state = self.env.car_state(self.agent)
        n = self.env.num_tiles
        beta = self.env.track[:, 1]
        position, angle, speed = state["position"], state["angle"], state["speed"]
        # the lane narrows towards the centre line in bends, where corner cutting needs the room
        turn = np.abs(np.angle(np.exp(1j * (beta - np.roll(beta, 1)))))
        lane = self.lane / (1.0 + LANE_BEND_SHRINK * np.maximum(turn, np.roll(turn, -3)))
        track = self.env.track_xy + lane[:, None] * np.stack([np.cos(beta), np.sin(beta)], axis=1)
        here = state["tile"] if state["tile"] >= 0 else int(np.argmin(np.sum((track - position) ** 2, axis=1)))
        window = (here + np.arange(0, PLAN_POINTS)) % n

        # Pure pursuit: the first path point at least `lookahead` away, ahead of us.
        lookahead = LOOKAHEAD_MIN + LOOKAHEAD_PER_SPEED * speed
        ahead = track[window[1:]]
        dist = np.hypot(*(ahead - position).T)
        target = ahead[min(int(np.argmax(dist > lookahead)), len(ahead) - 1)]
        c, s = math.cos(angle), math.sin(angle)
        dx, dy = target - position
        lateral, forward = dx * c + dy * s, -dx * s + dy * c  # car frame: x right, y forward
        curvature = 2.0 * lateral / max(lateral**2 + forward**2, 1e-6)
        steer = float(np.clip(math.atan(WHEELBASE * curvature) / MAX_STEER_ANGLE, -1.0, 1.0))

        # Speed plan: each bend ahead allows sqrt(a_lat / curvature), plus what braking can
        # shed over the distance to it.
        segment = np.maximum(np.hypot(*np.diff(track[window], axis=0).T), 1e-3)  # shorter inside a bend
        bend = np.abs(np.diff(np.unwrap(beta[window]))) / segment
        bend_speed = np.sqrt(LATERAL_ACCELERATION / np.maximum(bend, 1e-6))
        distance = np.concatenate([[0.0], np.cumsum(segment[:-1])])
        allowed = np.sqrt(bend_speed**2 + 2.0 * DECELERATION * distance)
        error = min(self.target_speed, float(np.min(allowed))) - speed

        braking = error < -BRAKE_MARGIN
        # rear-wheel drive: gas while steering hard makes the car spin, so steering cuts the gas
        gas = float(np.clip(SPEED_GAIN * error, 0.0, 1.0)) * (1.0 - abs(steer))
        if self.env.action_mode == "classic":
            return np.array([steer, gas, BRAKE if braking else 0.0], dtype=np.float32)
        u = min(self.env.dead_zone, -BRAKE) if braking else gas
        return np.array([steer, u], dtype=np.float32)


def lane_of(env: MultiCarRacing, agent: str) -> float:
    """Signed sideways offset of the car from the centre line (positive: right of it), e.g.
    its start-grid column, so drivers of different speeds overtake instead of colliding;
    clipped to +-MAX_LANE, the widest lane the driver holds on every tested track."""
    state = env.car_state(agent)
    tile = (
        state["tile"] if state["tile"] >= 0 else int(np.argmin(np.sum((env.track_xy - state["position"]) ** 2, axis=1)))
    )
    beta = env.track[tile, 1]
    offset = float(np.dot(state["position"] - env.track_xy[tile], [math.cos(beta), math.sin(beta)]))
    return float(np.clip(offset, -MAX_LANE, MAX_LANE))


def drive_race(env: MultiCarRacing, speeds: dict[str, float], seed: int | None = None, options=None):
    """Run one race with a pursuit driver per agent (``speeds``: agent -> target speed).

    Returns ``(total_rewards, last_infos, steps)``; every agent of the env must have a speed.
    """
    env.reset(seed=seed, options=options)
    drivers = {a: PursuitDriver(env, a, speeds[a]) for a in env.possible_agents}
    totals = {a: 0.0 for a in env.possible_agents}
    last_infos = {}
    steps = 0
    while env.agents:
        actions = {a: drivers[a].act() for a in env.agents}
        _, rewards, _, _, infos = env.step(actions)
        for a, r in rewards.items():
            totals[a] += r
        last_infos.update(infos)
        steps += 1
    return totals, last_infos, steps
