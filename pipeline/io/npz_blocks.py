"""An ``.npz`` file's arrays read a block of rows at a time (docs/compute.md, "Tiles"): a streamed writer
(``export.write_ply_streamed``: ``cloud.ply`` and ``cloud_deviation.ply`` from the tiles' files) holds one block of
each array, never a whole tile.

``np.savez`` stores each array uncompressed as an ``.npy`` member of a zip file: its header, then its values in
C order, so consecutive rows of a C-ordered array are consecutive bytes, read from the member as they come.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import BinaryIO
from zipfile import ZipFile

import numpy as np
from numpy.lib import format as npy

#: rows of each array a streamed reader of the tiles' files holds at a time (6 MB of a float64 (N, 3) array)
BLOCK_ROWS = 250_000


def _header(f: BinaryIO) -> tuple[tuple[int, ...], bool, np.dtype]:
    """(shape, Fortran order, dtype) of the ``.npy`` stream ``f``, left at its first value."""
    version = npy.read_magic(f)
    read = npy.read_array_header_1_0 if version == (1, 0) else npy.read_array_header_2_0
    return read(f)


def _rows(f: BinaryIO, dtype: np.dtype, row_shape: tuple[int, ...], count: int) -> np.ndarray:
    """The next ``count`` rows (each of ``row_shape``) of the ``.npy`` stream ``f``."""
    size = int(np.prod(row_shape, dtype=np.int64)) * count
    data = f.read(size * dtype.itemsize)
    if len(data) != size * dtype.itemsize:
        raise ValueError(f"npz member ended early: {len(data)} of {size * dtype.itemsize} bytes")
    return np.frombuffer(data, dtype, size).reshape((count, *row_shape))


def row_blocks(path: Path | str, names: Sequence[str], rows: int) -> Iterator[dict[str, np.ndarray]]:
    """The arrays ``names`` of the ``.npz`` file ``path`` (``np.savez``: each the same number of rows), ``rows``
    rows of each at a time, in order: ``{name: block}`` (read-only views of the bytes read; an empty file yields
    nothing). An array stored in Fortran order is read whole and cut into blocks."""
    if rows < 1:
        raise ValueError(f"rows must be at least 1, got {rows}")
    with ZipFile(path) as z:
        members = {name: z.open(f"{name}.npy") for name in names}
        try:
            layout = {name: _header(f) for name, f in members.items()}
            counts = {shape[0] for shape, _, _ in layout.values()}
            if len(counts) > 1:
                raise ValueError(f"{path}: arrays {list(names)} differ in rows: {sorted(counts)}")
            n = counts.pop() if counts else 0
            whole = {name: npy.read_array(z.open(f"{name}.npy")) for name, (_, fortran, _) in layout.items()
                     if fortran}
            for lo in range(0, n, rows):
                count = min(rows, n - lo)
                yield {name: whole[name][lo:lo + count] if name in whole else
                       _rows(members[name], dtype, shape[1:], count)
                       for name, (shape, _, dtype) in layout.items()}
        finally:
            for f in members.values():
                f.close()
