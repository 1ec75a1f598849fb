"""``durable.write_durably`` and ``write_replacing``: a write that fails leaves the file as it was and no ``.part``
beside it (the tiled stages' clean-up removes the files they name, not a half-written temporary)."""

from __future__ import annotations

import pytest
from tandemscan.pipeline.io.durable import write_durably, write_replacing


@pytest.mark.parametrize("write_file", [write_durably, write_replacing])
def test_a_failed_write_leaves_the_old_file_and_no_part(write_file, tmp_path):
    path = tmp_path / "tiles" / "tile.npz"
    write_file(path, lambda f: f.write(b"old"))
    assert path.read_bytes() == b"old"

    def half_then_full_disk(f):
        f.write(b"half a tile")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space left"):
        write_file(path, half_then_full_disk)
    assert path.read_bytes() == b"old"
    assert sorted(p.name for p in path.parent.iterdir()) == ["tile.npz"]
    write_file(path, lambda f: f.write(b"new"))
    assert path.read_bytes() == b"new"


def test_a_durable_write_returns_the_files_size(tmp_path):
    assert write_durably(tmp_path / "a.bin", lambda f: f.write(b"x" * 1234)) == 1234
