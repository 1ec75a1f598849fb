"""Which scan pairs a job's correction registers, and how overlaps are thinned before registration."""

from __future__ import annotations

import numpy as np
import pytest
from tandemscan.pipeline.registration.overlap import OverlapError, PairSelector, extract_overlap, overlapping_pairs
from tandemscan.pipeline.registration.sampling import thin_evenly


def _patch(x0_mm: float, y0_mm: float = 0.0, size_mm: float = 100.0, step_mm: float = 2.0) -> np.ndarray:
    """A flat square patch (z = 0) of points every ``step_mm``, its corner at (x0, y0)."""
    g = np.arange(0.0, size_mm, step_mm)
    x, y = np.meshgrid(g + x0_mm, g + y0_mm)
    return np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])


def test_raster_neighbours_are_paired_and_corner_touches_dropped():
    # a row of patches overlapping their neighbour by 40 mm; patch 4 overlaps patch 0 only at a 10 mm corner;
    # patch 5 is far away
    clouds = [_patch(0), _patch(60), _patch(120), _patch(180), _patch(-90, -90), _patch(5000)]
    stations = [0, 0, 0, 0, 0, 0]
    assert overlapping_pairs(clouds, stations, cell_mm=10.0, max_partners=1) == [(0, 1), (0, 4), (1, 2), (2, 3)]
    # with two partners the weaker links come back: every pair that shares a cell
    pairs = overlapping_pairs(clouds, stations, cell_mm=10.0, max_partners=2)
    assert (0, 4) in pairs and all(5 not in p for p in pairs)
    assert (0, 2) not in pairs                         # 0 and 2 share no cell at all


def test_each_station_keeps_links_to_the_others():
    # patch 2 (another tracker station) shares 4 cell columns with patch 1 and one with patch 0, while 0 and 1
    # share 7: a cap of one partner per scan still keeps each scan's best link to the other station
    clouds = [_patch(0), _patch(30), _patch(90)]
    assert overlapping_pairs(clouds, [0, 0, 1], cell_mm=10.0, max_partners=1) == [(0, 1), (0, 2), (1, 2)]
    # one station: patch 0's only kept partner is 1, and patch 2's is 1, so the weak 0-2 link goes
    assert overlapping_pairs(clouds, [0, 0, 0], cell_mm=10.0, max_partners=1) == [(0, 1), (1, 2)]


def test_pair_selection_rejects_bad_settings():
    with pytest.raises(OverlapError):
        overlapping_pairs([_patch(0)], [0], cell_mm=0.0, max_partners=3)
    with pytest.raises(OverlapError):
        overlapping_pairs([_patch(0)], [0], cell_mm=10.0, max_partners=0)
    with pytest.raises(OverlapError, match="cloud 1"):
        overlapping_pairs([_patch(0), np.zeros((3, 2))], [0, 0], cell_mm=10.0, max_partners=3)
    assert overlapping_pairs([], [], cell_mm=10.0, max_partners=3) == []


def test_thinning_keeps_the_ends_and_spreads_evenly():
    idx = np.arange(100, 1100)
    thin = thin_evenly(idx, 11)
    assert thin[0] == 100 and thin[-1] == 1099 and len(np.unique(thin)) == 11
    assert set(np.diff(thin)) <= {99, 100}
    np.testing.assert_array_equal(thin_evenly(idx[:5], 11), idx[:5])


def test_pairs_selected_as_clouds_arrive_include_every_final_pair():
    # a random walk of patches over three tracker stations: the pairs the incremental selector offers when
    # each cloud arrives hold every pair of the selection over all clouds, with few extra
    rng = np.random.default_rng(3)
    corners = np.cumsum(rng.uniform(-60, 60, size=(40, 2)), axis=0)
    clouds = [_patch(x, y, size_mm=80.0, step_mm=4.0) for x, y in corners]
    stations = np.repeat([0, 1, 2], [15, 15, 10])
    for partners in (1, 2, 4):
        selector = PairSelector(10.0, partners)
        offered = {(i, j) for j, c in enumerate(clouds) for i in selector.add(c, stations[j])}
        final = set(overlapping_pairs(clouds, stations, cell_mm=10.0, max_partners=partners))
        assert final <= offered
        assert len(offered) <= 2 * len(final)
    # a pair offered early and displaced later is in the offered set but not in the final selection
    clouds = [_patch(0), _patch(40), _patch(10)]
    selector = PairSelector(10.0, 1)
    offered = {(i, j) for j, c in enumerate(clouds) for i in selector.add(c, 0)}
    assert (0, 1) in offered and (0, 1) not in overlapping_pairs(clouds, [0, 0, 0], 10.0, 1)


def test_a_pair_stays_kept_until_displaced_and_every_final_pair_is_kept_throughout():
    """``PairSelector.kept``: every pair the selection over all clouds holds is kept after each arrival from its
    later cloud's on; a pair displaced by a later cloud is not kept from then on, never again."""
    rng = np.random.default_rng(5)
    corners = np.cumsum(rng.uniform(-60, 60, size=(30, 2)), axis=0)
    clouds = [_patch(x, y, size_mm=80.0, step_mm=4.0) for x, y in corners]
    stations = np.repeat([0, 1], [18, 12])
    final = set(overlapping_pairs(clouds, stations, cell_mm=10.0, max_partners=2))
    selector, offered, dropped = PairSelector(10.0, 2), set(), set()
    for j, c in enumerate(clouds):
        offered |= {(i, j) for i in selector.add(c, stations[j])}
        kept = {p for p in offered if selector.kept(*p)}
        assert dropped.isdisjoint(kept)
        dropped |= offered - kept
        assert {p for p in final if p[1] <= j} <= kept
    assert dropped and kept == final


def test_overlap_from_prebuilt_trees_is_the_overlap_of_the_moved_source():
    """``overlap_at`` (trees built once, the target moved into the source's frame) selects exactly what
    ``extract_overlap`` selects on the moved source: a wrong direction of the transform would not."""
    from scipy.spatial import cKDTree
    from tandemscan.pipeline.geometry.frames import from_rotvec, transform_points
    from tandemscan.pipeline.registration.overlap import overlap_at

    rng = np.random.default_rng(3)
    source, target = rng.uniform(0, 100, (4000, 3)), rng.uniform(30, 130, (4000, 3))
    T = from_rotvec([5.0, -2.0, 3.0], [0.05, 0.1, -0.08])
    expected = extract_overlap(transform_points(T, source), target, 3.0)
    got = overlap_at(source, cKDTree(source), target, cKDTree(target), T, 3.0)
    assert len(expected.source_idx) > 100
    np.testing.assert_array_equal(got.source_idx, expected.source_idx)
    np.testing.assert_array_equal(got.target_idx, expected.target_idx)
