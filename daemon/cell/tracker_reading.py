"""The target's pose at rest: the one averaging of tracker readings the job runner and the calibration share."""

from __future__ import annotations

import numpy as np
from tandemscan.config.models import TrackerConfig
from tandemscan.drivers.interfaces import Tracker, TrackerReading
from tandemscan.pipeline.geometry import frames as F


def averaged_covariance(covariance: np.ndarray, samples: int, still_fraction: float) -> np.ndarray:
    """The 6x6 covariance of the mean of ``samples`` readings of one still period, each with ``covariance``, of
    which the share ``still_fraction`` is common to them all (``tracker.still_noise_fraction``): that share stays,
    the rest is divided by ``samples``."""
    return covariance * (still_fraction + (1.0 - still_fraction) / samples)


async def read_at_rest(tracker: Tracker, samples: int, config: TrackerConfig) -> TrackerReading:
    """``samples`` readings of the still target averaged: the mean ``T_C_T`` (mm), the mean covariance reduced by
    :func:`averaged_covariance` with the tracker's ``still_noise_fraction`` (order translation then rotation, the
    driver's), the last reading's timestamp and frame number; each read waits at most ``config.timeout_s``."""
    readings = [await tracker.read_pose(config.timeout_s) for _ in range(samples)]
    if samples == 1:
        return readings[0]
    return TrackerReading(F.mean_pose([r.T_C_T for r in readings]),
                          averaged_covariance(np.mean([r.covariance for r in readings], axis=0), samples,
                                              config.still_noise_fraction),
                          readings[-1].timestamp_s, readings[-1].frame_number)


async def read_for_transfer(tracker: Tracker, config: TrackerConfig) -> TrackerReading:
    """One side of a coordinate transfer (Eq. 2): ``config.transfer_samples`` readings of the still target
    averaged, their covariance counting the share averaging does not reduce (``still_noise_fraction``)."""
    return await read_at_rest(tracker, config.transfer_samples, config)
