"""The target's pose at rest: the one averaging of tracker readings the job runner and the calibration share."""

from __future__ import annotations

import numpy as np
from tandemscan.drivers.interfaces import Tracker, TrackerReading
from tandemscan.pipeline.geometry import frames as F


async def read_at_rest(tracker: Tracker, samples: int, timeout_s: float | None = None) -> TrackerReading:
    """``samples`` readings of the still target averaged: the mean ``T_C_T`` (mm), the mean covariance divided by
    ``samples`` (the mean of independent readings; order translation then rotation, the driver's), the last
    reading's timestamp and frame number."""
    readings = [await tracker.read_pose(timeout_s) for _ in range(samples)]
    if samples == 1:
        return readings[0]
    return TrackerReading(F.mean_pose([r.T_C_T for r in readings]),
                          np.mean([r.covariance for r in readings], axis=0) / samples,
                          readings[-1].timestamp_s, readings[-1].frame_number)
