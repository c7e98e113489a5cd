"""Multi-car racing: N cars on one CarRacing-v3 track, each seeing its own 96x96 camera.

A PettingZoo ``ParallelEnv`` (docs/environment.md). Track generation, the car model and the
50 Hz Box2D world are gymnasium's CarRacing-v3 pieces, reused as they are:

* the track is built by gymnasium's own ``CarRacing._create_track`` on this env's world,
* every car is gymnasium's ``car_dynamics.Car``.

What is written here is what multi-car racing changes: per-car tile contacts and the
competitive reward split, hull-to-hull collisions, the start grid, the paper's throttle-brake
controls (dead zone, brake speed threshold), elimination rules, ghosts (recorded runs replayed
on the same track) and a renderer that draws each 96x96 view directly from a track image
rasterised once per reset (gymnasium draws 1000x800 polygons every step and scales down).

``rules="carracing"`` with ``num_agents=1, action_mode="classic"`` reproduces CarRacing-v3
step for step (tiles, poses, rewards, termination); tests check this against gymnasium.

Physics and rules live in ``MultiCarRacing``; pixels are drawn by ``TrackRenderer``, which the
env's last section (Drawing) hands what each view shows: the cars' outlines, colours and dashboards.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import Box2D
import cv2
import gymnasium
import numpy as np
from Box2D.b2 import contactListener, fixtureDef, polygonShape
from gymnasium import spaces
from gymnasium.envs.box2d import car_dynamics
from gymnasium.envs.box2d.car_dynamics import Car
from gymnasium.envs.box2d.car_racing import (
    FPS,
    GRASS_DIM,
    PLAYFIELD,
    SCALE,
    TRACK_RAD,
    TRACK_WIDTH,
    ZOOM,
    CarRacing,
)
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

# --- Rules ------------------------------------------------------------------------------
DT = 1.0 / FPS
VELOCITY_ITERATIONS = 6 * 30  # CarRacing-v3's Box2D solver settings
POSITION_ITERATIONS = 2 * 30
TIME_PENALTY = 0.1  # paid by every racing car every step
TRACK_REWARD = 1000.0  # shared out over the tiles of one lap
LAP_COMPLETE_PERCENT = 0.95  # CarRacing's lap rule
GRID_LATERAL_OFFSET = 0.45 * TRACK_WIDTH  # start grid: two staggered columns
RULES = ("race", "carracing")
ACTION_MODES = ("throttle_brake", "classic")

# --- Collision filtering (race rules): hulls collide with hulls, wheels touch tiles -----
CATEGORY_TILE = 0x0001  # Box2D's default category, which gymnasium's tiles keep
CATEGORY_HULL = 0x0002
CATEGORY_WHEEL = 0x0020  # gymnasium's wheel category

# --- Camera (CarRacing-v3's state_pixels view) -----------------------------------------
VIEW_W = VIEW_H = 96
_CARRACING_WINDOW_W, _CARRACING_WINDOW_H = 1000, 800  # CarRacing draws here, then scales
VIEW_SCALE_X = ZOOM * SCALE * VIEW_W / _CARRACING_WINDOW_W  # pixels per world unit, across
VIEW_SCALE_Y = ZOOM * SCALE * VIEW_H / _CARRACING_WINDOW_H  # ... and along the car
VIEW_CAR_X = VIEW_W / 2  # the car sits centred, a quarter from the bottom
VIEW_CAR_Y = VIEW_H * 3 / 4
DASHBOARD_H = VIEW_H * 5 // 40  # CarRacing's indicator strip: 5/40 of the height
MAP_PIXELS_PER_UNIT = 2.0  # track image resolution, close to the view's own scale
OVERVIEW_SIZE = 400  # rgb_array frame: whole-track overview beside the car views ...
OVERVIEW_HALF_WIDTH = 1.5 * TRACK_RAD + 25  # ... of this part of the world (the track's extent)

# --- Colours (RGB) ----------------------------------------------------------------------
ROAD_COLOR = (102, 102, 102)  # CarRacing's defaults
BG_COLOR = (102, 204, 102)
GRASS_COLOR = (102, 230, 102)
EGO_COLOR = (204, 0, 0)  # CarRacing's red hull
CAR_COLORS = ((204, 0, 0), (0, 0, 204), (204, 204, 0), (204, 0, 204), (0, 204, 204), (255, 128, 0))
GHOST_COLOR = (190, 190, 255)
WHEEL_COLOR = car_dynamics.WHEEL_COLOR

# Car outlines in body coordinates, polygons stacked; *_POLYGONS: (start, end) of each.
_HULL_VERTICES = np.concatenate(
    [
        np.array(p, dtype=np.float64)
        for p in (car_dynamics.HULL_POLY1, car_dynamics.HULL_POLY2, car_dynamics.HULL_POLY3, car_dynamics.HULL_POLY4)
    ]
) * car_dynamics.SIZE
HULL_POLYGONS = ((0, 4), (4, 8), (8, 16), (16, 20))  # HULL_POLY1..4
_WHEEL_VERTICES = (
    np.array([(-1, 1), (1, 1), (1, -1), (-1, -1)], dtype=np.float64)
    * (car_dynamics.WHEEL_W, car_dynamics.WHEEL_R)
    * car_dynamics.SIZE
)
WHEEL_POLYGONS = ((0, 4), (4, 8), (8, 12), (12, 16))


# =======================================================================================
# Ghosts (docs/environment.md)
# =======================================================================================
@dataclasses.dataclass(eq=False)
class GhostTrajectory:
    """One car's recorded run on one track, replayable as a ghost on the same track seed.

    ``poses[t]`` is the hull pose ``(x, y, angle)`` after env step ``t`` (``t = 0`` is the
    pose after ``reset``). ``tile_steps[j]`` is the step at which the car first touched tile
    ``tile_ids[j]``. ``finish_step`` is the step the lap was completed, -1 if it was not.
    """

    track_seed: int
    num_tiles: int
    poses: np.ndarray
    tile_steps: np.ndarray
    tile_ids: np.ndarray
    finish_step: int

    def __eq__(self, other) -> bool:
        if not isinstance(other, GhostTrajectory):
            return NotImplemented
        return all(np.array_equal(getattr(self, f.name), getattr(other, f.name)) for f in dataclasses.fields(self))

    @property
    def tiles(self) -> int:
        """Number of tiles the car touched in the whole run."""
        return len(self.tile_ids)

    def tiles_by_step(self, step: int) -> int:
        """Number of tiles touched at or before ``step``."""
        return int(np.searchsorted(self.tile_steps, step, side="right"))

    def to_dict(self) -> dict[str, Any]:
        """Plain types and arrays only, so checkpoints load with ``weights_only=True``."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> GhostTrajectory:
        return cls(
            track_seed=int(d["track_seed"]),
            num_tiles=int(d["num_tiles"]),
            poses=np.asarray(d["poses"], dtype=np.float64).reshape(-1, 3),
            tile_steps=np.asarray(d["tile_steps"], dtype=np.int64),
            tile_ids=np.asarray(d["tile_ids"], dtype=np.int64),
            finish_step=int(d["finish_step"]),
        )


