"""Built-in scenarios: camera motions (hand-held, smooth in acceleration) and the scenes they look at.

Each scene holds the part (`vio.sim.parts`: the 76.2 mm cube by default, or cube_features, freeform, a user STL)
standing on its support, with its part frame axis-aligned with the world.

orbit:   a 76.2 mm cube on a 2.0 x 1.6 m table in a 4.1 x 4.0 m room; the camera circles the cube at 0.38-0.66 m
         in four rings at 0, 20, 40 and 60 deg elevation (one loop per ring, 15 s per ring, 4 s C3 transitions),
         with hand wobble (sums of sinusoids, seeded phases) and the optical axis wandering around the cube.
figure8: the same scene, a horizontal figure eight (10 s per loop) above the table looking at the cube.
room:    a hand-held walk (steps bob the camera) around a 4 x 5 m room with a table, the cube and furniture.
static:  the orbit's scene, the phone at rest 0.45 m from the cube (an IMU noise log for `vio calibrate imu`).
tumble:  the phone laid still in 24 orientations (3 s each, turned in 1.5 s between them): the accelerometer log of
         a multi-position calibration (`vio calibrate imu-axes`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from vio.sim.parts import Part
from vio.sim.scene import Box, PlacedPart, Scene
from vio.sim.trajectory import PoseFn, Sinusoids, look_at, smoothstep7

_WALL_SHADE = (0.85, 0.80, 0.90, 0.75, 0.70, 0.95)  # room walls, floor (face 4), ceiling (face 5)
_SOLID_SHADE = (0.68, 0.76, 0.72, 0.64, 0.50, 0.92)


def _part_on(part: Part, surface: str, x: float, y: float, z_top: float) -> PlacedPart:
    """The part standing on a support whose top is at height z_top, its base centred on (x, y), world m."""
    world_T_part = np.eye(4)
    world_T_part[:3, 3] = [x, y, z_top]
    return PlacedPart(part, world_T_part, surface)


def tabletop_scene(texture_seed: int, part: Part, surface: str = "speckle") -> Scene:
    """The orbit scene: the part at the origin on a table top (z = 0), backdrop walls 1.9-2.3 m away."""
    table = Box("table", np.array([-1.0, -0.8, -0.03]), np.array([1.0, 0.8, 0.0]), 0.001, "table", False, (4,))
    room = Box("room", np.array([-2.0, -1.7, -0.75]), np.array([2.1, 2.3, 1.75]), 0.004, "wall", True, (), _WALL_SHADE)
    placed = _part_on(part, surface, 0.0, 0.0, 0.0)
    return Scene(room, (table,), placed, texture_seed, {"room_lo": room.lo, "room_hi": room.hi})


def room_scene(texture_seed: int, part: Part, surface: str = "speckle") -> Scene:
    """A 4 x 5 x 2.6 m room (floor z = 0) with a table carrying the part, a cabinet and a low chest."""
    room = Box("room", np.array([-2.0, -2.5, 0.0]), np.array([2.0, 2.5, 2.6]), 0.004, "wall", True, (), _WALL_SHADE)
    table = Box("table", np.array([-0.6, -0.4, 0.72]), np.array([0.6, 0.4, 0.75]), 0.002, "table", False, (4,))
    cabinet = Box("cabinet", np.array([-2.0, -0.5, 0.0]), np.array([-1.6, 0.7, 1.1]), 0.003, "furniture")
    chest = Box("chest", np.array([1.2, 1.7, 0.0]), np.array([2.0, 2.5, 0.5]), 0.003, "furniture")
    base = Box("table_base", np.array([-0.3, -0.2, 0.0]), np.array([0.3, 0.2, 0.72]), 0.003, "furniture", False, (4,))
    placed = _part_on(part, surface, 0.1, -0.05, 0.75)
    solids = tuple(Box(b.name, b.lo, b.hi, b.texel_m, b.style, False, (4,), _SOLID_SHADE) for b in (cabinet, chest))
    return Scene(room, (table, base, *solids), placed, texture_seed, {"room_lo": room.lo, "room_hi": room.hi})


def trajectory_room_scene(p_world: np.ndarray, texture_seed: int, part: Part, surface: str = "speckle") -> Scene:
    """A room around a recorded trajectory: walls 2 m beyond its bounding box, floor 1.2 m below it, the part on
    the floor below the trajectory's centre."""
    lo = p_world.min(axis=0) - np.array([2.0, 2.0, 1.2])
    hi = p_world.max(axis=0) + np.array([2.0, 2.0, 1.5])
    texel = max(0.004, float((hi - lo).max()) / 2048.0)
    room = Box("room", lo, hi, texel, "wall", True, (), _WALL_SHADE)
    centre = 0.5 * (p_world.min(axis=0) + p_world.max(axis=0))
    placed = _part_on(part, surface, float(centre[0]), float(centre[1]), float(lo[2]))
    return Scene(room, (), placed, texture_seed, {"room_lo": lo, "room_hi": hi})


