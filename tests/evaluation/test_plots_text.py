"""Figures with text the fonts cannot draw (a building named in Chinese) are written without matplotlib's warning per
missing glyph, so a command's stderr stays empty; other warnings still show."""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path

import matplotlib.pyplot as plt

from bimfactor.evaluation.plots import save_figure
from bimfactor.io.preview import missing_glyphs_quiet
from bimfactor.io.sequence import write_sequence
from tests.io.synthetic import make_frames, make_meta

CJK_NAME = "建筑"


def test_save_figure_draws_cjk_text_without_glyph_warnings(tmp_path: Path) -> None:
    fig, ax = plt.subplots()
    ax.set_title(f"{CJK_NAME}.ifc — 1F")
    ax.text(0.5, 0.5, "办公室 (Büro)")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        path = save_figure(fig, tmp_path / "plan.png")
    assert path.stat().st_size > 1000
    assert [str(w.message) for w in caught] == []


def test_only_the_missing_glyph_warning_is_silenced() -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with missing_glyphs_quiet():
            warnings.warn(
                "Glyph 24314 (\\N{CJK UNIFIED IDEOGRAPH-5EFA}) missing from font(s) DejaVu Sans.", stacklevel=1
            )
            warnings.warn("Glyph 24314 missing from current font.", stacklevel=1)  # matplotlib < 3.6
            warnings.warn("something else about a Glyph", UserWarning, stacklevel=1)
            warnings.warn("Glyph 1 missing from font(s) X.", DeprecationWarning, stacklevel=1)
        warnings.warn("Glyph 3 (x) missing from font(s) DejaVu Sans.", stacklevel=1)  # outside: shown
    assert [str(w.message) for w in caught] == [
        "something else about a Glyph",
        "Glyph 1 missing from font(s) X.",
        "Glyph 3 (x) missing from font(s) DejaVu Sans.",
    ]


def _bimfactor(*args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "bimfactor", *map(str, args)], capture_output=True, text=True, timeout=300
    )


def test_a_sequence_named_in_chinese_converts_with_an_empty_stderr(tmp_path: Path) -> None:
    """`convert` draws the preview titled with the sequence's name: no 'Glyph ... missing' on stderr."""
    write_sequence(tmp_path / "seq", make_meta(CJK_NAME), make_frames(2))
    proc = _bimfactor("convert", "sequence", tmp_path / "seq", "-o", tmp_path / "out", "--all-frames")
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    assert (tmp_path / "out" / "preview.png").stat().st_size > 5_000