def ghost_beaten(car_finish_step: int, car_tiles: int, ghost: GhostTrajectory) -> bool:
    """The paper's ghost rule: the car beats its ghost when it finishes earlier or, if
    neither finishes, has touched more tiles by the end (``finish_step`` -1: not finished)."""
    if car_finish_step >= 0:
        return ghost.finish_step < 0 or car_finish_step < ghost.finish_step
    if ghost.finish_step >= 0:
        return False
    return car_tiles > ghost.tiles


def race_winners(final_infos: list[dict]) -> list[bool]:
    """Who won a race, from each car's last info: the cars ranked 1 (finishing first, ties
    share); if no car finished, the one car with the most tiles (a tie: nobody won)."""
    ranks = [int(info["rank"]) for info in final_infos]
    if any(r == 1 for r in ranks):
        return [r == 1 for r in ranks]
    tiles = [int(info["tiles"]) for info in final_infos]
    best = max(tiles)
    return [t == best and tiles.count(best) == 1 for t in tiles]


# =======================================================================================
# Contacts: wheels on tiles (progress, friction) and hulls on hulls (collisions)
# =======================================================================================
class _HullTag:
    """``userData`` of a car hull, so contacts can tell which car it is."""

    def __init__(self, car_index: int):
        self.car_index = car_index


class _RaceContactListener(contactListener):
    """Keeps gymnasium's per-wheel tile sets (the car model reads them for friction) and
    reports first touches and hull contacts to the env, per car."""

    def __init__(self, env: MultiCarRacing):
        contactListener.__init__(self)
        self.env = env

    def BeginContact(self, contact):
        self._contact(contact, begin=True)

    def EndContact(self, contact):
        self._contact(contact, begin=False)

    def _contact(self, contact, begin: bool):
        a = contact.fixtureA.body.userData
        b = contact.fixtureB.body.userData
        if isinstance(a, _HullTag) and isinstance(b, _HullTag):
            self.env._on_hull_contact(a.car_index, b.car_index, begin)
            return
        if b is not None and hasattr(b, "road_friction"):
            a, b = b, a
        if a is None or not hasattr(a, "road_friction") or b is None or not hasattr(b, "tiles"):
            return  # not a tile-wheel contact
        if begin:
            b.tiles.add(a)
            self.env._on_tile_touch(b.car_index, a.idx)
        else:
            b.tiles.discard(a)


class _TrackBuilder:
    """The attributes gymnasium's ``CarRacing._create_track`` reads and writes, so its track
    builder runs unchanged on this env's world and random generator."""

    def __init__(self, world, np_random, verbose=False):
        self.world = world
        self.np_random = np_random
        self.verbose = verbose
        self.road_color = np.array(ROAD_COLOR)
        self.fd_tile = fixtureDef(shape=polygonShape(vertices=[(0, 0), (1, 0), (1, -1), (0, -1)]))
        self.road_poly: list = []
        self.road: list = []
        self.track: list = []

    def build(self):
        while not CarRacing._create_track(self):
            pass  # CarRacing retries failed tracks the same way
        return self


