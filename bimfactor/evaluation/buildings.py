"""`bimfactor bench buildings`: the paper's protocol over many buildings at once, its runs on Ray or a process pool.

Each building's prior is built once (OUT/priors/<IFC stem>/), then every run of every building goes to one runner.
Per building (keyed by IFC file name) and variant the report keeps Table I's keys and the routes' outcomes
(`evaluation.metrics.route_outcome`: success, wrong convergence, distance to convergence, top-3). docs/buildings.md.
"""

from __future__ import annotations

import json
import logging
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from bimfactor.config import Config
from bimfactor.errors import InputError
from bimfactor.io.atomic import write_text_atomic

if TYPE_CHECKING:
    from bimfactor.bim.prior import BimPrior

log = logging.getLogger(__name__)

PAPER_FLOOR = "paper-floor"
"""The synthetic preset that stands for the paper's floor in the default set (written as OUT/paper-floor.ifc)."""


def default_buildings() -> list[str | Path]:
    """The paper floor and every IFC file of the shared data folder (when it is there)."""
    from bimfactor.evaluation.bench import find_shared_ifc_dir

    shared = find_shared_ifc_dir()
    return [PAPER_FLOOR, *(sorted(shared.glob("*.ifc")) if shared is not None else [])]


def building_names(buildings: list[str | Path]) -> list[str]:
    """The key of each building in results.json: its IFC file name ("paper-floor.ifc" for the preset), or, where two
    files share a name, as many of their folders before it as tell them apart ("a/model.ifc", "b/model.ifc")."""
    paths = [Path(f"{PAPER_FLOOR}.ifc") if str(b) == PAPER_FLOOR else Path(b).resolve() for b in buildings]
    names = []
    for path in paths:
        depth = 1
        while depth < len(path.parts) and any(
            other != path and other.parts[-depth:] == path.parts[-depth:] for other in paths
        ):
            depth += 1
        names.append("/".join(path.parts[-depth:]))
    return names


def build_priors(buildings: list[str | Path], cfg: Config, out_dir: Path) -> dict[str, Path]:
    """Each building's prior in OUT/priors/<name without .ifc>/ (`building_names`; the preset written to OUT first),
    by building name; a prior an
    earlier run left there is kept when it is this IFC's with the same prior settings (`reusable_prior`)."""
    from bimfactor.bim.prior import build_prior
    from bimfactor.bim.synth import write_building
    from bimfactor.progress import progress

    priors = {}
    names = dict(zip(map(str, buildings), building_names(buildings), strict=True))
    for building in progress(buildings, desc="priors", unit="building"):
        ifc = Path(building)
        if str(building) == PAPER_FLOOR:
            ifc = out_dir / f"{PAPER_FLOOR}.ifc"
            write_building(PAPER_FLOOR, cfg.seed, ifc)
        prior_dir = out_dir / "priors" / Path(names[str(building)]).with_suffix("")
        if reusable_prior(prior_dir, ifc, cfg):
            log.info("%s: the prior in %s is kept (same IFC, same prior settings)", ifc.name, prior_dir)
        else:
            build_prior(ifc, cfg).save(prior_dir, config_yaml=cfg.dump_yaml())
        priors[names[str(building)]] = prior_dir
    return priors


def reusable_prior(prior_dir: Path, ifc: Path, cfg: Config) -> bool:
    """Whether `prior_dir` holds a prior of this very IFC file (SHA-256) in this bimfactor's format, built with the
    same prior settings (`bim`, `embed` and the seed of its saved config.yaml): an experiment on the filter or the
    simulator then reruns in minutes less, and any change that could change the prior rebuilds it."""
    from bimfactor.bim.ifc import file_sha256
    from bimfactor.bim.prior import PRIOR_VERSION
    from bimfactor.config import load_config
    from bimfactor.errors import BimfactorError

    meta_file, cfg_file = prior_dir / "prior.json", prior_dir / "config.yaml"
    if not (meta_file.is_file() and cfg_file.is_file()):
        return False
    try:
        meta = json.loads(meta_file.read_text())
        built = load_config(cfg_file)
    except (ValueError, BimfactorError):
        return False
    return (
        meta.get("version") == PRIOR_VERSION
        and meta.get("source_sha256") == file_sha256(ifc)
        and (built.bim, built.embed, built.seed) == (cfg.bim, cfg.embed, cfg.seed)
    )


