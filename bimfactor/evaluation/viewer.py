"""A Rerun recording of a localization run (`--rerun FILE.rrd`) and the command that opens one (`bimfactor view`).

`RunRecorder` watches the localizer (`pipeline.StepObserver`) and logs each keyframe on the `keyframe` sequence
timeline under the entity paths of `ENTITIES`, in the BIM's world frame (metres, z up). The prior of the robot's
storey (its first ground-truth storey, else the first estimate's) is logged once, as static data; particles on
other storeys are not drawn. rerun-sdk is the optional `viz` extra: `require_rerun` says how to install it.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib import colormaps
from matplotlib.colors import to_rgb

from bimfactor.backend.factors import Landmarks
from bimfactor.errors import InputError
from bimfactor.evaluation.metrics import chi2_2dof_quantile
from bimfactor.evaluation.plots import FURNITURE_RGB, WALL_RGB, room_name
from bimfactor.io.atomic import atomic_path
from bimfactor.registration.icp import scan_in_world

if TYPE_CHECKING:
    from collections.abc import Iterator

    from bimfactor.bim.prior import BimPrior
    from bimfactor.pipeline import Keyframe, Localizer, LocalizerStep

VIZ_INSTALL = "pip install 'bimfactor[viz]'"
TIMELINE = "keyframe"
ENTITIES = (
    "world/bim/walls", "world/bim/doors", "world/bim/objects", "world/bim/rooms",
    "world/particles", "world/modes", "world/estimate", "world/truth", "world/scene_graph", "world/scan", "world/icp",
    "camera/image", "camera/detections", "camera/plates",
    "plots/error_m", "plots/ess", "plots/n_modes",
)  # fmt: skip
"""Where a recording keeps what; a run logs the ones it has data for (truth, ICP, text only when there are some)."""
ARROW_M = 0.8  # a pose is drawn as an arrow this long along its heading
MAX_ICP_POINTS = 5000  # the registered scan is thinned to at most this many points
ELLIPSE_P = 0.95
TRUTH_RGB, ESTIMATE_RGB, MODE_RGB = to_rgb("tab:green"), to_rgb("tab:red"), to_rgb("tab:orange")


def require_rerun() -> ModuleType:
    """The rerun module, or an InputError (exit 2) naming the extra to install."""
    try:
        import rerun
    except ImportError as exc:
        raise InputError(f"--rerun needs the rerun-sdk package (the viz extra): {VIZ_INSTALL}") from exc
    return rerun


def _rgb8(rgb: tuple[float, float, float]) -> list[int]:
    return [round(255 * c) for c in rgb]


def _xyz(xy: np.ndarray, z_m: float = 0.0) -> np.ndarray:
    """(N, 3) points at height `z_m` from (N, 2) plan positions."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    return np.column_stack([xy, np.full(len(xy), z_m)])


def _arrows(rr: ModuleType, poses: np.ndarray, rgb: tuple, labels: list[str] | None = None) -> Any:
    """(N, 3) x, y, yaw poses as arrows `ARROW_M` long."""
    poses = np.asarray(poses, np.float64).reshape(-1, 3)
    vectors = ARROW_M * np.column_stack([np.cos(poses[:, 2]), np.sin(poses[:, 2]), np.zeros(len(poses))])
    return rr.Arrows3D(origins=_xyz(poses[:, :2]), vectors=vectors, colors=_rgb8(rgb), labels=labels)


def ellipse_outline(pose: np.ndarray, covariance: np.ndarray, p: float = ELLIPSE_P, n: int = 48) -> np.ndarray:
    """(n + 1, 2) closed outline of the p-probability position ellipse of a (3, 3) pose covariance."""
    values, vectors = np.linalg.eigh(np.asarray(covariance, np.float64)[:2, :2])
    radii = np.sqrt(chi2_2dof_quantile(p) * np.clip(values, 0.0, None))
    t = np.linspace(0.0, 2 * np.pi, n + 1)
    return np.asarray(pose[:2]) + (np.column_stack([np.cos(t), np.sin(t)]) * radii) @ vectors.T