# =======================================================================================
# Rendering: track image once per reset, then one affine warp per view
# =======================================================================================
def _rotation(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


class TrackRenderer:
    """Draws 96x96 egocentric views (CarRacing's colours, zoom and dashboard; its final zoom from the first
    frame, where CarRacing zooms in over its first second) and the ``rgb_array`` race frame.

    The static scene (background, grass squares, road tiles, curbs) is rasterised once into
    a world-aligned image; a view is an affine warp of it (rotate with the car, CarRacing's
    anisotropic 96/1000 x 96/800 scale), with cars and ghosts drawn on top as polygons.
    """

    def __init__(self, road_poly: list, pixels_per_unit: float = MAP_PIXELS_PER_UNIT):
        self.ppu = pixels_per_unit
        size = int(math.ceil(2 * PLAYFIELD * pixels_per_unit))
        self.map = np.zeros((size, size, 3), dtype=np.uint8)
        cv2.fillPoly(self.map, [self._map_px(self._square(-PLAYFIELD, -PLAYFIELD, 2 * PLAYFIELD))], BG_COLOR)
        grass = [
            self._map_px(self._square(GRASS_DIM * x, GRASS_DIM * y, GRASS_DIM))
            for x in range(-20, 20, 2)
            for y in range(-20, 20, 2)
        ]
        cv2.fillPoly(self.map, grass, GRASS_COLOR, lineType=cv2.LINE_AA, shift=4)
        for poly, color in road_poly:  # tiles and curbs, in gymnasium's drawing order
            color = tuple(int(c) for c in color)
            cv2.fillPoly(self.map, [self._map_px(np.asarray(poly))], color, lineType=cv2.LINE_AA, shift=4)
        self._overview = None

    @staticmethod
    def _square(x0, y0, side):
        return np.array([(x0, y0), (x0 + side, y0), (x0 + side, y0 + side), (x0, y0 + side)])

    def _map_px(self, world_xy: np.ndarray) -> np.ndarray:
        """World coordinates -> fixed-point (shift 4) map pixels for ``cv2.fillPoly``."""
        return np.round((world_xy + PLAYFIELD) * self.ppu * 16).astype(np.int32)

    @staticmethod
    def view_transform(x: float, y: float, angle: float) -> np.ndarray:
        """2x3 affine map world -> view pixels for a camera on the car at ``(x, y, angle)``:
        the car's right is +column, its forward is -row (up), the car at (48, 72)."""
        c, s = math.cos(angle), math.sin(angle)
        # local right = (c, s), local forward = (-s, c)
        a = np.array(
            [
                [VIEW_SCALE_X * c, VIEW_SCALE_X * s],
                [VIEW_SCALE_Y * s, -VIEW_SCALE_Y * c],
            ]
        )
        t = np.array([VIEW_CAR_X, VIEW_CAR_Y]) - a @ np.array([x, y])
        return np.hstack([a, t[:, None]])

    def view(self, pose, layers: list, dashboard: dict | None) -> np.ndarray:
        """The 96x96 view of the car at ``pose`` (x, y, angle). ``layers``: drawing order of
        ``(color, world vertices (M, 2), polygons)``, ``polygons`` the (start, end) rows of
        each polygon in the vertices."""
        world_to_view = self.view_transform(*pose)
        # view pixel -> map pixel: invert world->view, then world->map
        view_to_map = cv2.invertAffineTransform(world_to_view) * self.ppu
        view_to_map[:, 2] += PLAYFIELD * self.ppu
        img = cv2.warpAffine(
            self.map,
            view_to_map,
            (VIEW_W, VIEW_H),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=(0, 0, 0),
        )
        if layers:
            # all vertices in one transform, fixed point with 4 fractional bits (shift=4)
            points = (
                np.concatenate([v for _, v, _ in layers]) @ (world_to_view[:, :2].T * 16) + world_to_view[:, 2] * 16
            )
            points = np.round(points).astype(np.int32)
            start = 0
            for color, vertices, polygons in layers:
                cv2.fillPoly(
                    img, [points[start + a : start + b] for a, b in polygons], color, lineType=cv2.LINE_AA, shift=4
                )
                start += len(vertices)
        if dashboard is not None:
            self.draw_dashboard(img, **dashboard)
        return img

    @staticmethod
    def draw_dashboard(img, speed, wheel_omegas, steer_angle, angular_velocity):
        """CarRacing's indicator strip: speed, four ABS bars, steering and gyro."""
        w, h = img.shape[1], img.shape[0]
        s, u = w / 40.0, h / 40.0
        img[h - DASHBOARD_H :] = 0

        def bar(x0, x1, y0, y1, color, value):
            (x0, x1), (y0, y1) = sorted((round(x0), round(x1))), sorted((round(y0), round(y1)))
            if abs(value) > 1e-4 and x1 > x0 and y1 > y0:  # CarRacing skips ~zero readings
                cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), color, -1)

        def vertical(place, val, color, value):
            bar(place * s, (place + 1) * s, h - (u + u * val), h - u, color, value)

        def horizontal(place, val, color, value):
            bar(place * s, (place + val) * s, h - 4 * u, h - 2 * u, color, value)

        vertical(5, 0.02 * speed, (255, 255, 255), speed)
        for i, (omega, color) in enumerate(zip(wheel_omegas, ((0, 0, 255),) * 2 + ((51, 0, 255),) * 2)):
            vertical(7 + i, 0.01 * omega, color, omega)
        horizontal(20, -10.0 * steer_angle, (0, 255, 0), steer_angle)
        horizontal(30, -0.8 * angular_velocity, (255, 0, 0), angular_velocity)

    def overview(self, cars: list, ghosts: list, views: list, names: list) -> np.ndarray:
        """Race frame for videos: the whole track with every car (dots with headings), next
        to every car's own view scaled up, two views per column."""
        if self._overview is None:
            lo, hi = (np.array([-1, 1]) * OVERVIEW_HALF_WIDTH + PLAYFIELD) * self.ppu
            crop = self.map[int(lo) : int(hi), int(lo) : int(hi)]
            self._overview = cv2.resize(crop, (OVERVIEW_SIZE, OVERVIEW_SIZE), interpolation=cv2.INTER_AREA)
        frame_map = self._overview.copy()
        k = OVERVIEW_SIZE / (2 * OVERVIEW_HALF_WIDTH)

        def dot(x, y, angle, color, radius):
            p = np.array([(x + OVERVIEW_HALF_WIDTH) * k, (y + OVERVIEW_HALF_WIDTH) * k])
            head = p + 2 * radius * np.array([-math.sin(angle), math.cos(angle)])
            cv2.circle(frame_map, tuple(np.round(p).astype(int)), radius, color, -1, cv2.LINE_AA)
            cv2.line(frame_map, tuple(np.round(p).astype(int)), tuple(np.round(head).astype(int)), color, 2)

        for x, y, angle in ghosts:
            dot(x, y, angle, GHOST_COLOR, 5)
        for (x, y, angle), color in cars:
            dot(x, y, angle, color, 6)
        frame_map = frame_map[::-1]  # world y up
        tile = OVERVIEW_SIZE // 2
        cols = max(1, math.ceil(len(views) / 2))
        panel = np.zeros((OVERVIEW_SIZE, cols * tile, 3), dtype=np.uint8)
        for i, (view, name) in enumerate(zip(views, names)):
            r, c = i % 2, i // 2
            big = cv2.resize(view, (tile, tile), interpolation=cv2.INTER_NEAREST)
            cv2.putText(big, name, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
            panel[r * tile : (r + 1) * tile, c * tile : (c + 1) * tile] = big
        return np.ascontiguousarray(np.concatenate([frame_map, panel], axis=1))


# =======================================================================================
# The environment
# =======================================================================================
class MultiCarRacing(ParallelEnv):
    """N cars race one lap of a random CarRacing track; each agent sees its own camera.

    ## Description
    The track, the car model (``car_dynamics.Car``) and the 50 Hz Box2D world are gymnasium's CarRacing-v3; this
    env adds more cars (hull-to-hull collisions), one egocentric camera per car drawn straight at 96x96, per-car
    rewards and the race rules below. ``rules="carracing"`` with ``num_agents=1, action_mode="classic"``
    reproduces CarRacing-v3 exactly (same tiles, poses, rewards and termination for the same seed and actions).

    ## Action Space
    Per agent, ``action_mode="throttle_brake"`` (default): ``Box(-1, 1, (2,), float32)``, ``[steer, u]``: ``u > 0``
    is gas ``u``; ``u <= dead_zone`` brakes with strength ``|u|`` (no effect below ``brake_speed_threshold``);
    in between the car coasts. ``"classic"``: CarRacing's ``[steer, gas, brake]`` with its bounds. Finite
    out-of-range actions are clipped; NaN or infinite values, non-numeric values, wrong shapes, unknown or finished
    agents and a racing car without an action raise ``ValueError`` naming the agent (where there is one), before
    anything in the race changes.

    ## Observation Space
    Per agent ``Box(0, 255, (96, 96, 3), uint8)``: its own camera, following and rotating with its car, the own car
    red (``ego_color``), every other car and ghost visible, CarRacing's dashboard in the bottom strip.

    ## Rewards
    Per car and step: -0.1; the first touch of a track tile pays ``(1 - k/N) * 1000/T`` (``T`` tiles, ``N`` cars
    plus ghosts, ``k`` of them touched it earlier: with two cars the leader gets 1000/T and the follower 500/T; one
    car alone collects 1000); ``-collision_penalty`` while its hull touches another car; ``speed_reward_coef``
    times its forward speed along the track; ``-offroad_penalty`` once when it is eliminated.

    ## Starting State
    Under race rules two or more cars start on a staggered two-column grid behind the start line, in a random order;
    a single car (under either rules) starts at CarRacing's pose on tile 0. All randomness
    (track, grid order) comes from the seed of ``reset``.

    ## Episode End
    A car is terminated when it finishes the lap (all tiles, or 95% and back at the start) or is eliminated: its
    centre leaves the road, it leaves the playfield, or it touches no new tile for ``stall_steps`` steps. The race
    ends when every car is done; at ``max_steps`` the cars still racing are truncated. Under race rules a car that
    is done leaves the world, so the cars still racing cannot hit it.

    ## Info
    ``infos[agent]``: ``progress`` (fraction of tiles), ``tiles``, ``tile_reward``, ``lap_finished``,
    ``finish_step`` and ``rank`` (-1 until finished), ``eliminated`` (None, ``"off_road"``, ``"off_playfield"``,
    ``"stalled"``), ``speed``, ``collision_steps``, ``step``; racing a ghost also ``ghost_tiles_ahead``,
    ``ahead_of_ghost`` and, on the car's last step, ``ghost_beaten``; on each car's last step of a race reset with
    a seed, ``trajectory`` (the run as a ``GhostTrajectory``, for ghost racing:
    ``reset(seed, options={"ghosts": ...})``).

    ## Arguments
        num_agents: number of cars, agents ``car_0 .. car_{N-1}``.
        action_mode: ``"throttle_brake"``: ``[steer, u]`` in [-1, 1]^2 with the paper's
            dead zone on ``u``; ``"classic"``: CarRacing's ``[steer, gas, brake]``.
        rules: ``"race"`` (the paper's rules) or ``"carracing"`` (gymnasium CarRacing-v3, one car
            only: no brake threshold, no off-road/stall elimination, no speed term, the car
            starts where CarRacing puts it; the dead zone is the action mode's, so only
            ``action_mode="classic"`` has none).
        dead_zone: lower edge of the throttle-brake dead zone: ``u <= dead_zone`` brakes,
            ``dead_zone < u <= 0`` coasts. Change it between episodes with ``set_dead_zone``.
        brake_speed_threshold: brakes do nothing below this speed (world units per second),
            so a car cannot learn to stand still by braking.
        max_steps: the race is truncated after this many steps.
        stall_steps: a car that touches no new tile for this many steps is eliminated
            (0 switches the rule off).
        collision_penalty: paid per step by each car whose hull touches another car.
        offroad_penalty: paid once when a car is eliminated (off road, off the playfield,
            stalled).
        speed_reward_coef: reward per step per unit of forward speed along the track.
        eliminate_offroad: eliminate a car whose centre leaves the road.
        ego_color: draw the own car red and the others in other colours in every view
            (``False``: each car keeps its own colour in every view).
        render_mode: ``None``, ``"rgb_array"`` (overview + all views) or ``"human"``.
    """

    metadata = {
        "name": "multi_car_racing_v1",
        "render_modes": ["human", "rgb_array"],
        "render_fps": FPS,
        "is_parallelizable": True,
    }

    def __init__(
        self,
        num_agents: int = 2,
        action_mode: str = "throttle_brake",
        rules: str = "race",
        dead_zone: float = -0.5,
        brake_speed_threshold: float = 50.0,
        max_steps: int = 1000,
        stall_steps: int = 150,
        collision_penalty: float = 0.05,
        offroad_penalty: float = 100.0,
        speed_reward_coef: float = 0.0,
        eliminate_offroad: bool = True,
        ego_color: bool = True,
        render_mode: str | None = None,
        verbose: bool = False,
    ):
        if not isinstance(num_agents, (int, np.integer)) or num_agents < 1:
            raise ValueError(f"num_agents must be a positive integer, got {num_agents!r}")
        if action_mode not in ACTION_MODES:
            raise ValueError(f"action_mode must be one of {ACTION_MODES}, got {action_mode!r}")
        if rules not in RULES:
            raise ValueError(f"rules must be one of {RULES}, got {rules!r}")
        if rules == "carracing" and num_agents != 1:  # (its cars would start on one pose, their hulls colliding)
            raise ValueError(f"rules='carracing' is CarRacing-v3's one-car game: num_agents must be 1, "
                             f"got {num_agents}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        if not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
            raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}")
        if stall_steps < 0:
            raise ValueError(f"stall_steps must be >= 0 (0 switches the rule off), got {stall_steps!r}")
        self._check_dead_zone(dead_zone)
        self.num_cars = int(num_agents)
        self.action_mode = action_mode
        self.rules = rules
        self._pending_dead_zone = float(dead_zone)
        self._dead_zone = float(dead_zone)
        self.brake_speed_threshold = float(brake_speed_threshold)
        self.max_steps = int(max_steps)
        self.stall_steps = int(stall_steps)
        self.collision_penalty = float(collision_penalty)
        self.offroad_penalty = float(offroad_penalty)
        self.speed_reward_coef = float(speed_reward_coef)
        self.eliminate_offroad = bool(eliminate_offroad)
        self.ego_color = bool(ego_color)
        self.render_mode = render_mode
        self.verbose = verbose

        self.possible_agents = [f"car_{i}" for i in range(self.num_cars)]
        self.agents: list[str] = []
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        obs_space = spaces.Box(0, 255, (VIEW_H, VIEW_W, 3), dtype=np.uint8)
        if action_mode == "throttle_brake":
            act_space = spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)
        else:  # CarRacing's bounds: steer [-1, 1], gas [0, 1], brake [0, 1]
            act_space = spaces.Box(np.array([-1, 0, 0], np.float32), np.array([1, 1, 1], np.float32))
        self.observation_spaces = {a: obs_space for a in self.possible_agents}
        self.action_spaces = {a: act_space for a in self.possible_agents}

        self.world = self._new_world()
        self.np_random, _ = seeding.np_random(None)
        self.cars: list[Car | None] = []
        self._hull_tags = [_HullTag(i) for i in range(len(self.possible_agents))]  # see _create_car
        self.road: list = []
        self.renderer: TrackRenderer | None = None
        self._window = None
        self._race_over = True
        self._reset_done = False

    # --- PettingZoo API -----------------------------------------------------------------
    def observation_space(self, agent):
        return self.observation_spaces[agent]

    def action_space(self, agent):
        return self.action_spaces[agent]

    @property
    def dead_zone(self) -> float:
        """The dead zone's lower edge in force this episode."""
        return self._dead_zone

    @dead_zone.setter
    def dead_zone(self, value: float):
        self.set_dead_zone(value)

    def set_dead_zone(self, value: float) -> None:
        """Move the dead zone's lower edge; takes effect at the next ``reset`` so an
        episode's rules never change under it (schedules call this between episodes)."""
        self._check_dead_zone(value)
        self._pending_dead_zone = float(value)

    @staticmethod
    def _check_dead_zone(value):
        if not np.isfinite(value) or not -1.0 <= value <= 0.0:
            raise ValueError(f"dead_zone must lie in [-1, 0], got {value!r}")

    def reset(self, seed: int | None = None, options: dict | None = None):
        """Start a new race.

        ``options``: ``"ghosts"``: ``{agent: GhostTrajectory}`` replays ghosts (their
        ``track_seed`` must equal ``seed``); ``"grid"``: grid slot of every car (a permutation
        of ``range(num_agents)``, slot 0 is pole) instead of the seeded random order, so
        races can swap start positions fairly on the same track.
        """
        grid = (options or {}).get("grid")
        if grid is not None and sorted(int(g) for g in grid) != list(range(self.num_cars)):
            raise ValueError(f"options['grid'] must be a permutation of 0..{self.num_cars - 1}, got {list(grid)}")
        if seed is not None:
            self.np_random, _ = seeding.np_random(seed)
        ghosts = dict((options or {}).get("ghosts") or {})
        for agent, ghost in ghosts.items():
            if agent not in self._index:
                raise ValueError(f"ghost given for unknown agent {agent!r}; agents are {self.possible_agents}")
            if isinstance(ghost, dict):
                ghosts[agent] = ghost = GhostTrajectory.from_dict(ghost)
            if seed is None or int(seed) != ghost.track_seed:
                raise ValueError(
                    f"ghost of {agent} was recorded on track seed {ghost.track_seed}; "
                    f"reset with seed={ghost.track_seed} (got {seed})"
                )
        self._destroy()
        self.world = self._new_world()
        self._dead_zone = self._pending_dead_zone
        self.track_seed = None if seed is None else int(seed)

        builder = _TrackBuilder(self.world, self.np_random, self.verbose).build()
        self.road, self.road_poly = builder.road, builder.road_poly
        self.track = np.array(builder.track)  # rows: (alpha, beta, x, y)
        self.num_tiles = len(self.track)
        self._tile_quads = self._compute_tile_quads(self.track)
        self._tile_edges = np.roll(self._tile_quads, -1, axis=1) - self._tile_quads
        self.renderer = TrackRenderer(self.road_poly)
        for ghost in ghosts.values():
            if ghost.num_tiles != self.num_tiles:
                raise ValueError(f"ghost has {ghost.num_tiles} tiles, this track {self.num_tiles}")

        n = self.num_cars
        self.ghosts = [(self._index[a], g) for a, g in sorted(ghosts.items())]
        self._share_count = n + len(self.ghosts)  # N of the reward split counts ghosts
        self.agents = list(self.possible_agents)
        self.step_count = 0
        self._race_over = False
        self._tile_touches = np.zeros(self.num_tiles, dtype=np.int64)
        self.first_touch_step = np.full((n, self.num_tiles), -1, dtype=np.int64)
        self._pending_touches: list[tuple[int, int]] = []
        self._tiles = np.zeros(n, dtype=np.int64)
        self._cum_reward = np.zeros(n)
        self._prev_reward = np.zeros(n)
        self._tile_reward = np.zeros(n)
        self._new_lap = np.zeros(n, dtype=bool)
        self._finish_step = np.full(n, -1, dtype=np.int64)
        self._rank = np.full(n, -1, dtype=np.int64)
        self._eliminated: list[str | None] = [None] * n
        self._hull_contacts = np.zeros(n, dtype=np.int64)
        self._hit_this_step = np.zeros(n, dtype=bool)
        self._collision_steps = np.zeros(n, dtype=np.int64)
        self._last_new_tile_step = np.zeros(n, dtype=np.int64)
        self._poses: list[list[tuple[float, float, float]]] = [[] for _ in range(n)]
        self._finished_count = 0

        self.cars = [self._create_car(i, pose) for i, pose in enumerate(self._start_grid(grid))]
        self._car_tile = np.array([self._locate(*self._pose(i)[:2], -1) for i in range(n)])
        self._start_tile = self._car_tile.copy()
        # CarRacing's reset advances the world once with no control (its ``step(None)``);
        # tiles touched here are paid out with the first step's reward.
        self._physics_step()
        self._record_poses()
        self._last_views = {}
        observations = self._observe(self.agents)
        infos = {a: self._info(self._index[a]) for a in self.agents}
        self._reset_done = True
        if self.render_mode == "human":
            self.render()
        return observations, infos

    def step(self, actions: dict):
        if not self._reset_done:
            raise RuntimeError("MultiCarRacing.step called before reset()")
        if self._race_over:
            raise RuntimeError("the race is over (every car is done): call reset() before step()")
        controls = self._validate_actions(actions)
        self.step_count += 1
        for i, control in controls.items():
            self._apply_control(i, control)
        self._physics_step()
        self._record_poses()

        live = [self._index[a] for a in self.agents]
        truncate = self.step_count >= self.max_steps
        rewards, terminations, truncations = {}, {}, {}
        for i in live:
            terminated, step_reward = self._update_car(i)
            agent = self.possible_agents[i]
            rewards[agent] = float(step_reward)
            terminations[agent] = bool(terminated)
            truncations[agent] = bool(truncate and not terminated)
        done_agents = [
            self.possible_agents[i]
            for i in live
            if terminations[self.possible_agents[i]] or truncations[self.possible_agents[i]]
        ]
        observations = self._observe(self.agents)
        infos = {a: self._info(self._index[a]) for a in self.agents}
        for agent in done_agents:
            i = self._index[agent]
            ghost = self._ghost_of(i)
            if ghost is not None:
                infos[agent]["ghost_beaten"] = ghost_beaten(int(self._finish_step[i]), int(self._tiles[i]), ghost)
            if self.track_seed is not None:  # the whole run, ready to race as a ghost
                infos[agent]["trajectory"] = self.trajectory(agent)
            self.agents.remove(agent)
            if self.rules == "race":  # out of the race: off the track for the others
                self._destroy_car(i)
        self._race_over = not self.agents
        if self.render_mode == "human":
            self.render()
        return observations, rewards, terminations, truncations, infos

    def render(self):
        if self.render_mode is None:
            gymnasium.logger.warn("render() called with render_mode=None; pass render_mode='rgb_array' or 'human'")
            return None
        frame = self._race_frame()
        if self.render_mode == "rgb_array":
            return frame
        import pygame  # only the human mode needs a window

        if self._window is None:
            pygame.display.init()
            self._window = pygame.display.set_mode(frame.shape[1::-1])
            self._clock = pygame.time.Clock()
        pygame.event.pump()
        self._window.blit(pygame.surfarray.make_surface(frame.swapaxes(0, 1)), (0, 0))
        pygame.display.flip()
        self._clock.tick(self.metadata["render_fps"])  # real time, as CarRacing's human mode
        return None

    def close(self):
        if self._window is not None:
            import pygame

            pygame.display.quit()
            self._window = None

    # --- Ghost recording ----------------------------------------------------------------
    def trajectory(self, agent: str) -> GhostTrajectory:
        """The current (or last) race of ``agent`` as a ghost for this track seed."""
        if agent not in self._index:
            raise ValueError(f"unknown agent {agent!r}; agents are {self.possible_agents}")
        if not self._reset_done:
            raise RuntimeError("no race recorded yet: call reset() first")
        if self.track_seed is None:
            raise ValueError("a ghost needs a track seed: reset(seed=...) before recording")
        i = self._index[agent]
        steps = self.first_touch_step[i]
        touched = np.flatnonzero(steps >= 0)
        order = np.argsort(steps[touched], kind="stable")
        return GhostTrajectory(
            track_seed=self.track_seed,
            num_tiles=self.num_tiles,
            poses=np.array(self._poses[i], dtype=np.float64),
            tile_steps=steps[touched][order],
            tile_ids=touched[order],
            finish_step=int(self._finish_step[i]),
        )

    # --- Track geometry (also used by the pursuit driver) -------------------------------
    @property
    def track_xy(self) -> np.ndarray:
        """Centre-line points, one per tile (tile ``i`` spans points ``i-1`` to ``i``)."""
        return self.track[:, 2:4]

    def car_state(self, agent: str) -> dict[str, Any]:
        """Pose and motion of a racing car: position, angle, velocity, speed, tile index."""
        i = self._index[agent]
        car = self.cars[i]
        if car is None:
            raise ValueError(f"{agent} is not racing")
        vx, vy = car.hull.linearVelocity
        return {
            "position": np.array(car.hull.position),
            "angle": float(car.hull.angle),
            "velocity": np.array([vx, vy]),
            "speed": math.hypot(vx, vy),
            "tile": int(self._car_tile[i]),
        }

    @staticmethod
    def _compute_tile_quads(track: np.ndarray) -> np.ndarray:
        """(T, 4, 2) tile corners exactly as gymnasium builds them."""
        beta, x, y = track[:, 1], track[:, 2], track[:, 3]
        perp = np.stack([np.cos(beta), np.sin(beta)], axis=1) * TRACK_WIDTH
        p1 = np.stack([x, y], axis=1)
        p2 = np.roll(p1, 1, axis=0)
        perp2 = np.roll(perp, 1, axis=0)
        return np.stack([p1 - perp, p1 + perp, p2 + perp2, p2 - perp2], axis=1)

    def _locate(self, x: float, y: float, hint: int) -> int:
        """Index of the tile containing (x, y), or -1 off the road. Searches near ``hint``
        first (cars move a fraction of a tile per step), then the whole track."""
        if hint >= 0:
            idx = (hint + np.arange(-3, 6)) % self.num_tiles
            found = self._inside(x, y, idx)
            if found >= 0:
                return found
        return self._inside(x, y, np.arange(self.num_tiles))

    def _inside(self, x, y, idx):
        q, e = self._tile_quads[idx], self._tile_edges[idx]
        d = np.array([x, y]) - q
        cross = e[..., 0] * d[..., 1] - e[..., 1] * d[..., 0]
        inside = np.all(cross >= 0, axis=1) | np.all(cross <= 0, axis=1)
        hits = np.flatnonzero(inside)
        return int(idx[hits[0]]) if len(hits) else -1

    # --- Cars ---------------------------------------------------------------------------
    def _start_grid(self, grid=None) -> list[tuple[float, float, float]]:
        """Start poses (angle, x, y) per car. CarRacing rules: gymnasium's own start. Race
        rules: a staggered two-column grid behind the line, cars in random order (or in
        ``grid`` order: ``grid[i]`` is the slot of car i)."""
        beta, x, y = self.track[0, 1], self.track[0, 2], self.track[0, 3]
        if self.rules == "carracing" or self.num_cars == 1:
            return [(beta, x, y)] * self.num_cars
        order = self.np_random.permutation(self.num_cars)  # drawn either way: same random stream
        if grid is not None:
            order = np.asarray(grid, dtype=np.int64)
        poses = []
        for slot in order:
            beta, x, y = self.track[-int(slot) % self.num_tiles, 1:4]
            side = -1.0 if slot % 2 == 0 else 1.0
            poses.append(
                (beta, x + side * GRID_LATERAL_OFFSET * math.cos(beta), y + side * GRID_LATERAL_OFFSET * math.sin(beta))
            )
        return poses

    def _create_car(self, i: int, pose) -> Car:
        car = Car(self.world, *pose)
        for w in car.wheels:
            w.car_index = i
        # pybox2d drops its reference to a body's userData before destroying the body, and the destruction then
        # reports EndContact for the body's contacts: the env holds the tags, so the listener never reads a freed one
        car.hull.userData = self._hull_tags[i]
        if self.rules == "race":  # hull-to-hull collisions; wheels only feel the road
            for f in car.hull.fixtures:
                self._set_filter(f, CATEGORY_HULL, CATEGORY_HULL)
            for w in car.wheels:
                self._set_filter(w.fixtures[0], CATEGORY_WHEEL, CATEGORY_TILE)
        return car

    @staticmethod
    def _set_filter(fixture, category, mask):
        filt = fixture.filterData
        filt.categoryBits, filt.maskBits = category, mask
        fixture.filterData = filt

    def _new_world(self) -> Box2D.b2World:
        """An empty Box2D world for the next race. Each race gets its own (gymnasium's CarRacing keeps one for every
        reset), so that a race depends on its seed and actions alone: a reused world orders new contacts by the
        proxy ids of bodies destroyed in earlier races, and the order in which Box2D solves two hulls' contacts
        changes their collision's outcome in the last bits, then beyond."""
        return Box2D.b2World((0, 0), contactListener=_RaceContactListener(self))

    def _destroy_car(self, i: int):
        if self.cars[i] is not None:
            self.cars[i].destroy()
            self.cars[i] = None

    def _destroy(self):
        for i in range(len(self.cars)):
            self._destroy_car(i)
        for tile in self.road:
            self.world.DestroyBody(tile)
        self.road = []
        self.cars = []

    def _pose(self, i: int) -> tuple[float, float, float]:
        hull = self.cars[i].hull
        return float(hull.position[0]), float(hull.position[1]), float(hull.angle)

    # --- Actions ------------------------------------------------------------------------
    def _validate_actions(self, actions) -> dict[int, np.ndarray]:
        """Check every action before anything changes, so a rejected call leaves the race
        exactly as it was. Finite out-of-range values are clipped to the action space."""
        if not isinstance(actions, dict):
            raise ValueError(f"actions must be a dict agent -> action, got {type(actions).__name__}")
        controls = {}
        for agent, action in actions.items():
            if agent not in self._index:
                raise ValueError(f"action for unknown agent {agent!r}; agents are {self.possible_agents}")
            if agent not in self.agents:
                raise ValueError(f"action for {agent}, which is no longer racing (done earlier this race)")
            space = self.action_spaces[agent]
            a = self._real_array(agent, action)
            if a.shape != space.shape:
                raise ValueError(f"action for {agent} has shape {a.shape}, expected {space.shape}")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"action for {agent} is not finite: {a.tolist()}")
            with np.errstate(over="ignore"):  # a finite long double beyond float64 becomes inf, then clips
                controls[self._index[agent]] = np.clip(a.astype(np.float64), space.low, space.high)
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"no action for {', '.join(missing)} (every racing car needs one)")
        return controls

    @staticmethod
    def _real_array(agent: str, action) -> np.ndarray:
        """The action as an array of real numbers (ints or floats), or ValueError: strings, bytes, booleans,
        complex numbers, None and other objects are refused, never converted (numpy would turn "0.5" into 0.5,
        True into 1.0 and drop an imaginary part)."""
        try:
            a = np.asarray(action)
            if a.dtype.kind not in "iuf":
                raise TypeError(f"dtype {a.dtype}")
            if not isinstance(action, np.ndarray):  # a sequence numpy coerced: no bools mixed in with numbers
                items = np.asarray(action, dtype=object).ravel()
                if any(isinstance(x, (bool, np.bool_)) for x in items):
                    raise TypeError("booleans")
        except Exception as e:  # ragged sequences, tensors that refuse conversion, objects with a bad __array__ ...
            raise ValueError(f"action for {agent} is not numeric (real numbers expected): {action!r:.200}") from e
        return a

    def _apply_control(self, i: int, a: np.ndarray):
        car = self.cars[i]
        car.steer(-a[0])  # CarRacing: positive steer action turns right
        if self.action_mode == "classic":
            gas, brake = a[1], a[2]
        else:  # paper: u > 0 gas; u <= dead_zone brake |u|; in between coast
            u = a[1]
            gas = max(u, 0.0)
            brake = -u if u <= self._dead_zone else 0.0
        if self.rules == "race" and brake > 0:
            vx, vy = car.hull.linearVelocity
            if math.hypot(vx, vy) < self.brake_speed_threshold:
                brake = 0.0  # paper: no braking to a standstill
        car.gas(gas)
        car.brake(brake)

    # --- Physics and rules ---------------------------------------------------------------
    def _physics_step(self):
        self._hit_this_step[:] = False
        for car in self.cars:
            if car is not None:
                car.step(DT)
        self.world.Step(DT, VELOCITY_ITERATIONS, POSITION_ITERATIONS)
        for ghost_index, ghost in self.ghosts:
            lo, hi = np.searchsorted(ghost.tile_steps, [self.step_count, self.step_count + 1])
            for tile in ghost.tile_ids[lo:hi]:
                self._pending_touches.append((-1 - ghost_index, int(tile)))
        self._pay_tiles()
        for i, car in enumerate(self.cars):
            if car is not None and (self._hull_contacts[i] > 0 or self._hit_this_step[i]):
                self._collision_steps[i] += 1
                self._hit_this_step[i] = True

    def _on_tile_touch(self, i: int, tile: int):
        """Wheel of car ``i`` began touching ``tile`` (called by Box2D during a step)."""
        if self.first_touch_step[i, tile] < 0:
            self.first_touch_step[i, tile] = self.step_count
            self._pending_touches.append((i, tile))
        elif (
            self.rules == "race"
            and tile == self._start_tile[i]
            and self._tiles[i] / self.num_tiles > LAP_COMPLETE_PERCENT
        ):
            self._new_lap[i] = True  # back over its own start tile after most of the lap

    def _on_hull_contact(self, i: int, j: int, begin: bool):
        delta = 1 if begin else -1
        self._hull_contacts[[i, j]] += delta
        if begin:
            self._hit_this_step[[i, j]] = True

    def _pay_tiles(self):
        """Competitive split: the first touch of a tile pays ``(1 - k/N) * 1000/T`` where
        ``k`` cars or ghosts touched it in earlier steps (same-step touches share a rank)."""
        per_tile = TRACK_REWARD / self.num_tiles
        earlier = {}
        for who, tile in self._pending_touches:
            k = earlier.setdefault(tile, self._tile_touches[tile])
            self._tile_touches[tile] += 1
            if who < 0:
                continue  # a ghost: takes its share, pays nobody
            share = (1.0 - k / self._share_count) * per_tile
            self._cum_reward[who] += share
            self._tile_reward[who] += share
            self._tiles[who] += 1
            self._last_new_tile_step[who] = self.step_count
            # CarRacing's lap rule: crossing tile 0 as a first touch after 95% of the lap
            if tile == 0 and self._tiles[who] / self.num_tiles > LAP_COMPLETE_PERCENT:
                self._new_lap[who] = True
        self._pending_touches.clear()

    def _update_car(self, i: int) -> tuple[bool, float]:
        """Per-car rewards and termination after a physics step (docs/environment.md)."""
        car = self.cars[i]
        x, y = car.hull.position
        self._car_tile[i] = self._locate(x, y, int(self._car_tile[i]))
        self._cum_reward[i] -= TIME_PENALTY
        if self.rules == "carracing":
            car.fuel_spent = 0.0
            step_reward = self._cum_reward[i] - self._prev_reward[i]
            self._prev_reward[i] = self._cum_reward[i]
            terminated = False
            if self._tiles[i] == self.num_tiles or self._new_lap[i]:
                self._finish(i)
                terminated = True
            if abs(x) > PLAYFIELD or abs(y) > PLAYFIELD:  # CarRacing replaces the reward
                self._eliminated[i] = "off_playfield"
                return True, -self.offroad_penalty
            return terminated, step_reward

        if self._hit_this_step[i]:
            self._cum_reward[i] -= self.collision_penalty
        if self.speed_reward_coef and self._car_tile[i] >= 0:
            beta = self.track[self._car_tile[i], 1]
            vx, vy = car.hull.linearVelocity
            self._cum_reward[i] += self.speed_reward_coef * (-vx * math.sin(beta) + vy * math.cos(beta))
        terminated = False
        if self._tiles[i] == self.num_tiles or self._new_lap[i]:
            self._finish(i)
            terminated = True
        else:
            reason = None
            if abs(x) > PLAYFIELD or abs(y) > PLAYFIELD:
                reason = "off_playfield"
            elif self.eliminate_offroad and self._car_tile[i] < 0:
                reason = "off_road"
            elif self.stall_steps and self.step_count - self._last_new_tile_step[i] >= self.stall_steps:
                reason = "stalled"
            if reason is not None:
                self._eliminated[i] = reason
                self._cum_reward[i] -= self.offroad_penalty
                terminated = True
        step_reward = self._cum_reward[i] - self._prev_reward[i]
        self._prev_reward[i] = self._cum_reward[i]
        return terminated, step_reward

    def _finish(self, i: int):
        self._finish_step[i] = self.step_count
        already = int(np.sum((self._finish_step >= 0) & (self._finish_step < self.step_count)))
        self._rank[i] = already + 1  # cars finishing on the same step share a rank

    def _ghost_of(self, i: int) -> GhostTrajectory | None:
        for owner, ghost in self.ghosts:
            if owner == i:
                return ghost
        return None

    def _record_poses(self):
        for i, car in enumerate(self.cars):
            if car is not None and self.possible_agents[i] in self.agents:
                self._poses[i].append(self._pose(i))

    def _info(self, i: int) -> dict[str, Any]:
        car = self.cars[i]
        speed = math.hypot(*car.hull.linearVelocity) if car is not None else 0.0
        info = {
            "progress": float(self._tiles[i] / self.num_tiles),
            "tiles": int(self._tiles[i]),
            "tile_reward": float(self._tile_reward[i]),
            "lap_finished": bool(self._finish_step[i] >= 0),
            "finish_step": int(self._finish_step[i]),
            "rank": int(self._rank[i]),
            "eliminated": self._eliminated[i],
            "speed": float(speed),
            "collision_steps": int(self._collision_steps[i]),
            "step": int(self.step_count),
        }
        ghost = self._ghost_of(i)
        if ghost is not None:
            ahead = int(self._tiles[i]) - ghost.tiles_by_step(self.step_count)
            info["ghost_tiles_ahead"] = ahead
            info["ahead_of_ghost"] = ahead > 0
        return info

    # --- Drawing ------------------------------------------------------------------------
    def _car_vertices(self, i: int) -> np.ndarray:
        """World-space outline of car ``i``: 16 wheel vertices, then 20 hull vertices."""
        car = self.cars[i]
        x, y, angle = self._pose(i)
        wheels = [_WHEEL_VERTICES @ _rotation(w.angle).T + tuple(w.position) for w in car.wheels]
        return np.concatenate(wheels + [_HULL_VERTICES @ _rotation(angle).T + (x, y)])

    def _ghost_poses(self) -> list[tuple[float, float, float]]:
        t = self.step_count
        return [tuple(g.poses[t]) for _, g in self.ghosts if t < len(g.poses)]

    def _observe(self, agents: list[str]) -> dict[str, np.ndarray]:
        """Every listed agent's camera: ghosts first, then the other cars, own car on top."""
        outlines = {i: self._car_vertices(i) for i, car in enumerate(self.cars) if car is not None}
        ghost_layers = [
            (GHOST_COLOR, _HULL_VERTICES @ _rotation(angle).T + (x, y), HULL_POLYGONS)
            for x, y, angle in self._ghost_poses()
        ]
        obs = {}
        for agent in agents:
            i = self._index[agent]
            layers = list(ghost_layers)
            for j in sorted(outlines, key=lambda j: j == i):
                layers.append((WHEEL_COLOR, outlines[j][:16], WHEEL_POLYGONS))
                layers.append((self._car_color(j, viewer=i), outlines[j][16:], HULL_POLYGONS))
            obs[agent] = self.renderer.view(self._pose(i), layers, self._dashboard(i))
        self._last_views.update(obs)  # a car out of the race keeps its last view in render()
        return obs

    def _car_color(self, j: int, viewer: int) -> tuple[int, int, int]:
        if not self.ego_color:
            return CAR_COLORS[j % len(CAR_COLORS)]
        if j == viewer:
            return EGO_COLOR
        others = [k for k in range(self.num_cars) if k != viewer]
        return CAR_COLORS[1 + others.index(j) % (len(CAR_COLORS) - 1)]

    def _dashboard(self, i: int) -> dict:
        car = self.cars[i]
        return {
            "speed": math.hypot(*car.hull.linearVelocity),
            "wheel_omegas": [w.omega for w in car.wheels],
            "steer_angle": car.wheels[0].joint.angle,
            "angular_velocity": car.hull.angularVelocity,
        }

    def _race_frame(self) -> np.ndarray:
        if self.renderer is None:
            raise RuntimeError("render() before reset()")
        cars = [
            (self._pose(i), CAR_COLORS[i % len(CAR_COLORS)])
            for i, car in enumerate(self.cars)
            if car is not None
        ]
        # Every car's panel in every frame (a finished or eliminated car's last view, labelled
        # "out"), so the frame size stays constant through a race and videos can be encoded.
        views = [self._last_views[a] for a in self.possible_agents]
        names = [a if a in self.agents else f"{a} (out)" for a in self.possible_agents]
        return self.renderer.overview(cars, self._ghost_poses(), views, names)


