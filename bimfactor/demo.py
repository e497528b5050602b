"""The demo: named steps from a procedural building to its prior, a simulated sequence and its localization.

Each step reads what earlier steps left in the `DemoContext`, writes its files under the output folder and
returns one line that says what it did. Later stages (simulation, localization) are added as further steps.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from bimfactor.config import Config
from bimfactor.io.atomic import check_output_dir, container_dir, write_text_atomic

if TYPE_CHECKING:
    import numpy as np

    from bimfactor.active import Suggestion
    from bimfactor.bim.prior import BimPrior
    from bimfactor.bim.synth import BuildingSpec
    from bimfactor.types import Frame, SequenceMeta

DEMO_PRESET = "paper-floor"
# The suggestion's building and route: eight alike offices, where route 2 starts in one and the belief is split
# between them after a few keyframes; the route is driven until the localizer suggests where to look, at most this far.
SUGGEST_PRESET, SUGGEST_ROUTE, SUGGEST_MAX_KEYFRAMES = "office", 2, 20


@dataclass
class DemoContext:
    """What the steps share: the config, the output folder, where to write a Rerun recording of the localization
    (None: none), and each step's results."""

    cfg: Config
    out_dir: Path
    rerun_path: Path | None = None
    ifc_path: Path | None = None
    building: BuildingSpec | None = None
    prior_dir: Path | None = None
    prior: BimPrior | None = None
    sequence_dir: Path | None = None
    suggestion: Suggestion | None = None
    figures: list[Path] = field(default_factory=list)
    step_seconds: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class DemoStep:
    """One named step; `run` returns a one-line account of what it did."""

    name: str
    run: Callable[[DemoContext], str]


def _synth(ctx: DemoContext) -> str:
    from bimfactor.bim.synth import write_building

    ctx.ifc_path = ctx.out_dir / f"{DEMO_PRESET}.ifc"
    ctx.building = write_building(DEMO_PRESET, ctx.cfg.seed, ctx.ifc_path)
    counts = ctx.building.object_counts()
    n_rooms = sum(len(storey.rooms) for storey in ctx.building.storeys)
    return (
        f"wrote {ctx.ifc_path} (preset {DEMO_PRESET}, seed {ctx.cfg.seed}): {n_rooms} rooms, "
        f"{sum(counts.values())} objects in {len(counts)} categories"
    )


def _prior(ctx: DemoContext) -> str:
    from bimfactor.bim.prior import build_prior
    from bimfactor.evaluation.plots import save_floorplans

    assert ctx.ifc_path is not None, "the prior step needs the synth step's IFC"
    ctx.prior_dir = ctx.out_dir / "prior"
    ctx.prior = build_prior(ctx.ifc_path, ctx.cfg)
    ctx.prior.save(ctx.prior_dir, config_yaml=ctx.cfg.dump_yaml(), extra_files=save_floorplans)
    ctx.figures.extend(sorted(ctx.prior_dir.glob("floorplan_*.png")))
    summary = ctx.prior.summary()
    return (
        f"wrote {ctx.prior_dir}/: {summary['rooms']} rooms, {summary['doors_connecting']} connecting doors, "
        f"{summary['objects']} objects"
    )


def write_simulation(
    output: Path,
    prior: BimPrior,
    prior_dir: Path,
    cfg: Config,
    meta: SequenceMeta,
    frames: list[Frame],
    route: tuple[int, np.ndarray, np.ndarray],
    seed: int,
    overwrite: bool = True,
) -> tuple[int, Path]:
    """A simulated sequence folder as `bimfactor simulate` writes it, atomically: the sequence, detections.jsonl (the
    sim perception's detections of the frames as stored), config.yaml, preview.png and trajectory.png of the `route`
    (storey, (N, 2) dense xy, (K, 3) keyframe poses). Returns the number of rooms the route visits and the preview."""
    import numpy as np

    from bimfactor.embed.text import make_text_embedder
    from bimfactor.evaluation.plots import save_trajectory_plot
    from bimfactor.io.atomic import output_dir
    from bimfactor.io.preview import write_preview
    from bimfactor.io.sequence import read_sequence, write_sequence_files
    from bimfactor.perception.detections import DETECTIONS_FILE
    from bimfactor.perception.pipeline import write_sim_detections

    storey, dense_xy, keyframes = route
    rooms = {int(r) for r in prior.room_at(dense_xy, storey) if r >= 0}
    odom = np.asarray([f.odom_pose for f in frames])
    with output_dir(output, "sequence", inputs=[prior_dir], replace=overwrite) as folder:
        write_sequence_files(folder, meta, frames, label=str(output))
        # from the frames as stored (depth in millimetres), so they are what the sim backend sees in this folder
        stored = read_sequence(folder)
        write_sim_detections(folder / DETECTIONS_FILE, cfg, meta, stored, make_text_embedder(cfg.embed), seed)
        (folder / "config.yaml").write_text(cfg.dump_yaml())
        preview = write_preview(stored, folder / "preview.png")
        title = f"{meta.name}: {len(frames)} keyframes, {len(rooms)} room{'' if len(rooms) == 1 else 's'}"
        save_trajectory_plot(prior, storey, folder / "trajectory.png", dense_xy, keyframes, odom, title=title)
    return len(rooms), output / preview.name


