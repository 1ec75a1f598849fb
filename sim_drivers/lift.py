"""The simulated lifting column of the measurement AGV (``[lift] enabled = true``), acting on the SimWorld.

It implements :class:`tandemscan.drivers.interfaces.Lift`: a vertical axis under the arm that moves within
``[lift] min_mm .. max_mm`` at ``speed_mm_s`` (simulated time, ``sim.time_scale``), refuses motion while the
safety latch is tripped, and moves as part of the measurement robot, so the world's motion log flags any moment
it moves with the tracking robot.
"""

from __future__ import annotations

from tandemscan.drivers.errors import DeviceTimeout, OutOfReach
from tandemscan.drivers.interfaces import DeviceState
from tandemscan.sim_drivers.twins import _SimDevice
from tandemscan.sim_drivers.world import SimWorld


class SimLift(_SimDevice):
    """A lifting-column twin: the true height is ``world.lift_mm`` (mm above the arm's mount)."""

    async def move_to(self, height_mm: float, timeout_s: float | None = None) -> float:
        self._require_connected()
        self._require_motion_allowed()
        cfg = self.world.config.lift
        if not cfg.min_mm - 1e-6 <= height_mm <= cfg.max_mm + 1e-6:
            raise OutOfReach(self.name, f"column height {height_mm:.0f} mm outside {cfg.min_mm:.0f} .. "
                                        f"{cfg.max_mm:.0f} mm")
        duration = abs(height_mm - self.world.lift_mm) / cfg.speed_mm_s
        limit = cfg.timeout_s if timeout_s is None else timeout_s
        if duration > limit:
            raise DeviceTimeout(self.name, f"move needs {duration:.0f} s, over the {limit:.0f} s timeout")
        self._state = DeviceState.MOVING
        self.world.motion.start(SimWorld.MEASURE_ROBOT)
        try:
            await self._elapse(duration)
            self.world.lift_mm = float(height_mm)
        finally:
            self.world.motion.stop(SimWorld.MEASURE_ROBOT)
            self._state = DeviceState.IDLE
        return self.world.lift_mm

    async def height(self) -> float:
        self._require_connected()
        return self.world.lift_mm

    async def stop(self) -> None:
        self._state = DeviceState.IDLE

    def _detail(self) -> dict[str, object]:
        return {"height_mm": self.world.lift_mm}
