"""Why `-c paper` is not the paper's 0.60 m: its filter with our components added one at a time, on both seeds.

    .venv/bin/python tools/paper_ablation.py run        # 2 seeds x len(STEPS) `bench paper --variant smcl` runs,
                                                        #   then docs/results/paper-ablation.json (about 1 h here)
    .venv/bin/python tools/paper_ablation.py render     # docs/paper-reproduction.md from that file
    .venv/bin/python tools/paper_ablation.py render --check   # exit 1 when the page is out of date

Each step is `-c paper` plus the `--set`s of every step before it and its own, so the last step is the default
filter in the paper's world (no as-built changes); the runs are written under runs/paper-ablation/.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from subprocess import DEVNULL

sys.path.insert(0, str(Path(__file__).resolve().parent))
from render_results import write_or_check  # a sibling script

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "docs/results/paper-ablation.json"
PAGE = ROOT / "docs/paper-reproduction.md"
SEEDS = (0, 1)
STEPS: list[tuple[str, list[str]]] = [
    ("the paper's filter (`-c paper`)", []),
    ("+ KLD-sampling: as many particles as the belief needs, up to 5000", ["smcl.resampler.kind=kld"]),
    (
        "+ object footprints: in view when any of it is, expected at its nearest point",
        ["smcl.semantic.fov_extent=true", "smcl.semantic.footprint_match=true"],
    ),
    (
        "+ class probability (softmax) for φ_sem, summed over the observations",
        [
            "smcl.semantic.similarity=softmax",
            "smcl.semantic.threshold=0.1",
            "smcl.semantic.temperature=0.2",
            "smcl.semantic.count_exponent=0",
        ],
    ),
    ("+ the depth scan against the BIM's walls", ["smcl.scan.enabled=true", "smcl.motion.off_map_weight=0.1"]),
    (
        "+ recoveries: augmented MCL, relocalization, challenger",
        ["smcl.augmented.enabled=true", "smcl.relocalize.enabled=true", "smcl.challenger.enabled=true"],
    ),
    (
        "+ door plates read (plates hang in the world)",
        ["sim.door_plates.enabled=true", "perception.text.enabled=true", "smcl.text_reset.enabled=true"],
    ),
]
KEYS = ("trans_err_m", "orient_err_deg", "room_acc", "success_rate", "wrong_convergence_rate", "converged_runs")


def run() -> int:
    from tqdm import tqdm

    out: dict = {"benchmark": "paper-ablation", "steps": [], "seeds": list(SEEDS)}
    runs_dir = ROOT / "runs/paper-ablation"
    bar = tqdm(total=len(SEEDS) * len(STEPS), desc="bench paper", unit="run")
    rows: dict[int, list[dict]] = {seed: [] for seed in SEEDS}
    for seed in SEEDS:
        prior: Path | None = None  # the seed's building, built by the first step that runs
        sets: list[str] = []
        for k, (_, own) in enumerate(STEPS):
            sets += own
            target = runs_dir / f"seed{seed}-step{k}"
            command = [str(ROOT / ".venv/bin/bimfactor"), "bench", "paper", "-c", "paper", "--variant", "smcl"]
            command += ["-o", str(target), "--set", f"seed={seed}", *(a for s in sets for a in ("--set", s))]
            if not _ran(target, command):  # a run of this very command is kept (the tool resumes)
                subprocess.run([*command, *(["--prior", str(prior)] if prior else [])], check=True, stdout=DEVNULL)
                (target / "command.json").write_text(json.dumps(command))
                prior = prior or target / "prior"
            average = json.loads((target / "results.json").read_text())["smcl"]["average"]
            rows[seed].append({key: average[key] for key in KEYS})
            bar.update()
    out["steps"] = [{"name": name, "set": own} for name, own in STEPS]
    out["rows"] = {str(seed): rows[seed] for seed in SEEDS}
    RESULTS.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {RESULTS}")
    return 0


def _ran(target: Path, command: list[str]) -> bool:
    done = target / "command.json"
    return done.is_file() and (target / "results.json").is_file() and json.loads(done.read_text()) == command


def _cell(row: dict) -> str:
    return (
        f"{row['trans_err_m']:.2f} m, {row['orient_err_deg']:.1f}°, {100 * row['room_acc']:.0f} %; "
        f"{100 * row['success_rate']:.0f} % / {100 * row['wrong_convergence_rate']:.0f} %"
    )


def page(report: dict) -> str:
    lines = [
        "# Reproducing the paper",
        "",
        "The paper (CoarseBIMLoc, Table I) reports 0.60 m, 12° and 92.7 % room accuracy for its semantic MCL on its",
        "floor. `-c paper` is that filter as the text specifies it, every extension of ours off, and on our paper",
        "floor it does not come close. The table adds our components to it one at a time, each row keeping the rows",
        "above it (`bench paper --variant smcl`, 6 routes × 3 repeats, scored from the filter's converged flag). A",
        "cell: translation, orientation, room accuracy; then success / wrong convergence (the share of runs within",
        "1 m and 15° of the truth at the route's end / that said converged while more than 2 m off). Generated by",
        "`tools/paper_ablation.py`",
        "from [results/paper-ablation.json](results/paper-ablation.json); its `run` regenerates that file.",
        "",
        "| Step | `--set` added | " + " | ".join(f"seed {s}" for s in report["seeds"]) + " |",
        "|---|---|" + "---|" * len(report["seeds"]),
    ]
    for k, step in enumerate(report["steps"]):
        sets = "<br>".join(f"`{s}`" for s in step["set"]) or "–"
        cells = " | ".join(_cell(report["rows"][str(s)][k]) for s in report["seeds"])
        lines.append(f"| {step['name']} | {sets} | {cells} |")
    lines += ["", *_reading(report), "", *UNSPECIFIED]
    return "\n".join(lines) + "\n"


def _reading(report: dict) -> list[str]:
    """What the table says, from its numbers: each step's change of success and wrong convergence, both seeds
    pooled, the two largest first."""

    def pooled(k: int, key: str) -> float:
        return sum(report["rows"][str(s)][k][key] for s in report["seeds"]) / len(report["seeds"])

    gains = [(pooled(k, "success_rate") - pooled(k - 1, "success_rate"), k) for k in range(1, len(report["steps"]))]
    text = []
    for _, k in sorted(gains, reverse=True)[:2]:
        name = report["steps"][k]["name"].removeprefix("+ ")
        text.append(
            f"{name} (success {100 * pooled(k - 1, 'success_rate'):.0f} → {100 * pooled(k, 'success_rate'):.0f} %, "
            f"wrong convergence {100 * pooled(k - 1, 'wrong_convergence_rate'):.0f} → "
            f"{100 * pooled(k, 'wrong_convergence_rate'):.0f} %)"
        )
    last = len(report["steps"]) - 1
    return [
        "Both seeds pooled, the two largest steps are " + " and ".join(text) + ". With every component the filter",
        f"succeeds on {100 * pooled(last, 'success_rate'):.0f} % of the runs, against "
        f"{100 * pooled(0, 'success_rate'):.0f} % for the paper's filter alone. The mean translation error stays",
        "above the paper's: it averages every scored step of every run, from the step the filter first called itself",
        "converged, and a run that said so early, before the scan and the challenger had moved it off a look-alike",
        "room, weighs in with metres. The paper does not say over which steps and runs its 0.60 m averages.",
    ]


UNSPECIFIED = [
    "## What the paper's text leaves open",
    "",
    "`-c paper` has to choose these, and each choice moves the result:",
    "",
    "- **The detector and its errors.** The paper runs an open-vocabulary detector in Gazebo and gives no",
    "  precision, recall or label confusion. The sim perception's `paper` preset stands in for it",
    "  (bimfactor/configs/perception_sim.yaml); wrong and missed labels are what leave a filter of objects alone",
    "  in the wrong room of a floor whose rooms hold the same furniture.",
    "- **The temperature and the similarity threshold** of Eq. 4: named, no value given (`-c paper`: 0.01 and 0.08,",
    "  the cosine's own scale).",
    "- **The visibility sector's radius r** (`bim.visibility.radius_m`, 8 m) and **the keyframe spacing** of a step",
    "  (0.5 m or 15°): the motion noise σ_trans 0.2 m and σ_rot 10° is given per step, not per metre.",
    "- **When a run counts as converged** and from which step Table I scores: the text gives neither; the benchmark",
    "  scores the T = 50 steps from the filter's own converged flag (docs/evaluation.md).",
    "- **The routes.** Six trajectories of 50 steps with distinct starts; where they start and what they look at is",
    "  not given. Ours are planned between viewpoints that see objects (docs/simulator.md).",
    "- **The floor itself.** The paper's building is not published; `paper-floor` is our reading of its figures,",
    "  with repeated offices of the same furniture, the case an object-only filter cannot tell apart.",
]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("what", choices=("run", "render"))
    parser.add_argument("--check", action="store_true", help="render: write nothing; exit 1 when out of date")
    args = parser.parse_args(argv)
    if args.what == "run":
        return run()
    return write_or_check({PAGE: page(json.loads(RESULTS.read_text()))}, args.check, "tools/paper_ablation.py render")


if __name__ == "__main__":
    sys.exit(main())