def _camera_fn(pos: Callable, target: Callable, roll: Callable) -> PoseFn:
    def fn(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = pos(t)
        return p, look_at(p, target(t), roll(t))

    return fn


def _hand(rng: np.random.Generator) -> tuple[Sinusoids, Sinusoids, Sinusoids]:
    """Hand wobble of position (m), aim point (m) and roll (rad); vertical position wobble is halved."""
    pos = Sinusoids.make([0.008, 0.005, 0.003, 0.0012], [0.41, 0.93, 1.63, 2.71], 3, rng, gains=[1.0, 1.0, 0.5])
    aim = Sinusoids.make([0.012, 0.006, 0.002], [0.17, 0.43, 1.13], 3, rng)
    roll = Sinusoids.make([0.05, 0.02, 0.004], [0.11, 0.37, 1.9], 1, rng)
    return pos, aim, roll


def orbit_camera(
    rng: np.random.Generator,
    part_centre: np.ndarray,
    ring_s: float = 15.0,
    elevations_deg: tuple[float, ...] = (0.0, 20.0, 40.0, 60.0),
    radius_min_m: float = 0.38,
    radius_max_m: float = 0.66,
) -> PoseFn:
    """Camera pose function of the orbit: one loop per ring, rings up then back down, radius in [min, max].

    The radius wanders smoothly over [min + 2 cm, max - 2 cm]; the hand wobble adds up to ~2 cm.
    """
    pattern_deg = np.array([*elevations_deg, *elevations_deg[-2:0:-1]], dtype=float)
    transition_s = min(4.0, 0.4 * ring_s)
    r_mid = 0.5 * (radius_min_m + radius_max_m)
    r_amp = max(0.5 * (radius_max_m - radius_min_m) - 0.02, 0.0)
    w_az = 2.0 * np.pi / ring_s
    az0 = rng.uniform(0.0, 2.0 * np.pi)
    az_wob = Sinusoids.make([0.06, 0.025], [0.05, 0.21], 1, rng)
    rad = Sinusoids.make([0.6 * r_amp, 0.4 * r_amp], [0.045, 0.113], 1, rng)
    el_wob = Sinusoids.make([np.radians(1.0), np.radians(0.5)], [0.09, 0.31], 1, rng)
    pos_wob, aim_wob, roll_wob = _hand(rng)

    def elevation(t: np.ndarray) -> np.ndarray:
        n_seg = int(np.ceil((t.max(initial=0.0) + transition_s) / ring_s)) + 1
        levels = np.radians(pattern_deg[np.arange(n_seg + 1) % pattern_deg.size])
        e = np.full(t.shape, levels[0])
        for k in range(n_seg):
            start = (k + 1) * ring_s - transition_s / 2.0
            e += (levels[k + 1] - levels[k]) * smoothstep7((t - start) / transition_s)
        return e + el_wob(t)[:, 0]

    def pos(t: np.ndarray) -> np.ndarray:
        e = elevation(t)
        az = az0 + w_az * t + az_wob(t)[:, 0]
        r = r_mid + rad(t)[:, 0]
        ring = np.stack([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.sin(e)], axis=1)
        return part_centre + r[:, None] * ring + pos_wob(t)

    return _camera_fn(pos, lambda t: part_centre + aim_wob(t), lambda t: roll_wob(t)[:, 0])


def figure8_camera(rng: np.random.Generator, part_centre: np.ndarray, loop_s: float = 10.0) -> PoseFn:
    """A horizontal figure eight 0.7 x 0.32 m, 0.26-0.34 m above the table, in front of the cube."""
    w = 2.0 * np.pi / loop_s
    ph = rng.uniform(0.0, 2.0 * np.pi)
    pos_wob, aim_wob, roll_wob = _hand(rng)
    centre = np.array([0.0, -0.42, 0.30])

    def pos(t: np.ndarray) -> np.ndarray:
        a = w * t + ph
        loop = np.stack([0.35 * np.sin(a), 0.16 * np.sin(2.0 * a), 0.04 * np.sin(a + 1.0)], axis=1)
        return centre + loop + pos_wob(t)

    return _camera_fn(pos, lambda t: part_centre + aim_wob(t), lambda t: roll_wob(t)[:, 0])


def room_camera(rng: np.random.Generator, lap_s: float = 25.0) -> PoseFn:
    """A walk around an ellipse (1.1 x 1.5 m half axes) at 1.45 m, steps at 1.8 Hz, looking ahead and inwards."""
    w = 2.0 * np.pi / lap_s
    ph = rng.uniform(0.0, 2.0 * np.pi)
    sway = Sinusoids.make([0.010, 0.004], [0.9, 2.1], 3, rng, gains=[1.0, 1.0, 0.0])
    bob = Sinusoids.make([0.012, 0.003], [1.8, 3.6], 1, rng)
    yaw = Sinusoids.make([0.55, 0.2], [0.045, 0.13], 1, rng)
    pos_wob, aim_wob, roll_wob = _hand(rng)

    def pos(t: np.ndarray) -> np.ndarray:
        a = w * t + ph
        p = np.stack([1.1 * np.cos(a), 1.5 * np.sin(a), np.full(t.shape, 1.45)], axis=1)
        p[:, 2] += bob(t)[:, 0]
        return p + sway(t) + pos_wob(t)

    def target(t: np.ndarray) -> np.ndarray:
        a = w * t + ph
        heading = np.arctan2(1.5 * np.cos(a), -1.1 * np.sin(a)) + 0.6 + yaw(t)[:, 0]
        look = np.stack([np.cos(heading), np.sin(heading), np.full(t.shape, -0.35)], axis=1)
        return pos(t) + 1.5 * look + 3.0 * aim_wob(t)

    return _camera_fn(pos, target, lambda t: roll_wob(t)[:, 0])


def static_camera(rng: np.random.Generator, part_centre: np.ndarray) -> PoseFn:
    """The phone at rest (an IMU noise log): the camera 0.45 m from the part, looking at it, never moving.

    `rng` is unused (the pose has nothing random); it keeps the signature of the other camera motions."""
    del rng
    p = np.asarray(part_centre, float) + np.array([0.30, -0.25, 0.25])

    def fn(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p_cam = np.repeat(p[None, :], len(t), axis=0)
        return p_cam, look_at(p_cam, np.asarray(part_centre, float)[None, :], np.zeros(len(t)))

    return fn


TUMBLE_POSES = 24
TUMBLE_HOLD_S = 3.0
TUMBLE_TURN_S = 1.5


def tumble_camera(rng: np.random.Generator, part_centre: np.ndarray) -> PoseFn:
    """A multi-position IMU calibration: the phone laid still in `TUMBLE_POSES` orientations for `TUMBLE_HOLD_S`
    each and turned about its camera between them in `TUMBLE_TURN_S` (C3-smooth: the IMU sees no jerk at the
    ends). First the six with a camera axis pointing down or up, then seeded uniformly random ones, so gravity
    covers the sphere of the IMU's axes. The phone stays 0.3 m above the part (the images, if rendered, see the
    room)."""
    axes = np.vstack([np.eye(3), -np.eye(3)])
    faces = [Rotation.align_vectors([[0.0, 0.0, -1.0]], [a])[0] for a in axes]
    rest = Rotation.random(TUMBLE_POSES - len(faces), random_state=rng)
    world_R_cam = Rotation.concatenate(faces + [rest])
    p = np.asarray(part_centre, float) + np.array([0.0, 0.0, 0.3])
    period = TUMBLE_HOLD_S + TUMBLE_TURN_S
    turns = [Slerp([0.0, 1.0], world_R_cam[[i, min(i + 1, TUMBLE_POSES - 1)]]) for i in range(TUMBLE_POSES)]

    def fn(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, float)
        i = np.clip(np.floor(t / period).astype(int), 0, TUMBLE_POSES - 1)
        u = smoothstep7(np.clip((t - i * period - TUMBLE_HOLD_S) / TUMBLE_TURN_S, 0.0, 1.0))
        R = np.empty((len(t), 3, 3))
        for n in np.unique(i):
            sel = i == n
            R[sel] = turns[n](u[sel]).as_matrix()
        return np.repeat(p[None, :], len(t), axis=0), R

    return fn
