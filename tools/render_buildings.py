"""Render docs/results/buildings*.json (OUT/results.json of `bimfactor bench buildings`) into docs/buildings.md.

.venv/bin/bimfactor bench buildings --variant smcl+graph -o runs/bench-buildings
cp runs/bench-buildings/results.json docs/results/buildings.json
.venv/bin/python tools/render_buildings.py            # rewrite the tables between the markers
.venv/bin/python tools/render_buildings.py --check    # exit 1 when they are out of date
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from bimfactor.evaluation.buildings import format_buildings_report

sys.path.insert(0, str(Path(__file__).resolve().parent))
from render_results import replace_block, write_or_check  # a sibling script

ROOT = Path(__file__).resolve().parent.parent
PAGE = ROOT / "docs" / "buildings.md"
# marker name → the committed results it renders
RESULTS = {
    name: ROOT / "docs" / "results" / f"{name}.json"
    for name in (
        "buildings",  # the defaults: the shipped detector's eyes (perception.sim_preset: yolox)
        "buildings-paper-eyes",  # the same with the paper's open-vocabulary eyes (perception.sim_preset: paper)
        "buildings-150",  # the paper's eyes, 150-keyframe routes
        "buildings-active",  # the paper's eyes, --scenario active: each route passive and following the suggestions
        "buildings-storeys",  # --scenario storeys: routes that change floor, without and with the storey-change event
    )
}
EYES = ("buildings", "buildings-paper-eyes")  # the side-by-side table: the shipped detector's eyes, the paper's
CELLS = (  # (column, key in a variant's average, format)
    ("translation [m]", "trans_err_m", "{:.2f}"),
    ("room", "room_acc", "{:.0%}"),
    ("storey", "storey_acc", "{:.0%}"),
    ("success", "success_rate", "{:.0%}"),
    ("wrong conv.", "wrong_convergence_rate", "{:.0%}"),
)


def side_by_side(new: dict, old: dict) -> str:
    """Per building and variant, each cell as `shipped detector's eyes / paper's eyes`."""
    lines = [
        "| building | variant | " + " | ".join(c for c, _, _ in CELLS) + " |",
        "|---|---|" + "---|" * len(CELLS),
    ]
    for name, run in new["buildings"].items():
        before = old["buildings"].get(name)
        for variant in run["variants"]:
            cells = []
            for _, key, fmt in CELLS:
                now = fmt.format(run[variant]["average"][key])
                was = before[variant]["average"][key] if before and variant in before else None
                cells.append(now if was is None else f"{now} / {fmt.format(was)}")
            lines.append(f"| {name} | {variant} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def render(name: str) -> str:
    """One committed run's tables, without the report's own title line."""
    text = format_buildings_report(json.loads(RESULTS[name].read_text()))
    return text.split("\n", 2)[2].strip().replace("\n## ", "\n### ")  # under the page's own sections


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 when docs/buildings.md is out of date")
    args = parser.parse_args(argv)
    page = PAGE.read_text()
    for name, path in RESULTS.items():
        if path.is_file():
            page = replace_block(page, render(name), f"<!-- {name}:begin -->", f"<!-- {name}:end -->")
    new, old = (json.loads(RESULTS[name].read_text()) for name in EYES)
    page = replace_block(page, side_by_side(new, old), "<!-- eyes:begin -->", "<!-- eyes:end -->")
    return write_or_check({PAGE: page}, args.check, "tools/render_buildings.py")


if __name__ == "__main__":
    raise SystemExit(main())
