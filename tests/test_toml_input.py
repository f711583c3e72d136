"""TOML inputs (rig, machine description) fail with the file's name and the problem."""
from __future__ import annotations

import pytest

from glossrig.core.errors import InputError
from glossrig.core.fabrication.machine import load_machine
from glossrig.core.rig import load_rig
from glossrig.hardware.toolpath_check import load_machine_limits


def test_missing_rig_file_is_named(tmp_path):
    with pytest.raises(InputError, match=r"nope\.toml: rig file not found"):
        load_rig(tmp_path / "nope.toml")


def test_invalid_toml_names_file_and_line(tmp_path):
    bad = tmp_path / "rig.toml"
    bad.write_text("[cylinder]\nradius_with_sample = = 3\n")
    with pytest.raises(InputError, match=r"rig\.toml: rig file is not valid TOML: .*line 2"):
        load_rig(bad)


@pytest.mark.parametrize("loader", [load_machine, load_machine_limits])
def test_undecodable_machine_description_is_named(tmp_path, loader):
    bad = tmp_path / "machine.toml"
    bad.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(InputError, match=r"machine\.toml: cannot read machine description"):
        loader(bad)
