"""``compute.StoredResults`` (docs/compute.md): a backend whose kept results wait in files of a folder, not where they
were computed; each unit given their handles reads them, and a file lives as long as this process's handle to it."""

from __future__ import annotations

import gc

import numpy as np
from tandemscan.pipeline.compute import LocalBackend, StoredResult, StoredResults


def _scaled(unit: float, values: np.ndarray) -> np.ndarray:
    return unit * values


def test_kept_results_are_files_read_by_the_units_that_take_them(tmp_path):
    folder = tmp_path / "kept"
    with StoredResults(LocalBackend(2), folder) as backend:
        kept = backend.keep(np.arange, [3, 4], ["arange-3", "arange-4"])
        assert all(isinstance(h, StoredResult) for h in kept)
        assert sorted(p.name for p in folder.iterdir()) == ["arange-3.pickle", "arange-4.pickle"]
        np.testing.assert_array_equal(kept[1].read(), np.arange(4))
        # a unit given handles reads them (map), also where its result is kept in turn (keep)
        assert [list(v) for v in backend.map(_scaled, [2.0, 3.0], ["x2", "x3"], [(h,) for h in kept])] == [
            [0, 2, 4], [0, 3, 6, 9]]
        again = backend.keep(_scaled, [10.0], ["x10"], [(kept[0],)])
        np.testing.assert_array_equal(again[0].read(), [0, 10, 20])
        del kept[0]                  # its last handle here: its file goes, the others stay
        gc.collect()
        assert sorted(p.name for p in folder.iterdir()) == ["arange-4.pickle", "x10.pickle"]
    assert not folder.exists()       # removed at the end of the block; the wrapped backend is the caller's
    assert backend.map(abs, [-1], ["abs"]) == [1]
