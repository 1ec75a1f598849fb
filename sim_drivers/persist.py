"""Keep the simulated world's state across a daemon restart, as a real cell keeps its robots where they stopped.

Without this a restarted daemon would rebuild the world at its start poses, teleporting both robots; with it,
a crash test sees what a real cell shows. Saved: the true and odometry pose of each chassis, the arm joints,
counters, the random generators' states (the emulated chassis's slip streams too), the tracker's still error of
the still period under way and the arm's flange offset of its last move (so the run goes on with the same noise
model, not a replay of its first draws), the world frame W of the job under way and the ground-truth observers'
logs. mm, rad. The twins save it as they act (:func:`keep_world_state`); the hardware-in-the-loop cell whenever an
emulated robot comes to rest (``sim_drivers.hil``); :class:`tandemscan.sim_drivers.cell.Simulation` restores it
when a session starts.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
from tandemscan.drivers.interfaces import ChassisPose
from tandemscan.sim_drivers.world import SimWorld


class WorldStateError(Exception):
    """A saved world state does not fit this world (different chassis or a corrupt file)."""


def world_state(world: SimWorld) -> dict:
    """The mutable state of ``world`` as JSON-able data."""
    return {
        "seed": world.config.sim.seed,
        "chassis": {
            name: {"true_pose": c.true_pose.tolist(), "moves": c.moves,
                   "odometry": [c.odometry.x_mm, c.odometry.y_mm, c.odometry.heading_rad],
                   "slip_rng": c.slip_rng.bit_generator.state}
            for name, c in world.chassis.items()
        },
        "joints_rad": world.joints_rad.tolist(),
        "captures": world.captures,
        "tracker_frames": world.tracker_frames,
        "rng": world.rng.bit_generator.state,
        "still_rng": world.still_rng.bit_generator.state,
        "still_T_C_T": None if world.still_T_C_T is None else world.still_T_C_T.tolist(),
        "still_unit": world.still_unit.tolist(),
        "arm_rng": world.arm_rng.bit_generator.state,
        "flange_offset": world.flange_offset.tolist(),
        "T_W_F": world.T_W_F.tolist(),
        "scoring": world.scoring,
    }


def restore_world_state(world: SimWorld, state: dict) -> None:
    """Put ``world`` back into ``state`` (from :func:`world_state` of a world made from the same config)."""
    if set(state.get("chassis", {})) != set(world.chassis) or state.get("seed") != world.config.sim.seed:
        raise WorldStateError("saved world state is from another cell configuration")
    for name, c in state["chassis"].items():
        truth = world.chassis[name]
        truth.true_pose = np.array(c["true_pose"], float)
        truth.odometry = ChassisPose(*c["odometry"])
        truth.moves = int(c["moves"])
        if "slip_rng" in c:  # a state saved before the emulated chassis's slip stream was kept has none
            truth.slip_rng.bit_generator.state = c["slip_rng"]
    world.joints_rad = np.array(state["joints_rad"], float)
    world.captures = int(state["captures"])
    world.tracker_frames = int(state["tracker_frames"])
    world.rng.bit_generator.state = state["rng"]
    if "still_rng" in state:  # a state saved before the tracker's still error existed has none
        world.still_rng.bit_generator.state = state["still_rng"]
        world.still_T_C_T = None if state["still_T_C_T"] is None else np.array(state["still_T_C_T"], float)
        world.still_unit = np.array(state["still_unit"], float)
    if "arm_rng" in state:  # a state saved before the arm's repeatability error existed has none
        world.arm_rng.bit_generator.state = state["arm_rng"]
        world.flange_offset = np.array(state["flange_offset"], float)
    world.T_W_F = np.array(state["T_W_F"], float)
    world.scoring = state.get("scoring", {})


def save_world_state(world: SimWorld, path: Path) -> None:
    """Write the state atomically (temporary file, rename): a killed process leaves the old or the new state,
    never half of one. No fsync: the twins save on the event loop at every reading, and an fsync there would
    stall the 50 Hz safety loop; after a power cut the simulated robots may be a reading behind, which a resumed
    job's fresh target reading absorbs."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(world_state(world), f)
    os.replace(tmp, path)


def keep_world_state(world: SimWorld) -> None:
    """Save the state to ``world.state_file`` where the world has one (the twins call this after every move,
    capture and reading, so the saved state is never behind what the job recorded)."""
    if world.state_file is not None:
        save_world_state(world, world.state_file)


def load_world_state(world: SimWorld, path: Path) -> bool:
    """Restore from ``path`` when it exists; returns whether it did."""
    path = Path(path)
    if not path.is_file():
        return False
    try:
        state = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise WorldStateError(f"{path}: unreadable world state: {e}") from e
    restore_world_state(world, state)
    return True