class SingleCarRacing(gymnasium.Env):
    """The one-car race as a plain gymnasium env (registered as ``dlc/SingleCarRacing-v0``),
    so any gymnasium or Stable-Baselines3 algorithm trains on it. Keyword arguments are
    those of ``MultiCarRacing`` (``num_agents`` is fixed to 1)."""

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": FPS}

    def __init__(self, render_mode: str | None = None, **kwargs):
        if "num_agents" in kwargs and kwargs["num_agents"] != 1:
            raise ValueError(f"SingleCarRacing has one car, got num_agents={kwargs['num_agents']}")
        kwargs.pop("num_agents", None)
        self.race = MultiCarRacing(num_agents=1, render_mode=render_mode, **kwargs)
        self.agent = self.race.possible_agents[0]
        self.observation_space = self.race.observation_space(self.agent)
        self.action_space = self.race.action_space(self.agent)
        self.render_mode = render_mode

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs, infos = self.race.reset(seed=seed, options=options)
        self._np_random = self.race.np_random  # env.np_random: the generator the track came from
        if self._np_random_seed is None:  # never seeded: gymnasium's "unknown seed" (reading it keeps this generator)
            self._np_random_seed = -1
        return obs[self.agent], infos[self.agent]

    def step(self, action):
        obs, rewards, terms, truncs, infos = self.race.step({self.agent: action})
        a = self.agent
        return obs[a], rewards[a], terms[a], truncs[a], infos[a]

    def render(self):
        return self.race.render()

    def close(self):
        self.race.close()
