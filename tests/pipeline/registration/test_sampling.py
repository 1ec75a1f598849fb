"""Thinning by voxels (``registration.sampling``, docs/registration.md): a cloud's voxels counted over its box, as a
dense scan's are, give the thinning that sorting them gives, bit for bit."""

from __future__ import annotations

import numpy as np
from tandemscan.pipeline.registration import sampling


def test_occupied_voxels_are_np_unique_of_the_voxel_numbers():
    index = np.random.default_rng(2).integers(0, 5_000, 20_000)
    for got, want in zip(sampling.occupied_voxels(index, 5_000),
                         np.unique(index, return_inverse=True, return_counts=True), strict=True):
        np.testing.assert_array_equal(got, want)


def test_a_dense_scans_voxels_counted_over_its_box_are_its_sorted_thinning(monkeypatch):
    rng = np.random.default_rng(3)
    xy = rng.uniform(-40.0, 40.0, (60_000, 2))  # a patch 0.3 mm apart, 440 mm away: a few voxels of depth
    points = np.c_[xy, 440.0 + 2.0 * np.sin(xy[:, 0] / 9.0) + rng.normal(0.0, 0.05, len(xy))].astype(np.float32)
    counted_boxes = []
    real = sampling.occupied_voxels
    monkeypatch.setattr(sampling, "occupied_voxels", lambda *a: counted_boxes.append(a[1]) or real(*a))
    counted = sampling.voxel_centroids(points, 1.0)
    assert counted_boxes and len(counted[0]) > 5_000  # counted over its box, not sorted
    monkeypatch.setattr(sampling, "DENSE_BOX_VOXELS", 0)  # every box sorted
    sorted_ = sampling.voxel_centroids(points, 1.0)
    assert len(counted_boxes) == 1
    for got, want in zip(counted, sorted_, strict=True):
        np.testing.assert_array_equal(got, want)
