"""The door-plate term's text comparison (the term itself is tested on the duplex's plates in tests/sim)."""

from __future__ import annotations

import pytest

from bimfactor.bim.plates import normalise_text
from bimfactor.localization.text import edit_distance


@pytest.mark.parametrize(
    ("a", "b", "n"),
    [("101", "101", 0), ("101", "107", 1), ("A101", "B101", 1), ("", "12", 2), ("KITTEN", "SITTING", 3)],
)
def test_edit_distance(a: str, b: str, n: int) -> None:
    assert edit_distance(a, b) == n == edit_distance(b, a)


def test_normalise_text() -> None:
    assert normalise_text(" b-101 ") == "B101" and normalise_text("Raum 2.04") == "RAUM204"