def _simulate(ctx: DemoContext) -> str:
    from bimfactor.sim.simulate import load_world_inputs, simulate_sequence

    assert ctx.prior_dir is not None, "the simulate step needs the prior step's folder"
    prior, model = load_world_inputs(ctx.prior_dir, ctx.cfg)
    result = simulate_sequence(prior, model, ctx.cfg, trajectory_index=0, seed=ctx.cfg.seed)
    ctx.sequence_dir = ctx.out_dir / "sequence"
    drive = result.trajectory
    route = (drive.storey_index, drive.poses[:, :2], drive.keyframe_poses)
    _, preview = write_simulation(
        ctx.sequence_dir, prior, ctx.prior_dir, ctx.cfg, result.meta, result.frames, route, ctx.cfg.seed
    )
    ctx.figures += [preview, ctx.sequence_dir / "trajectory.png"]
    return f"wrote {ctx.sequence_dir}/: {len(result.frames)} RGB-D keyframes with odometry and ground truth"


# The online stages in the order they build on each other, and how the demo names what each adds.
STAGES = (
    ("smcl", "S-MCL (the paper's filter)"),
    ("smcl+graph", "+ per-mode GTSAM pose graphs"),
    ("full", "+ Open3D ICP"),
)


def _localize(ctx: DemoContext) -> str:
    """Localize the sequence with each stage up to the configured variant (all three by default), so the account
    shows what each stage adds; the configured variant's run is written. The filter runs the same in every variant (the
    back end never feeds back into it), so S-MCL's line is the `smcl+graph` run's filter track, not a run of its own."""
    from bimfactor.config import updated
    from bimfactor.evaluation.report import run_metrics, track_metrics, write_run
    from bimfactor.evaluation.viewer import maybe_record
    from bimfactor.io.sequence import read_sequence
    from bimfactor.pipeline import localize_sequence

    assert ctx.prior_dir is not None and ctx.sequence_dir is not None, "the localize step needs a prior and a sequence"
    # the prior as `bimfactor localize` reads it (saved arrays, not the builder's own), so the runs are the same
    from bimfactor.bim.prior import BimPrior

    prior = BimPrior.load(ctx.prior_dir)
    sequence = read_sequence(ctx.sequence_dir)
    n = len(sequence)
    names = [name for name, _ in STAGES]
    variant = ctx.cfg.localization.variant
    stages = STAGES[: names.index(variant) + 1] if variant in names else [(variant, variant)]
    lines, run = [], None
    for name, label in stages:
        if name == "smcl" and variant != "smcl":
            continue  # the filter is the same in every variant: its line comes from the next run's filter track
        cfg = ctx.cfg if name == variant else updated(ctx.cfg, {"localization.variant": name})
        snapshots = sorted({0, n // 4, n // 2, n - 1}) if name == variant else ()
        with maybe_record(ctx.rerun_path if name == variant else None, prior, sequence.meta.name) as recorder:
            run = localize_sequence(
                prior, sequence.meta, sequence, cfg, ctx.cfg.seed, snapshot_steps=snapshots, observer=recorder
            )
        if not lines and name != "smcl":  # the first run: its filter track is S-MCL's line
            filtered = track_metrics(run.filter, run.gt_poses, run.gt_rooms)
            assert filtered is not None
            lines.append(_stage_line(STAGES[0][1], filtered))
        m = run_metrics(run)
        assert m is not None
        extra = ""
        if run.fine is not None:
            extra = f"; ICP accepted on {int(run.fine.accepted.sum())} of {int(run.fine.ran.sum())} keyframes"
        lines.append(_stage_line(label, m, extra))
    run_dir = ctx.out_dir / "localize"
    assert run is not None
    ctx.figures.extend(
        write_run(
            run,
            prior,
            run_dir,
            ctx.cfg.dump_yaml(),
            title=sequence.meta.name,
            inputs=[ctx.prior_dir, ctx.sequence_dir],
        )
    )
    return f"wrote {run_dir}/ (variant {variant}):\n" + "\n".join(f"      {line}" for line in lines)


def _suggest(ctx: DemoContext) -> str:
    """Drive a short route on a building with alike rooms (`SUGGEST_PRESET`) until the belief, split between them,
    has a suggestion (`Localizer.suggest`), at most `SUGGEST_MAX_KEYFRAMES`; write suggestion.json and suggestion.png.
    Only the filter is run (the `smcl` variant): the suggestion reads the filter's belief alone."""
    import json

    from bimfactor.bim.prior import build_prior
    from bimfactor.bim.synth import write_building
    from bimfactor.config import updated
    from bimfactor.evaluation.plots import save_suggestion_figure
    from bimfactor.io.atomic import output_dir
    from bimfactor.pipeline import Localizer
    from bimfactor.sim.simulate import simulate_sequence, source_model

    ifc = ctx.out_dir / f"{SUGGEST_PRESET}.ifc"
    write_building(SUGGEST_PRESET, ctx.cfg.seed, ifc)
    cfg = updated(ctx.cfg, {"evaluation.trajectory_length": SUGGEST_MAX_KEYFRAMES, "localization.variant": "smcl"})
    prior = build_prior(ifc, cfg)
    sim = simulate_sequence(prior, source_model(prior, cfg), cfg, SUGGEST_ROUTE, ctx.cfg.seed, progress=False)
    localizer = Localizer(prior, sim.meta, cfg, ctx.cfg.seed)
    for n, frame in enumerate(sim.frames, start=1):  # noqa: B007 (n: the keyframes driven, after the loop)
        localizer.step(frame)
        suggestion = localizer.suggest()
        if suggestion.goal_odom is not None:
            break
    ctx.suggestion = suggestion
    run_dir = ctx.out_dir / "suggest"
    title = f"{ifc.name}, route {SUGGEST_ROUTE} after {n} keyframe{'' if n == 1 else 's'}"
    with output_dir(run_dir, "run", inputs=[ifc]) as folder:
        (folder / "suggestion.json").write_text(json.dumps(suggestion.to_dict(), indent=2))
        save_suggestion_figure(prior, suggestion, folder / "suggestion.png", title, truth=frame.gt_pose)
    ctx.figures.append(run_dir / "suggestion.png")
    return (
        f"wrote {run_dir}/ ({ifc.name}, its offices alike; route {SUGGEST_ROUTE}, {n} keyframes):\n"
        f"      {suggestion.describe()}"
    )


def _stage_line(label: str, m, extra: str = "") -> str:
    """One stage's account: its label and the paper's metrics (`TrajectoryMetrics`) of its output."""
    return (
        f"{label}: translation {m.trans_err_m:.2f} ± {m.trans_err_std_m:.2f} m, orientation "
        f"{m.orient_err_deg:.1f} ± {m.orient_err_std_deg:.1f}°, room accuracy {100 * m.room_acc:.0f} %{extra}"
    )


STEPS: tuple[DemoStep, ...] = (
    DemoStep("synth", _synth),
    DemoStep("prior", _prior),
    DemoStep("simulate", _simulate),
    DemoStep("localize", _localize),
    DemoStep("suggest", _suggest),
)


def run_demo(
    cfg: Config,
    out_dir: str | Path,
    on_step: Callable[[int, str, float, str], None] | None = None,
    rerun: str | Path | None = None,
) -> DemoContext:
    """Run every step in order; `on_step(index, name, seconds, message)` is called after each one. With `rerun`, the
    configured variant's localization is also written to that Rerun recording (`evaluation.viewer`).

    `out_dir` must be new, empty or an earlier demo's folder (`io.atomic.container_dir`); each step's output in it
    is written atomically, and only bimfactor's own outputs are replaced.
    """
    from bimfactor.bim.synth import check_synth_output

    ctx = DemoContext(cfg=cfg, out_dir=Path(out_dir), rerun_path=None if rerun is None else Path(rerun))
    check_output_dir(ctx.out_dir, "demo")
    for preset in (DEMO_PRESET, SUGGEST_PRESET):
        check_synth_output(ctx.out_dir / f"{preset}.ifc")
    for name, kind in (("prior", "prior"), ("sequence", "sequence"), ("localize", "run"), ("suggest", "run")):
        check_output_dir(ctx.out_dir / name, kind)
    with container_dir(ctx.out_dir, "demo"):
        write_text_atomic(ctx.out_dir / "config.yaml", cfg.dump_yaml())
        for index, step in enumerate(STEPS):
            started = time.perf_counter()
            message = step.run(ctx)
            ctx.step_seconds[step.name] = time.perf_counter() - started
            if on_step is not None:
                on_step(index, step.name, ctx.step_seconds[step.name], message)
    return ctx
