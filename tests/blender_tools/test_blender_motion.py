"""The motion rules of a sequence (blender_tools.motion, no bpy): over many seeds and every layout, no two
road users' boxes meet in any frame, nobody enters a building, speeds stay in their classes' ranges,
cars wait at red signals, and the plan is deterministic and leaves the scene's build alone."""
from __future__ import annotations

import math

import numpy as np
import pytest

from blender_tools.motion import CAR_SPEED, WALK_SPEED, WALL_HEIGHT, Footprint, Signals, _obstacles, plan_motion
from blender_tools.routes import Route, car_route, opposite_arm, walk_route
from blender_tools.scenarios import build_model, catalog
from blender_tools.street import LAYOUTS_SPEC, Street, overlap

LAYOUT_NAMES = [n for n in catalog() if n != "toy"]


def _quads(feet: dict, motion, frame):
    return {n: feet[n].quad(p[frame, :2], p[frame, 3]) for n, p in motion.poses.items()}


def _static(model) -> tuple[list, list[str], dict]:
    """Footprints of the buildings and of the other obstacles, which each is, and the road users' feet."""
    buildings = [Footprint.of(a, below=WALL_HEIGHT).quad(a.location[:2], a.yaw) for a in model.actors
                 if a.extras.get("kind") == "building"]
    others = _obstacles(model)
    feet = {a.name: Footprint.of(a) for a in model.actors if a.cls != "other"}
    return buildings + others, ["building"] * len(buildings) + ["obstacle"] * len(others), feet


def _meetings(model, motion, frame, static) -> set[tuple[str, str]]:
    """Pairs of road users whose footprints overlap at ``frame``, and (name, "building") or (name,
    "obstacle") for one inside a building, or a wall, tree trunk or pole (``static``: ``_static``)."""
    quads = _quads(static[2], motion, frame)
    names = sorted(quads)
    everything = [quads[n] for n in names] + static[0]
    kinds = names + static[1]
    centre = np.array([q.mean(axis=0) for q in everything])
    radius = np.array([np.linalg.norm(q - q.mean(axis=0), axis=1).max() for q in everything])
    near = np.linalg.norm(centre[:, None] - centre[None], axis=2) <= radius[:, None] + radius[None]
    return {(names[i], kinds[j]) for i, j in zip(*np.nonzero(np.triu(near[:len(names)], k=1)))
            if overlap(everything[i], everything[j])}


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_no_two_road_users_meet_and_nobody_enters_a_building_in_any_frame(seed):
    for name in LAYOUT_NAMES:
        model = build_model(name, seed)
        motion = plan_motion(model, frames=30, fps=5.0, moving_cameras=2)
        static = _static(model)
        built = _meetings(model, motion, 0, static)  # the scene as built (a few walkers stand by a tree trunk)
        assert not [m for m in built if m[1] == "building"], (name, seed)
        for f in range(1, motion.frames):
            now = _meetings(model, motion, f, static)
            assert now <= built, (name, seed, f, now - built)


def test_road_users_move_within_their_speeds_and_cars_keep_their_lanes_moving():
    model = build_model("intersection_07", 0)
    fps = 10.0
    motion = plan_motion(model, frames=40, fps=fps)
    actors = {a.name: a for a in model.actors}
    car_speeds, walk_speeds = [], []
    for name, p in motion.poses.items():
        speed = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1) * fps
        (car_speeds if actors[name].cls == "car" else walk_speeds).append(speed.max())
    assert max(car_speeds) <= CAR_SPEED[1] + 1e-6 and max(walk_speeds) <= WALK_SPEED[1] + 1e-6
    moving_cars = [n for n in motion.moving if actors[n].cls == "car"]
    moving_people = [n for n in motion.moving if actors[n].cls == "pedestrian"]
    assert len(moving_cars) >= 3 and len(moving_people) >= 5
    # the camera cars are parked by default: a fixed rig
    mounts = {r.mounted_on for r in model.cameras}
    assert not mounts & set(motion.moving)
    # some pedestrians stand (those hidden behind parked vehicles at least)
    standing = [a.name for a in model.actors if a.cls == "pedestrian" and a.name not in motion.moving]
    assert standing


def test_moving_cameras_drive_the_first_camera_cars():
    model = build_model("intersection_01", 0)
    motion = plan_motion(model, frames=20, fps=5.0, moving_cameras=2)
    rigs = sorted(model.cameras, key=lambda r: r.name)
    assert {rigs[0].mounted_on, rigs[1].mounted_on} <= set(motion.moving)
    assert not {r.mounted_on for r in rigs[2:]} & set(motion.moving)