def run_buildings_bench(
    buildings: list[str | Path],
    cfg: Config,
    out_dir: str | Path,
    runner: str = "ray",
    workers: int | None = None,
    address: str | None = None,
    rerun_dir: str | Path | None = None,
) -> dict:
    """The protocol on every building, its runs on one runner (`evaluation.paper.RUNNERS`); writes OUT/results.json,
    OUT/report.md, OUT/buildings.png and OUT/config.yaml, and returns the report. With `rerun_dir`, every forward
    pass is also a Rerun recording there (`evaluation.paper.run_recording_path`)."""
    from bimfactor.bim.prior import BimPrior
    from bimfactor.bim.symmetry import twin_motions
    from bimfactor.evaluation.paper import (
        check_protocol,
        paper_jobs,
        paper_report,
        reported_variants,
        run_jobs,
        runner_description,
    )

    check_protocol(cfg)
    out = Path(out_dir)
    priors = build_priors(buildings, cfg, out)
    loaded = {name: BimPrior.load(prior_dir) for name, prior_dir in priors.items()}
    if cfg.evaluation.scenario == "storeys":
        priors = {name: path for name, path in priors.items() if changes_storey(loaded[name], cfg)}
        if not priors:
            raise InputError("--scenario storeys: no building has a lift or stair between two floors the robot drives")
    twins = {name: twin_motions(prior) for name, prior in loaded.items()}
    jobs, owners = [], []
    for name, prior_dir in priors.items():
        for job in paper_jobs(prior_dir, cfg, twins[name], rerun_dir):
            jobs.append(job)
            owners.append(name)
    desc = f"bench buildings ({len(priors)} buildings, {', '.join(cfg.evaluation.variants)})"
    where: dict = {}
    results = run_jobs(jobs, desc, runner, workers, address, where, names=owners)
    report: dict = {
        "benchmark": "buildings",
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "runner": {
            "name": runner,
            "address": address,
            "own_instance": runner == "ray" and address is None,
            "runs_on": runner_description(runner, address, workers),
            **where,
        },
        "variants": reported_variants(cfg.evaluation),
        "buildings": {},
    }
    for name in priors:
        runs = [r for runs, owner in zip(results, owners, strict=True) if owner == name for r in runs]
        block = paper_report(priors[name], loaded[name], cfg, twins[name], runs)
        block["route_success"] = {
            variant: {
                f"{r.trajectory}/{r.repeat}": bool(r.outcome.success)
                for r in runs
                if r.variant == variant and r.outcome is not None
            }
            for variant in reported_variants(cfg.evaluation)
        }
        report["buildings"][name] = block
    report["worst"] = worst_building(report)
    write_text_atomic(out / "config.yaml", cfg.dump_yaml())
    write_text_atomic(out / "results.json", json.dumps(report, indent=2))
    write_text_atomic(out / "report.md", format_buildings_report(report))
    save_buildings_figure(report, out / "buildings.png")
    return report


def changes_storey(prior: BimPrior, cfg: Config) -> bool:
    """Whether the robot can drive from one floor of the building to another (`TrajectorySimulator.portal_ways`);
    the storeys scenario leaves a building out, and says so, where not."""
    from bimfactor.sim.trajectory import TrajectorySimulator

    if prior.portals and TrajectorySimulator(prior, cfg).portal_ways():
        return True
    kinds = f"its portals ({len(prior.portals)}) join no two floors it drives on" if prior.portals else "no portal"
    log.warning("%s: left out of the storeys scenario: %s", Path(prior.source_file).name, kinds)
    return False


def worst_building(report: dict) -> dict | None:
    """The building and route with the largest mean translation error of the last variant (the one the others build
    up to), over its scored steps."""
    variant = report["variants"][-1]
    worst = None
    for name, block in report["buildings"].items():
        for trajectory, cells in block[variant]["per_trajectory"].items():
            if worst is None or cells["trans_err_m"] > worst["trans_err_m"]:
                worst = {"building": name, "route": int(trajectory), "variant": variant, **_cells(cells)}
    return worst


