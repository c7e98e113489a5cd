"""Regenerate the env images of the README and docs/environment.md: ``python docs/make_env_images.py``."""

import argparse
import os
import sys

import cv2
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
from envs import MultiCarRacing  # noqa: E402
from envs.pursuit import PursuitDriver  # noqa: E402


def save(path, rgb):
    cv2.imwrite(path, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    print("wrote", path)


def main(seed=3, steps=140, out=HERE):
    """Two pursuit drivers race `steps` steps on track `seed`; their two views and the rgb_array frame go to `out`."""
    env = MultiCarRacing(num_agents=2, render_mode="rgb_array")
    env.reset(seed=seed)
    drivers = {
        "car_0": PursuitDriver(env, "car_0", 70.0, lane=-2.0),
        "car_1": PursuitDriver(env, "car_1", 55.0, lane=2.0),
    }
    for _ in range(steps):
        obs, *_ = env.step({a: drivers[a].act() for a in env.agents})
    views = np.concatenate([obs["car_0"], np.zeros((96, 4, 3), np.uint8), obs["car_1"]], axis=1)
    save(os.path.join(out, "views.png"), cv2.resize(views, None, fx=3, fy=3, interpolation=cv2.INTER_NEAREST))
    save(os.path.join(out, "race_frame.png"), env.render())


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seed", type=int, default=3, help="track seed")
    parser.add_argument("--steps", type=int, default=140, help="steps driven before the pictures are taken")
    parser.add_argument("--out", default=HERE, help="directory of views.png and race_frame.png")
    args = parser.parse_args()
    main(args.seed, args.steps, args.out)