def test_the_plan_is_deterministic_and_draws_none_of_the_builds_numbers():
    a = plan_motion(build_model("intersection_03", 4), frames=12, fps=2.0)
    b = plan_motion(build_model("intersection_03", 4), frames=12, fps=2.0)
    assert a.moving == b.moving and all(np.array_equal(a.poses[n], b.poses[n]) for n in a.poses)
    model = build_model("intersection_03", 4)
    before = [(x.name, x.location, x.yaw) for x in model.actors]
    plan_motion(model, frames=5, fps=2.0)
    assert [(x.name, x.location, x.yaw) for x in model.actors] == before
    other = plan_motion(build_model("intersection_03-s1", 4), frames=12, fps=2.0)
    assert any(not np.array_equal(other.poses.get(n, 0), a.poses[n]) for n in a.poses)


def test_a_car_waits_at_its_red_signal_and_goes_on_green():
    street = Street(LAYOUTS_SPEC["intersection_01"])
    signals = Signals(4, 0.0)
    assert signals.green(0, 1.0) and signals.green(2, 1.0) and not signals.green(1, 1.0)
    assert not any(signals.green(k, 9.0) for k in range(4))  # the all-red clearance
    assert signals.green(1, 12.0) and not signals.green(0, 12.0)
    route = car_route(street, 0, 0, True, street.arm(0)[1] * 30 - street.arm(0)[2] * 1.65, 2.2)
    assert route.stop_at is not None and route.arm == 0
    # the route runs on to the opposite arm's outgoing lane
    end = route.points[-1]
    assert opposite_arm(street, 0) == 2 and end[0] < -30 and abs(end[1] + 1.65) < 1e-6


def test_a_pedestrian_heading_for_the_junction_turns_onto_the_crosswalk_and_crosses():
    street = Street(LAYOUTS_SPEC["intersection_01"])
    _, e, n = street.arm(0)
    start = e * 25 + n * (street.hw[0] + 1.5)
    route = walk_route(street, 0, start, math.pi)  # facing the junction (arm 0 runs along +x)
    lateral = route.points @ n
    assert lateral[0] > street.hw[0] and lateral[-1] < -street.hw[0]  # from one sidewalk to the other
    assert isinstance(route, Route) and route.length > 20


def test_the_toy_scene_moves_its_walker_and_keeps_its_parked_cars():
    model = build_model("toy", 0)
    motion = plan_motion(model, frames=3, fps=2.0)
    assert motion.moving == ["ped_open"]
    assert np.linalg.norm(motion.poses["ped_open"][-1, :2] - motion.poses["ped_open"][0, :2]) > 0.5


@pytest.mark.parametrize("frames, fps", [(10, 10.0), (5, 2.0)])
@pytest.mark.slow  # over ~5 s: outside the fast subset (./scripts/test -m "not slow")
def test_road_users_speed_up_and_brake_within_their_limits_in_every_frame(frames, fps):
    """Issue 74 item 7 (cars) and issue 83 item 2 (pedestrians): along its route a road user speeds up and brakes
    within its class's limits between any two frames (a stop for what fills the way ahead begins in time, as on a red
    signal or at the route's end); the speeds frames.json holds (displacement between frames: a turn's chord is
    shorter than its arc) within 0.75 m/s^2 of them, on every layout and redraws with moving camera cars."""
    from blender_tools.motion import ACCEL, BRAKE, WALK_ACCEL, WALK_BRAKE

    assert WALK_ACCEL <= 2.0 and WALK_BRAKE <= 2.0  # human limits (the data guide states them)
    limits = {"car": (ACCEL, BRAKE), "pedestrian": (WALK_ACCEL, WALK_BRAKE)}
    walked = 0
    for name in [*LAYOUT_NAMES, "intersection_07-s1", "intersection_10-s2", "procedural-5"]:
        model = build_model(name, 0)
        motion = plan_motion(model, frames, fps, moving_cameras=2)
        for a in (a for a in model.actors if a.cls in limits):
            up, down = limits[a.cls]
            along = np.diff(motion.speeds[a.name]) * fps
            assert along.min() >= -down - 1e-9 and along.max() <= up + 1e-9, (name, a.name, along)
            chord = np.linalg.norm(np.diff(motion.poses[a.name][:, :2], axis=0), axis=1) * fps
            written = np.diff(chord) * fps
            if len(written):
                assert written.min() >= -down - 0.75 and written.max() <= up + 0.75, (name, a.name, written)
            walked += a.cls == "pedestrian" and a.name in motion.moving
    assert walked > 20  # the pedestrians' rule was exercised, not only the cars'
