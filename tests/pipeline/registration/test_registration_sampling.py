"""The voxel thinning (``registration.sampling``, docs/registration.md): a scan's voxels counted over its box
(``occupied_voxels``) give what sorting them gives, bit for bit."""

from __future__ import annotations

import numpy as np
from tandemscan.pipeline.registration import sampling
from tandemscan.pipeline.registration.sampling import occupied_voxels, voxel_centroids


def test_voxels_counted_over_the_box_are_those_sorting_finds():
    rng = np.random.default_rng(3)
    index = rng.integers(0, 5000, 20_000) ** 2 // 5000  # repeats, gaps and an uneven spread in [0, 5000)
    occupied, rank, counts = occupied_voxels(index, 5000)
    unique, inverse, unique_counts = np.unique(index, return_inverse=True, return_counts=True)
    assert np.array_equal(occupied, unique) and np.array_equal(rank, inverse)
    assert np.array_equal(counts, unique_counts) and rank.dtype == index.dtype


def test_a_scans_centroids_counted_over_its_box_are_the_sorted_ones(monkeypatch):
    """A scan-like patch (60 k points, a box of about two voxels a point at 1 mm: counted densely) thinned as it is
    and with the dense count switched off (sorted): the same centroids and counts, bit for bit."""
    rng = np.random.default_rng(4)
    xy = rng.uniform([-150.0, -100.0], [150.0, 100.0], (60_000, 2))
    P = np.c_[xy, 0.002 * xy[:, 0] + rng.normal(0.0, 0.05, len(xy))]
    counts = []
    monkeypatch.setattr(sampling, "occupied_voxels", lambda *a: counts.append(1) or occupied_voxels(*a))
    counted = voxel_centroids(P, 1.0)
    monkeypatch.setattr(sampling, "DENSE_BOX_VOXELS", 0)
    sorted_ = voxel_centroids(P, 1.0)
    assert counts == [1]  # the first counted over the box, the second sorted
    assert len(counted[0]) < len(P) and counted[1].sum() == len(P)
    assert np.array_equal(counted[0], sorted_[0]) and np.array_equal(counted[1], sorted_[1])
