"""Environments: the multi-car race (PettingZoo), its single-car gymnasium view, the
pure-pursuit driver and the highway-env scenario (imported on demand: it needs highway-env)."""

import gymnasium

from envs.multi_car_racing import GhostTrajectory, MultiCarRacing, SingleCarRacing, ghost_beaten, race_winners

SINGLE_CAR_ID = "dlc/SingleCarRacing-v0"

if SINGLE_CAR_ID not in gymnasium.registry:
    # Truncation at max_steps happens inside the env, so no TimeLimit wrapper is added.
    gymnasium.register(id=SINGLE_CAR_ID, entry_point="envs.multi_car_racing:SingleCarRacing")

__all__ = ["MultiCarRacing", "SingleCarRacing", "GhostTrajectory", "ghost_beaten", "race_winners", "SINGLE_CAR_ID"]
