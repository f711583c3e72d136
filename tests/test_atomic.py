"""The one atomic file write (glossrig.core.atomic): content, mode, no half files, no clobbering."""
from __future__ import annotations

import json
import stat

import pytest

from glossrig.core.atomic import atomic_write, atomic_write_bytes, atomic_write_json, atomic_write_text


def test_writes_and_replaces_with_mode_0644(tmp_path):
    p = tmp_path / "a.json"
    atomic_write_json(p, {"x": 1})
    assert p.read_text() == '{\n "x": 1\n}\n'
    assert stat.S_IMODE(p.stat().st_mode) == 0o644
    atomic_write_text(p, "new")
    assert p.read_text() == "new" and list(tmp_path.iterdir()) == [p]


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    p = tmp_path / "a.bin"
    atomic_write_bytes(p, b"old")

    def fail(tmp):
        tmp.write_bytes(b"half")
        raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError):
        atomic_write(p, fail)
    assert p.read_bytes() == b"old" and list(tmp_path.iterdir()) == [p]


def test_without_overwrite_an_existing_file_is_kept(tmp_path):
    p = tmp_path / "a.txt"
    atomic_write_text(p, "first", overwrite=False)
    with pytest.raises(FileExistsError):
        atomic_write_text(p, "second", overwrite=False)
    assert p.read_text() == "first" and list(tmp_path.iterdir()) == [p]
    assert json.loads(atomic_write_json(tmp_path / "b.json", [1], indent=None).read_text()) == [1]