def log_prior(rec: Any, rr: ModuleType, prior: BimPrior, storey: int) -> None:
    """One storey of the prior, static: wall cells, doors (green: joins two places), objects and room names."""
    layers = prior.storeys[storey]
    walls = prior.grid.cell_to_world(np.argwhere(layers.structure))
    rec.log("world/bim/walls", rr.Points3D(_xyz(walls), colors=_rgb8(WALL_RGB), radii=0.04), static=True)
    doors = [d for d in prior.doors if d.storey_index == storey]
    ends = [np.asarray(d.center_xy) + s * np.asarray(d.axis_xy) * d.width_m / 2 for d in doors for s in (-1, 1)]
    strips = [_xyz(np.asarray(ends[2 * i : 2 * i + 2]), 0.02) for i in range(len(doors))]
    colours = [_rgb8(to_rgb("tab:green" if d.connects else "tab:red")) for d in doors]
    door_labels = [d.kind for d in doors]
    rec.log("world/bim/doors", rr.LineStrips3D(strips, colors=colours, labels=door_labels, radii=0.05), static=True)
    objects = [o for o in prior.objects if o.storey_index == storey and o.label != "door"]
    xy = _xyz(np.asarray([o.position_m[:2] for o in objects]))
    object_points = rr.Points3D(xy, colors=_rgb8(FURNITURE_RGB), labels=[o.label for o in objects])
    rec.log("world/bim/objects", object_points, static=True)
    rooms = [r for r in prior.rooms if r.storey_index == storey]
    centroids = _xyz(np.asarray([r.centroid_xy for r in rooms]))
    rec.log("world/bim/rooms", rr.Points3D(centroids, labels=[room_name(r) for r in rooms], radii=0.01), static=True)


