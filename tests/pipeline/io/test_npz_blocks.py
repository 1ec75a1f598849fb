"""``npz_blocks.row_blocks``: an ``.npz`` file's arrays read a block of rows at a time, the same values as read
whole."""

from __future__ import annotations

import numpy as np
import pytest
from tandemscan.pipeline.io.npz_blocks import row_blocks


def test_the_blocks_put_together_are_the_arrays_in_either_order(tmp_path):
    rng = np.random.default_rng(1)
    a, b, c = rng.normal(size=(1003, 3)), np.asfortranarray(rng.normal(size=(1003, 3))), rng.random(1003, np.float32)
    np.savez(tmp_path / "x.npz", a=a, b=b, c=c)
    blocks = list(row_blocks(tmp_path / "x.npz", ("a", "b", "c"), 100))
    assert [len(block["a"]) for block in blocks] == [100] * 10 + [3]
    for name, whole in (("a", a), ("b", b), ("c", c)):
        got = np.concatenate([block[name] for block in blocks])
        assert got.dtype == whole.dtype and np.array_equal(got, whole)


def test_arrays_of_other_lengths_or_a_bad_block_are_refused(tmp_path):
    np.savez(tmp_path / "x.npz", a=np.zeros((5, 3)), b=np.zeros(4))
    with pytest.raises(ValueError, match="differ in rows"):
        list(row_blocks(tmp_path / "x.npz", ("a", "b"), 2))
    with pytest.raises(ValueError, match="at least 1"):
        list(row_blocks(tmp_path / "x.npz", ("a",), 0))
    np.savez(tmp_path / "empty.npz", a=np.zeros((0, 3)))
    assert list(row_blocks(tmp_path / "empty.npz", ("a",), 10)) == []
