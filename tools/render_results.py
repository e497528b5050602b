"""Render the committed `bimfactor bench paper` results into README.md and docs/results.md.

    .venv/bin/python tools/render_results.py            # rewrite both from docs/results/*.json
    .venv/bin/python tools/render_results.py --check    # exit 1 when either is out of date

Each file under docs/results/ is an `OUT/results.json` that `bimfactor bench paper` wrote, copied there under a name
that says what it is: `BUILDING-seedN-PRESET.json` (e.g. `paper-floor-seed0-default.json`), optionally
`BUILDING-seedN-PRESET-TAG.json` for another run of the same building, seed and preset (a kidnap scenario, say).
BUILDING `paper-floor` is the preset building `bench paper` synthesizes; any other is the IFC file of that name in
`../shared/data/ifc/`. SEED is the config's `seed` (`--set seed=N`), PRESET the `-c` preset (`default`: none). The
command that regenerates a file is built from its name and from the protocol and variants the file records, against
the preset's own settings; a run's other `--set`s are not in results.json, so give such a run a TAG and say so
beside it.

The README gets Table I in compact form (one row per variant, one column per untagged file: translation, orientation,
room accuracy) between `<!-- results:begin -->` and `<!-- results:end -->`; docs/results.md gets every file in full
(per trajectory, the 95 % bootstrap intervals, the scoring start, the same runs from their first frame) with the
command that regenerates it. Output depends on the files alone: rendering twice changes nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path

from bimfactor.evaluation.paper import table_notes

ROOT = Path(__file__).resolve().parent.parent
BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"
NAME = re.compile(r"^(?P<building>.+?)-seed(?P<seed>\d+)-(?P<preset>[A-Za-z0-9_]+)(?:-(?P<tag>[A-Za-z0-9_.-]+))?$")
PRESET_ORDER = {"default": 0, "paper": 1, "fast": 2}
VARIANT_ORDER = {"smcl": 0, "smcl+graph": 1, "refine": 2, "full": 3}
IFC_DIR = "../shared/data/ifc"
OTHER_BENCHMARKS = {  # their renderers
    "buildings": "tools/render_buildings.py",
    "speed": "tools/render_speed.py",
    "paper-ablation": "tools/paper_ablation.py",
}


@dataclass(frozen=True)
class Source:
    """One results.json and what its name says about it."""

    path: Path
    building: str
    seed: int
    preset: str
    tag: str | None
    report: dict

    @property
    def key(self) -> tuple:
        order = PRESET_ORDER.get(self.preset, len(PRESET_ORDER))
        return (self.building != "paper-floor", self.building, self.seed, order, self.preset, self.tag or "")

    @property
    def label(self) -> str:
        parts = [] if self.building == "paper-floor" else [self.building]
        parts += [f"seed {self.seed}", self.preset]
        return ", ".join(parts + ([self.tag] if self.tag else []))

    @property
    def variants(self) -> list[str]:
        return [v for v in self.report["variants"] if v in self.report]


def load_sources(results_dir: Path) -> list[Source]:
    """Every BUILDING-seedN-PRESET[-TAG].json under `results_dir`, sorted: paper floor first, then by seed and preset
    (default, paper, fast, others); a `bench paper` file whose name does not fit is an error, not skipped. Other
    benchmarks' results there (`bench buildings`, `bench speed`) have renderers of their own and are left alone."""
    sources = []
    for path in sorted(results_dir.glob("*.json")):
        try:
            report = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise SystemExit(f"error: {path}: not JSON ({exc.msg}, line {exc.lineno})") from None
        if not isinstance(report, dict):
            raise SystemExit(f"error: {path}: not a results.json of bimfactor bench paper")
        if report.get("benchmark") in OTHER_BENCHMARKS:
            continue
        match = NAME.match(path.stem)
        if not match:
            raise SystemExit(f"error: {path}: name must be BUILDING-seedN-PRESET[-TAG].json")
        if report.get("benchmark") != "paper":
            raise SystemExit(f"error: {path}: not a results.json of bimfactor bench paper")
        sources.append(Source(path, match["building"], int(match["seed"]), match["preset"], match["tag"], report))
    return sorted(sources, key=lambda s: s.key)


def _preset_settings(preset: str, seed: int) -> tuple[int, dict] | None:
    """The preset's seed and evaluation settings, or None when this checkout cannot load the preset."""
    try:
        from bimfactor.config import load_config
        from bimfactor.errors import BimfactorError
    except ImportError:
        return None
    try:
        cfg = load_config(None if preset == "default" else preset)
    except BimfactorError:
        return None
    return cfg.seed, cfg.evaluation.model_dump()


def _yaml(value) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