@dataclass
class RunRecorder:
    """Writes what each step of a run shows to a Rerun recording (a `pipeline.StepObserver`); `record` opens it."""

    rec: Any
    rr: ModuleType
    prior: BimPrior
    storey: int | None = None
    keyframes: int = 0
    estimates: list[np.ndarray] = field(default_factory=list)
    truths: list[np.ndarray] = field(default_factory=list)
    landmarks: np.ndarray | None = None
    shown: set[str] = field(default_factory=set)  # the entities of `_log_or_clear` that show something now

    def on_step(self, localizer: Localizer, key: Keyframe, out: LocalizerStep) -> None:
        if self.storey is None:
            self.storey = out.storey if key.frame.gt_storey is None else int(key.frame.gt_storey)
            log_prior(self.rec, self.rr, self.prior, self.storey)
        self.rec.set_time(TIMELINE, sequence=self.keyframes)
        self.keyframes += 1
        self._belief(localizer, out)
        self._poses(key, out)
        self._seen(key, out)
        self._camera(key)

    def _belief(self, localizer: Localizer, out: LocalizerStep) -> None:
        """The particles on the recorded storey coloured by weight, the modes with their 95 % ellipses, ESS."""
        rr, on_storey = self.rr, localizer.filter.storeys == self.storey
        weights = localizer.filter.estimation_weights()[on_storey]
        shade = weights / max(float(weights.max(initial=0.0)), 1e-300)
        colours = (255 * colormaps["viridis"](shade)[:, :3]).astype(np.uint8)
        self.rec.log("world/particles", rr.Points3D(_xyz(localizer.filter.particles[on_storey, :2]), colors=colours))
        modes = out.graph.modes if out.graph is not None else []
        drawn = [m for m in modes if m.storey == self.storey]
        labels = [f"mode {m.mode_id}: p {m.probability:.2f}" for m in drawn]
        self.rec.log("world/modes", _arrows(rr, np.asarray([m.pose for m in drawn]), MODE_RGB, labels))
        ellipses = [_xyz(ellipse_outline(m.pose, m.covariance), 0.01) for m in drawn]
        self.rec.log("world/modes/ellipses", rr.LineStrips3D(ellipses, colors=_rgb8(MODE_RGB), labels=labels))
        self.rec.log("plots/ess", rr.Scalars(float(out.filtered.ess)))
        self.rec.log("plots/n_modes", rr.Scalars(float(len(modes))))

    def _poses(self, key: Keyframe, out: LocalizerStep) -> None:
        """The output pose and its trail; the truth, its trail and the error where the frame has ground truth."""
        rr = self.rr
        self.estimates.append(np.asarray(out.pose, np.float64))
        self.rec.log("world/estimate", _arrows(rr, out.pose, ESTIMATE_RGB, ["estimate"]))
        trail = _xyz(np.asarray(self.estimates)[:, :2], 0.01)
        self.rec.log("world/estimate/trail", rr.LineStrips3D([trail], colors=_rgb8(ESTIMATE_RGB)))
        if key.frame.gt_pose is None:
            return
        truth = np.asarray(key.frame.gt_pose, np.float64)
        self.truths.append(truth)
        self.rec.log("world/truth", _arrows(rr, truth, TRUTH_RGB, ["truth"]))
        trail = _xyz(np.asarray(self.truths)[:, :2], 0.01)
        self.rec.log("world/truth/trail", rr.LineStrips3D([trail], colors=_rgb8(TRUTH_RGB)))
        self.rec.log("plots/error_m", rr.Scalars(float(np.hypot(*(out.pose[:2] - truth[:2])))))

    def _seen(self, key: Keyframe, out: LocalizerStep) -> None:
        """The nodes in view (and text read) where the best mode puts them, lines to the BIM objects it matched
        them to; the scan endpoints at the output pose; the registered depth returns where ICP ran."""
        rr, seen = self.rr, out.observations
        best = out.graph.best if out.graph is not None else None
        pose = out.pose if best is None else best.pose
        ranges, bearings = seen.measurements()
        nodes = scan_in_world(np.column_stack([ranges * np.cos(bearings), ranges * np.sin(bearings)]), pose)
        labels = list(seen.labels) + (list(seen.texts.texts) if seen.texts is not None else [])
        self.rec.log("world/scene_graph", rr.Points3D(_xyz(nodes, 0.5), labels=labels, radii=0.12))
        if best is not None:
            if self.landmarks is None:
                self.landmarks = Landmarks.from_prior(self.prior).xy
            lines = [_xyz(np.stack([nodes[k], self.landmarks[j]]), 0.5) for k, j in best.matches]
            self.rec.log("world/scene_graph/matches", rr.LineStrips3D(lines, colors=_rgb8(MODE_RGB)))
        scan = None
        if key.scan is not None:
            scan = rr.Points3D(_xyz(scan_in_world(key.scan, out.pose), 0.05), radii=0.03)
        self._log_or_clear("world/scan", scan)
        icp = None
        if out.fine is not None and out.fine.registration is not None and key.points is not None:
            base = key.points.base[:: max(1, len(key.points.base) // MAX_ICP_POINTS)]
            registered = np.column_stack([scan_in_world(base, out.fine.pose), base[:, 2]])
            accepted = to_rgb("tab:blue" if out.fine.accepted else "tab:gray")
            icp = rr.Points3D(registered, colors=_rgb8(accepted), radii=0.02)
        self._log_or_clear("world/icp", icp)

    def _camera(self, key: Keyframe) -> None:
        """The colour image with the detections' boxes and labels, and the text read."""
        rr = self.rr
        self.rec.log("camera/image", rr.Image(key.frame.rgb).compress(jpeg_quality=80))
        boxes = np.asarray([d.box_xyxy for d in key.detections], np.float64).reshape(-1, 4)
        labels = [f"{d.label} {d.box_score:.2f}" for d in key.detections]
        self.rec.log("camera/detections", rr.Boxes2D(array=boxes, array_format=rr.Box2DFormat.XYXY, labels=labels))
        plates = None
        if key.readings:
            xyxy = np.asarray([r.box_xyxy for r in key.readings], np.float64).reshape(-1, 4)
            plates = rr.Boxes2D(array=xyxy, array_format=rr.Box2DFormat.XYXY, labels=[r.text for r in key.readings])
        self._log_or_clear("camera/plates", plates)

    def _log_or_clear(self, entity: str, data: Any | None) -> None:
        """Log what a keyframe has for an entity that not every keyframe has (None: nothing); at the first keyframe
        without after one with, clear it, so the viewer does not go on showing an older keyframe's."""
        if data is not None:
            self.rec.log(entity, data)
            self.shown.add(entity)
        elif entity in self.shown:
            self.rec.log(entity, self.rr.Clear(recursive=False))
            self.shown.discard(entity)


def blueprint(prior: BimPrior) -> Any:
    """The layout a recording opens in: the world seen from above the building at an angle, beside the camera image
    over one plot each of the error, the ESS and the number of modes."""
    import rerun.blueprint as rrb

    x0, x1, y0, y1 = (float(v) for v in prior.grid.extent)
    centre, span = ((x0 + x1) / 2, (y0 + y1) / 2, 0.0), max(x1 - x0, y1 - y0)
    eye = rrb.EyeControls3D(position=(centre[0], centre[1] - span, 1.2 * span), look_target=centre, eye_up=(0, 0, 1))
    world = rrb.Spatial3DView(origin="world", name="world", eye_controls=eye)
    plots = [rrb.TimeSeriesView(origin=f"plots/{name}", name=name) for name in ("error_m", "ess", "n_modes")]
    side = rrb.Vertical(rrb.Spatial2DView(origin="camera", name="camera"), *plots, row_shares=[3, 1, 1, 1])
    return rrb.Blueprint(rrb.Horizontal(world, side, column_shares=[3, 2]), collapse_panels=True)


@contextmanager
def record(path: str | Path, prior: BimPrior, name: str) -> Iterator[RunRecorder]:
    """A recorder writing the Rerun recording `path` (application "bimfactor", recording `name`); the file appears
    whole when the block ends, and not at all when it fails."""
    rr = require_rerun()
    with atomic_path(path) as tmp:
        rec = rr.RecordingStream("bimfactor")
        rec.save(tmp, default_blueprint=blueprint(prior))
        rec.send_recording_name(name)
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        try:
            yield RunRecorder(rec, rr, prior)
        finally:
            rec.flush()
            rec.disconnect()


def check_recording(path: str | Path | None, output: str | Path) -> None:
    """Before any work: an InputError unless `path` (None: no recording asked for) names a .rrd file outside the
    command's `output` folder, and rerun-sdk is installed."""
    if path is None:
        return
    if Path(path).suffix != ".rrd" or Path(path).is_dir():
        raise InputError(f"--rerun {path}: name a Rerun recording file, ending in .rrd")
    check_outside(path, output)
    require_rerun()


def check_outside(path: str | Path, output: str | Path) -> None:
    """An InputError when a recording's `path` lies inside the `output` folder: bimfactor writes that folder whole (or
    keeps only its own files there), so a recording inside would be lost or block the next run."""
    if Path(path).resolve().is_relative_to(Path(output).resolve()):
        raise InputError(f"--rerun {path} lies inside {output}, which bimfactor writes whole: put it beside it")


@contextmanager
def maybe_record(path: str | Path | None, prior: BimPrior, name: str) -> Iterator[RunRecorder | None]:
    """`record` when a path is given; otherwise no recorder."""
    if path is None:
        yield None
        return
    with record(path, prior, name) as recorder:
        yield recorder


def recordings_in(target: str | Path) -> list[Path]:
    """The .rrd files `bimfactor view` opens: the file given, or those in the folder given (and its subfolders)."""
    target = Path(target)
    if target.is_file() and target.suffix == ".rrd":
        return [target]
    found = sorted(target.rglob("*.rrd")) if target.is_dir() else []
    if not found:
        raise InputError(f"{target}: no Rerun recording (.rrd) there; write one with --rerun FILE.rrd")
    return found


def has_display() -> bool:
    """Whether a window can open here: macOS and Windows always, elsewhere an X11 or Wayland display."""
    return sys.platform in ("darwin", "win32") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def viewer_commands(files: list[Path]) -> tuple[list[str], list[str]]:
    """The commands that open recordings: the native viewer (needs a display) and the web viewer (`rerun
    --web-viewer`: it serves the viewer on http://localhost:9090 to a browser on this or another machine)."""
    names = [str(f) for f in files]
    return ["rerun", *names], ["rerun", "--web-viewer", *names]


def open_viewer(files: list[Path]) -> list[str]:
    """Start the native Rerun viewer on the recordings, detached from this process; the command it ran."""
    require_rerun()
    viewer = shutil.which("rerun")
    if viewer is None:
        raise InputError(f"the rerun viewer is not on PATH: {VIZ_INSTALL}")
    command = [viewer, *viewer_commands(files)[0][1:]]
    subprocess.Popen(command, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return command
