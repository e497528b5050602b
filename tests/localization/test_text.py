"""The door-plate term's text comparison (the term itself is tested on the duplex's plates in tests/sim)."""

from __future__ import annotations

import pytest

from bimfactor.bim.plates import look_alikes, normalise_text
from bimfactor.localization.measurements.text import edit_distance, edit_operations


@pytest.mark.parametrize(
    ("a", "b", "n"),
    [("101", "101", 0), ("101", "107", 1), ("A101", "B101", 1), ("", "12", 2), ("KITTEN", "SITTING", 3)],
)
def test_edit_distance(a: str, b: str, n: int) -> None:
    assert edit_distance(a, b) == n == edit_distance(b, a)


def test_look_alikes_cost_part_of_an_edit() -> None:
    assert "8" in look_alikes("B") and "B" in look_alikes("8") and "O" in look_alikes("0") and look_alikes("K") == ""
    assert edit_distance("B204", "8204", 0.5) == 0.5 == edit_distance("8204", "B204", 0.5)
    assert edit_distance("A204", "8204", 0.5) == 1.0  # "A" and "8" are not look-alikes
    assert edit_distance("B1O1", "B101", 0.25) == 0.25 and edit_distance("B1O1", "B101") == 1.0
    # A substitution that costs more than a deletion and an insertion is done as those.
    assert edit_distance("B204", "8204", 3.0) == 2.0


def test_edit_operations_count_what_a_reader_did() -> None:
    assert edit_operations("B201", "8201", 0.5) == {"same": 3, "look_alike": 1, "other": 0, "dropped": 0, "inserted": 0}
    assert edit_operations("A101", "101") == {"same": 3, "look_alike": 0, "other": 0, "dropped": 1, "inserted": 0}
    assert edit_operations("A103", "A103A104")["inserted"] == 4  # two neighbouring plates read as one
    assert edit_operations("B201", "0201", 0.5)["other"] == 1


def test_normalise_text() -> None:
    assert normalise_text(" b-101 ") == "B101" and normalise_text("Raum 2.04") == "RAUM204"