def command(source: Source) -> str:
    """The command whose OUT/results.json is this file, then the copy into docs/results/. Settings are given where the
    file's protocol differs from the preset's (all of them when the preset cannot be loaded here)."""
    protocol, stem = source.report["protocol"], source.path.stem
    settings = _preset_settings(source.preset, source.seed)
    base_seed, base = settings if settings else (None, {})
    args = ["bimfactor bench paper"]
    if source.preset != "default":
        args.append(f"-c {source.preset}")
    if source.building != "paper-floor":
        args.append(f"--ifc {IFC_DIR}/{source.building}.ifc")
    scenario = protocol.get("scenario", "global")
    if scenario != base.get("scenario"):
        args.append(f"--scenario {scenario}")
    sets = []
    if source.seed != base_seed:
        sets.append(("seed", source.seed))
    for key, name in (("trajectories", "num_trajectories"), ("steps", "trajectory_length"), ("repeats", "repeats")):
        if protocol[key] != base.get(name):
            sets.append((f"evaluation.{name}", protocol[key]))
    if scenario == "global" and protocol["score_from"] != base.get("score_from"):
        sets.append(("evaluation.score_from", protocol["score_from"]))
    if protocol["score_from"] == "filter_converged" and protocol["warmup_max_steps"] != base.get("warmup_max_steps"):
        sets.append(("evaluation.warmup_max_steps", protocol["warmup_max_steps"]))
    if protocol.get("known_storey", False) != base.get("known_storey"):
        sets.append(("evaluation.known_storey", protocol.get("known_storey", False)))
    extra = {"guess": ("guess_offset_m", "guess_offset_deg"), "kidnap": ("kidnap_at", "kidnap_resume_at")}
    for key in extra.get(scenario, ()):
        if protocol[key] != base.get(key):
            sets.append((f"evaluation.{key}", protocol[key]))
    args += [f"--set {key}={_yaml(value)}" for key, value in sets]
    if list(source.report["variants"]) != base.get("variants"):
        args += [f"--variant {variant}" for variant in source.report["variants"]]
    args.append(f"-o runs/{stem}")
    return f".venv/bin/{' '.join(args)} && cp runs/{stem}/results.json docs/results/{stem}.json"


def _link(source: Source, page: Path) -> str:
    return Path(os.path.relpath(source.path, page.parent)).as_posix()


def _cell(average: dict) -> str:
    return f"{average['trans_err_m']:.2f} m / {average['orient_err_deg']:.1f}° / {100 * average['room_acc']:.1f} %"


def _variant_rows(sources: list[Source]) -> list[str]:
    variants = {v for s in sources for v in s.variants}
    return sorted(variants, key=lambda v: (VARIANT_ORDER.get(v, 9), v))


def _scored(source: Source) -> str:
    protocol = source.report["protocol"]
    start = "the filter's converged flag" if protocol["score_from"] == "filter_converged" else "the first frame"
    runs = protocol["trajectories"] * protocol["repeats"]
    scenario = protocol.get("scenario", "global")
    return f"{runs} runs, {protocol['steps']} steps scored from {start}" + (
        f", scenario {scenario}" if scenario != "global" else ""
    )


def readme_block(sources: list[Source], readme: Path) -> str:
    """Table I in compact form: a row per variant, a column per untagged file."""
    main = [s for s in sources if s.tag is None]
    if not main:
        return "No results are committed yet: see `tools/render_results.py` for how to add one."
    header = ["Variant"] + [f"[{s.label}]({_link(s, readme)})" for s in main]
    lines = ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    for variant in _variant_rows(main):
        cells = [_cell(s.report[variant]["average"]) if variant in s.variants else "–" for s in main]
        lines.append(f"| {variant} | " + " | ".join(cells) + " |")
    lines += ["", "Translation / orientation error / room accuracy, mean over every scored step of every run."]
    lines += [f"- {s.label} ({_scored(s)}): `{command(s)}`" for s in main]
    return "\n".join(lines)


def _interval(average: dict, key: str, scale: float, digits: int) -> str:
    if key not in average:
        return "–"
    low, high = average[key]
    return f"{scale * low:.{digits}f}–{scale * high:.{digits}f}"


def _conv(cell: dict) -> str:
    if cell.get("trans_err_conv_m") is None:
        return "–"
    return f"{cell['trans_err_conv_m']:.3f} m / {cell['orient_err_conv_deg']:.2f}°"


def _from_start(average: dict) -> str:
    first = average.get("from_start")
    if not first:
        return "–"
    return f"{first['trans_err_m']:.2f} m / {first['orient_err_deg']:.1f}° / {100 * first['room_acc']:.1f} %"


def _trajectory_table(report: dict, variant: str) -> list[str]:
    lines = [
        "| Route | Trans. (m) | Orient. (°) | Room acc. (%) | Converged | After convergence | 95 % coverage |",
        "|---|---|---|---|---|---|---|",
    ]

    def row(name: str, cell: dict) -> str:
        return (
            f"| {name} | {cell['trans_err_m']:.2f} ± {cell['trans_err_std_m']:.2f} "
            f"| {cell['orient_err_deg']:.1f} ± {cell['orient_err_std_deg']:.1f} "
            f"| {100 * cell['room_acc']:.1f} ± {100 * cell['room_acc_std']:.1f} "
            f"| {cell['converged_runs']} / {cell['runs']} | {_conv(cell)} | {100 * cell['ellipse_coverage']:.0f} % |"
        )

    per_trajectory = report[variant]["per_trajectory"]
    for key in sorted(per_trajectory, key=int):
        lines.append(row(str(int(key) + 1), per_trajectory[key]))
    lines.append(row("**Avg.**", report[variant]["average"]))
    return lines


