"""Render docs/results/speed.json (OUT/results.json of `bimfactor bench speed`) into the table of docs/speed.md.

.venv/bin/bimfactor bench speed -o runs/bench-speed && cp runs/bench-speed/results.json docs/results/speed.json
.venv/bin/python tools/render_speed.py            # rewrite the table between the speed markers
.venv/bin/python tools/render_speed.py --check    # exit 1 when it is out of date
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from bimfactor.evaluation.speedtable import SpeedRow, format_speed_table

sys.path.insert(0, str(Path(__file__).resolve().parent))
from render_results import replace_block, write_or_check  # a sibling script

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "docs" / "results" / "speed.json"
PAGE = ROOT / "docs" / "speed.md"
BEGIN, END = "<!-- speed:begin -->", "<!-- speed:end -->"


def render() -> str:
    report = json.loads(RESULTS.read_text())
    rows = [SpeedRow(r["what"], r["building"], r["value"], r["unit"], r["target"]) for r in report["rows"]]
    return format_speed_table(rows)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 when docs/speed.md is out of date")
    args = parser.parse_args()
    page = replace_block(PAGE.read_text(), render(), BEGIN, END)
    return write_or_check({PAGE: page}, args.check, "tools/render_speed.py")


if __name__ == "__main__":
    raise SystemExit(main())
