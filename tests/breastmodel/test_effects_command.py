"""``breastmodel effects``: the registry as a user reads it."""

import pytest

from breastmodel.cli import main
from mechanics.effects import EFFECTS


def test_lists_every_registered_effect(capsys):
    assert main(["effects"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert sorted(line.split()[0] for line in out) == sorted(EFFECTS)


def test_describes_one_effect_with_units_and_bounds(capsys):
    assert main(["effects", "skin"]) == 0
    out = capsys.readouterr().out
    assert "wrinkl" in out and "face_sets:skin" in out
    row = next(line for line in out.splitlines() if line.startswith("E "))
    assert row.split()[1:4] == ["kPa", "4", "[1,"]


def test_unknown_effect_is_one_clear_error(capsys):
    assert main(["effects", "nope"]) == 1
    err = capsys.readouterr().err
    assert "no effect 'nope'" in err and "skin" in err
    with pytest.raises(SystemExit):
        main(["effects", "--help"])