def _notes(report: dict, variant: str) -> list[str]:
    """The lines `bimfactor bench paper` prints under a variant's table (`table_notes`), and its step time."""
    average = report[variant]["average"]
    notes = [*table_notes(report, variant)]
    if "icp_accepted_share" in average and average["icp_accepted_share"] is not None:
        notes.append(f"ICP fits accepted on {100 * average['icp_accepted_share']:.0f} % of the keyframes")
    notes.append(f"step time (median): {average['step_ms_median']:.0f} ms")
    return [f"- {note}" for note in notes]


def results_page(sources: list[Source], page: Path) -> str:
    lines = [
        "# Results",
        "",
        "<!-- Generated by tools/render_results.py from docs/results/*.json: do not edit by hand. -->",
        "",
        "Table I of `bimfactor bench paper` (the protocol: [evaluation.md](evaluation.md)) for every results file "
        "committed under [results/](results/). To add or refresh one, run the command given with it, then "
        "`.venv/bin/python tools/render_results.py`, which rewrites this page and the README's table.",
        "",
    ]
    if not sources:
        return "\n".join([*lines, "No results are committed yet.", ""])
    lines += [
        "## Summary",
        "",
        "Mean over every scored step of every run; [95 % bootstrap interval over the runs]; after convergence: the "
        "steps after each run's convergence step, pooled; from the first frame: the same runs scored from their "
        "first frame, the uniform cloud included.",
        "",
        "| Run | Variant | Trans. (m) | Orient. (°) | Room acc. (%) | After convergence | Converged | 95 % coverage "
        "| From the first frame |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for s in sources:
        for variant in s.variants:
            a = s.report[variant]["average"]
            lines.append(
                f"| [{s.label}]({_link(s, page)}) | {variant} "
                f"| {a['trans_err_m']:.2f} [{_interval(a, 'trans_err_ci95_m', 1, 2)}] "
                f"| {a['orient_err_deg']:.1f} [{_interval(a, 'orient_err_ci95_deg', 1, 1)}] "
                f"| {100 * a['room_acc']:.1f} [{_interval(a, 'room_acc_ci95', 100, 1)}] "
                f"| {_conv(a)} | {a['converged_runs']} / {a['runs']} | {100 * a['ellipse_coverage']:.0f} % "
                f"| {_from_start(a)} |"
            )
    for s in sources:
        protocol = s.report["protocol"]
        lines += [
            "",
            f"## {s.label}",
            "",
            f"[{s.path.name}]({_link(s, page)}), written {s.report.get('created_utc', '–')}: {_scored(s)} "
            f"({protocol['trajectories']} routes × {protocol['repeats']} repeats). Regenerate with:",
            "",
            "```bash",
            command(s),
            "```",
        ]
        for variant in s.variants:
            lines += ["", f"### {variant}", "", *_trajectory_table(s.report, variant), "", *_notes(s.report, variant)]
    return "\n".join(lines) + "\n"


def replace_block(text: str, block: str, begin: str = BEGIN, end: str = END) -> str:
    """`text` with what lies between the markers (the results', by default) replaced by `block`."""
    if text.count(begin) != 1 or text.count(end) != 1 or text.index(begin) > text.index(end):
        raise SystemExit(f"error: the file must hold {begin} and then {end}, once each")
    head, rest = text.split(begin)
    _, tail = rest.split(end)
    return f"{head}{begin}\n{block}\n{end}{tail}"


def write_or_check(wanted: dict[Path, str], check: bool, tool: str) -> int:
    """Write each file whose text differs from `wanted`; with `check`, write nothing and exit 1 when one does."""
    stale = [path for path, text in wanted.items() if not path.exists() or path.read_text() != text]
    if check:
        for path in stale:
            print(f"{path}: out of date (run {tool})", file=sys.stderr)
        return 1 if stale else 0
    for path in stale:
        path.write_text(wanted[path])
        print(f"wrote {path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--results", type=Path, default=ROOT / "docs/results", help="folder of results files")
    parser.add_argument("--readme", type=Path, default=ROOT / "README.md")
    parser.add_argument("--page", type=Path, default=ROOT / "docs/results.md")
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 when either file is out of date")
    args = parser.parse_args(argv)
    sources = load_sources(args.results)
    readme_text = args.readme.read_text()
    wanted = {
        args.readme: replace_block(readme_text, readme_block(sources, args.readme)),
        args.page: results_page(sources, args.page),
    }
    return write_or_check(wanted, args.check, "tools/render_results.py")


if __name__ == "__main__":
    sys.exit(main())