def _cells(cells: dict) -> dict:
    return {k: cells.get(k) for k in ("trans_err_m", "orient_err_deg", "room_acc", "success_rate")}


ROW_KEYS = (
    ("trans_err_m", "translation [m]", "{:.2f}"),
    ("orient_err_deg", "orientation [°]", "{:.1f}"),
    ("room_acc", "room", "{:.0%}"),
    ("storey_acc", "storey", "{:.0%}"),
    ("storey_acc_after_change", "storey after change", "{:.0%}"),
    ("success_rate", "success", "{:.0%}"),
    ("wrong_convergence_rate", "wrong conv.", "{:.0%}"),
    ("distance_to_convergence_m", "dist. to conv. [m]", "{:.1f}"),
    ("keyframes_to_convergence", "keyframes to conv.", "{:.0f}"),
    ("top3_rate", "top 3", "{:.0%}"),
)


def _fmt(value: float | None, pattern: str) -> str:
    return "–" if value is None or (isinstance(value, float) and not np.isfinite(value)) else pattern.format(value)


def runs_on(runner: dict | str) -> str:
    """Where a report's runs went, in words (a report before the runner record held only a name)."""
    if isinstance(runner, str):
        return runner
    nodes = f", {runner['nodes']} node(s) with {runner['cpus']} CPUs in all" if "nodes" in runner else ""
    return f"{runner['runs_on']}{nodes}"


def format_buildings_report(report: dict) -> str:
    """report.md: one table per building (a row per variant), then the worst building and route."""
    lines = [
        "# bench buildings",
        "",
        f"Runs on {runs_on(report['runner'])}, created {report['created_utc']}. Scored as `bench paper` scores "
        "(Table I's cells over the scored steps); success, wrong convergence, distance to correct convergence and "
        "top 3 over each whole route from its first frame.",
    ]
    header = "| variant | " + " | ".join(title for _, title, _ in ROW_KEYS) + " | runs |"
    rule = "|---" * (len(ROW_KEYS) + 2) + "|"
    for name, block in report["buildings"].items():
        storeys = block["storeys"]
        lines += ["", f"## {name} ({storeys} storey{'' if storeys == 1 else 's'})", "", header, rule]
        for variant in report["variants"]:
            avg = block[variant]["average"]
            cells = [_fmt(avg.get(key), pattern) for key, _, pattern in ROW_KEYS]
            lines.append(f"| {variant} | " + " | ".join(cells) + f" | {avg['runs']} |")
    worst = report.get("worst")
    if worst is not None:
        lines += [
            "",
            f"Worst: {worst['building']}, route {worst['route']} ({worst['variant']}): "
            f"{_fmt(worst['trans_err_m'], '{:.2f}')} m, {_fmt(worst['orient_err_deg'], '{:.1f}')}°, "
            f"room {_fmt(worst['room_acc'], '{:.0%}')}, success {_fmt(worst['success_rate'], '{:.0%}')}.",
        ]
    return "\n".join(lines) + "\n"


def save_buildings_figure(report: dict, path: Path) -> Path:
    """Per building, each variant's success rate and mean translation error, side by side."""
    import matplotlib.pyplot as plt

    from bimfactor.evaluation.plots import save_figure

    names = list(report["buildings"])
    variants = report["variants"]
    fig, (ax_s, ax_t) = plt.subplots(1, 2, figsize=(12, 0.6 * len(names) + 2.0))
    height = 0.8 / max(len(variants), 1)
    y = np.arange(len(names))
    for i, variant in enumerate(variants):
        avg = [report["buildings"][n][variant]["average"] for n in names]
        ax_s.barh(y + i * height, [a.get("success_rate") or 0.0 for a in avg], height, label=variant)
        ax_t.barh(y + i * height, [a["trans_err_m"] for a in avg], height, label=variant)
    for ax, title in ((ax_s, "success rate at the route's end"), (ax_t, "mean translation error [m]")):
        ax.set_yticks(y + 0.4 - height / 2, names)
        ax.set_title(title)
        ax.invert_yaxis()
    ax_t.set_xscale("symlog", linthresh=0.1)
    ax_s.set_xlim(0, 1)
    ax_s.legend(loc="lower right", fontsize=8)
    return save_figure(fig, path)
