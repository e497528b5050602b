"""The configuration tree: validated pydantic models, one sub-model per stage.

Each field carries its default (the paper's hyperparameters plus the recommended extensions; the `default` preset),
what it means, its bounds and, in a comment, why it has that value; values no preset or user needs to change are
fixed values of their stage (`ClassVar`). Units are SI (metres, seconds, radians) unless the key names another
(`..._deg`, `..._px`). Presets are YAML files that override part of the default: the named ones (`PRESETS`: `paper`,
`fast`) ship in bimfactor/configs/, and any other file can be given by path; `--set a.b=value` on the command line
overrides single fields.
"""

from __future__ import annotations

import copy
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal, TypeVar

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, FiniteFloat, ValidationError, model_validator
from pydantic.fields import FieldInfo

from bimfactor.errors import ConfigError
from bimfactor.resources import check_particle_memory
from bimfactor.textfile import read_utf8

CONFIG_DIR = Path(__file__).resolve().parent / "configs"
"""The package's config folder: the named presets and the data tables (package data in a wheel)."""
PRESETS = ("paper", "default", "fast")
"""The named presets: the paper's filter alone (CONFIG_DIR/paper.yaml), the recommended pipeline (the fields'
defaults themselves) and the fewest milliseconds per keyframe (CONFIG_DIR/fast.yaml)."""


class _Strict(BaseModel):
    """The base of every config model: unknown keys are errors, never silently dropped, and no float anywhere (also
    inside lists and tuples) may be inf or nan: a `.inf` passes `ge=0`, and a field without bounds takes `.nan`."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class IfcReadConfig(_Strict):
    # Threads for ifcopenshell's geometry iterator.
    geometry_threads: ClassVar[int] = 2
    cache_dir: str = Field(
        "~/.cache/bimfactor/geometry",
        description="Folder for the per-file geometry cache (keyed by the IFC's SHA-256); '' disables it.",
    )


class GridConfig(_Strict):
    resolution_m: float = Field(0.05, gt=0.0, le=1.0, description="Occupancy grid cell size.")
    # obstacles are what the geometry holds between these heights above the storey; from where the scan starts
    # (sensor.min_z_m): a window's sill below it filled the recess to the pane
    band_min_m: float = Field(0.15, description="Lower edge of the obstacle band, above the storey elevation.")
    # the paper's modeled height (Sec. III.A)
    band_max_m: float = Field(1.2, description="Upper edge of the obstacle band (robot sensing height).")
    # Clearpath Jackal: 0.508 x 0.430 m footprint
    robot_radius_m: float = Field(0.25, ge=0.0, description="Robot footprint radius; free space is eroded by it.")
    # Margin added around the building's footprint.
    padding_m: ClassVar[float] = 1.0
    # IFC classes never rasterised as obstacles (open doors, slabs, spaces, annotations).
    obstacle_exclude_classes: ClassVar[tuple[str, ...]] = (
        "IfcDoor",
        "IfcSlab",
        "IfcCovering",
        "IfcRoof",
        "IfcSpace",
        "IfcOpeningElement",
        "IfcAnnotation",
        "IfcSite",
        "IfcVirtualElement",
        "IfcFooting",
        "IfcSpatialZone",
    )


class RoomsConfig(_Strict):
    source: Literal["floodfill", "ifcspace", "auto"] = Field(
        "auto",
        description="Where rooms come from: the paper's flood fill, the model's IfcSpace, or IfcSpace when present.",
    )
    # Free-space components smaller than this are no room.
    min_room_area_m2: ClassVar[float] = 1.0
    # How far a door's footprint is grown when it is closed for the flood fill.
    door_seal_margin_m: ClassVar[float] = 0.1
    # How far beyond the wall a door looks for its rooms.
    door_probe_m: ClassVar[float] = 0.4
    # Rooms touching along at least this much free boundary are joined as open plan. IfcSpace rooms that touch along a
    # wall-less edge this long are open-plan neighbours
    min_opening_m: ClassVar[float] = 0.6
    # Lower edge of the band above door height where a wall with no wall below it marks a doorway. a leafless doorway:
    # wall above door height with none below it
    lintel_band_min_m: ClassVar[float] = 2.15
    # Upper edge of that lintel band, above the storey elevation.
    lintel_band_max_m: ClassVar[float] = 2.4
    # IFC classes whose geometry in the lintel band can mark a doorway. walls above an opening, downstand beams over a
    # passage
    lintel_classes: ClassVar[tuple[str, ...]] = ("IfcWall", "IfcBeam")
    # IoU at which a flood-fill room matches an IfcSpace.
    iou_match_threshold: ClassVar[float] = 0.5


class ObjectsConfig(_Strict):
    classes: list[str] = Field(
        [
            "IfcFurnishingElement",
            "IfcSanitaryTerminal",
            "IfcFireSuppressionTerminal",
            "IfcFlowTerminal",
            "IfcWindow",
            "IfcDoor",
            "IfcStair",
            "IfcTransportElement",
        ],
        description="IFC classes (and their subclasses) that become object nodes.",
    )
    # Objects closer than this are joined by an edge.
    proximity_edge_m: ClassVar[float] = 2.0
    # Label table, relative to bimfactor/configs/.
    vocabulary_file: ClassVar[str] = "vocabulary.yaml"
    # Minimum cosine similarity for the nearest-embedding label fallback.
    embedding_fallback_min_sim: ClassVar[float] = 0.45


class ClassifyConfig(_Strict):
    # Room-category pool, relative to bimfactor/configs/.
    room_categories_file: ClassVar[str] = "room_categories.yaml"
    min_objects: int = Field(1, ge=0, description="Rooms with fewer labelled objects are typed 'unknown'.")
    # A room with no labelled objects but doors to at least this many places is a hallway; 0: off. topology: an
    # object-less room joining three or more places is a corridor
    hallway_min_doors: ClassVar[int] = 3
    # Object labels left out of a room's sentence because every room has them (door, window). in every kind of room,
    # or circulation
    ignore_labels: ClassVar[tuple[str, ...]] = ("door", "window", "stairs", "elevator", "escalator")


class VisibilityConfig(_Strict):
    """The prior's table of the objects in line of sight from each lattice cell (`bim.visibility`)."""

    # Lattice of the precomputed visible-object table.
    cell_m: ClassVar[float] = 0.25
    radius_m: float = Field(8.0, gt=0.0, description="The visibility sector's radius r (not given in the paper).")


class BimConfig(_Strict):
    ifc: IfcReadConfig = Field(default_factory=IfcReadConfig)
    grid: GridConfig = Field(default_factory=GridConfig)
    rooms: RoomsConfig = Field(default_factory=RoomsConfig)
    objects: ObjectsConfig = Field(default_factory=ObjectsConfig)
    classify: ClassifyConfig = Field(default_factory=ClassifyConfig)
    # the prior's table of objects in line of sight from each lattice cell
    visibility: VisibilityConfig = Field(default_factory=VisibilityConfig)


class EmbedConfig(_Strict):
    # minilm | clip (CLIP's text tower: the vlm backend needs it)
    text_model: Literal["minilm", "clip"] = Field(
        "minilm", description="Text embedder: the bundled all-MiniLM-L6-v2, or CLIP's text tower (needs weights)."
    )
    clip_model: str = Field("ViT-L-14", description="open_clip architecture name, e.g. ViT-L-14.")
    # one CLIP checkpoint for both towers: the prior's text, the vlm backend's crops
    clip_weights: str = Field(
        "",
        description="Local path of the CLIP checkpoint, read for both towers: the BIM text (prior) and the vlm "
        "backend's crops; '' when not available.",
    )


class SimPerceptionErrors(_Strict):
    """One named error preset of the simulated perception backend (bimfactor/configs/perception_sim.yaml)."""

    detector: Literal["open_vocabulary", "yolox"] = Field(
        description="The detector it emulates. open_vocabulary: the paper's YOLO-World + SAM + CLIP, every class the "
        "BIM holds, with masks and crop embeddings (the mask_* and embedding_* keys); yolox: the shipped YOLOX-Nano, "
        "only the classes it reports under the vocabulary, boxes segmented by depth and embedded by their label."
    )
    range_half_m: float = Field(gt=0.0, description="Distance at which the detection quality falls to one half.")
    range_width_m: float = Field(gt=0.0, description="Width of that logistic fall-off with distance.")
    visible_half: float = Field(ge=0.0, le=1.0, description="Visible fraction at which the quality halves.")
    visible_width: float = Field(gt=0.0, description="Width of the logistic fall-off with occlusion.")
    area_half_px: float = Field(gt=0.0, description="Visible pixel area at which the quality halves.")
    area_width_log: float = Field(gt=0.0, description="Width of the fall-off with log(area).")
    box_score_max: float = Field(gt=0.0, le=1.0, description="Box score of an unoccluded, near, large object.")
    box_score_std: float = Field(ge=0.0, description="Gaussian noise on the box score.")
    text_score_mean: float = Field(ge=0.0, le=1.0, description="Mean text (region-label) score.")
    text_score_std: float = Field(ge=0.0, description="Gaussian noise on the text score.")
    miss_prob: float = Field(ge=0.0, le=1.0, description="Misses that no geometry explains (appearance).")
    box_jitter: float = Field(ge=0.0, description="Box corner noise as a share of the box side.")
    confusion_rate: float = Field(ge=0.0, le=1.0, description="Share of detections given another label.")
    confusion_temperature: float = Field(gt=0.0, description="τ: confused label drawn ∝ exp(cos(true, other) / τ).")
    false_positive_candidates: float = Field(ge=0.0, description="Mean false-positive boxes per frame before scoring.")
    false_positive_score_max: float = Field(gt=0.0, le=1.0, description="False-positive box scores ~ U(0, this).")
    false_positive_side_px: list[float] = Field(
        min_length=2, max_length=2, description="Side range of a false-positive box (log-uniform)."
    )
    mask_dilate_prob: float | None = Field(
        default=None, ge=0.0, le=1.0, description="Share of masks grown into the background ..."
    )
    mask_erode_prob: float | None = Field(
        default=None, ge=0.0, le=1.0, description="... or shrunk, each by 1..mask_radius_px pixels."
    )
    mask_radius_px: int | None = Field(default=None, ge=0, description="Largest dilation / erosion radius.")
    mask_bleed: float | None = Field(
        default=None, ge=0.0, le=1.0, description="Random background pixels of the box added, share of mask."
    )
    embedding_dprime: float | None = Field(
        default=None, gt=0.0, description="d' = Δμ/σ of matched vs unmatched crop-to-text cosines (CLIP ViT-L/14: ≈ 3)."
    )
    embedding_same_instance: float | None = Field(
        default=None, gt=0.0, lt=1.0, description="Crop-to-crop cosine, same object."
    )
    embedding_same_class: float | None = Field(
        default=None, gt=0.0, lt=1.0, description="Crop-to-crop cosine, same class, other object."
    )
    embedding_other_class: float | None = Field(
        default=None, gt=0.0, lt=1.0, description="Crop-to-crop cosine, other class."
    )

    @model_validator(mode="after")
    def _masks_and_embeddings_for_the_open_vocabulary_detector(self) -> SimPerceptionErrors:
        extra = [f for f in type(self).model_fields if f.startswith(("mask_", "embedding_"))]
        given = [f for f in extra if getattr(self, f) is not None]
        if self.detector == "open_vocabulary" and len(given) < len(extra):
            missing = ", ".join(f for f in extra if f not in given)
            raise ValueError(f"detector open_vocabulary needs its masks' and crop embeddings' keys: {missing}")
        if self.detector == "yolox" and given:
            raise ValueError(f"detector yolox has no masks or crop embeddings to model: drop {', '.join(given)}")
        return self


class VlmConfig(_Strict):
    """Local weight files of the vision-language backend. Its third file, CLIP's, is `embed.clip_weights` (+
    `embed.clip_model`): one checkpoint serves CLIP's image tower here and its text tower, which embeds the BIM when
    the prior is built, with or without this backend (docs/decisions.md)."""

    yolo_world_weights: str = Field(
        "", description="YOLO-World checkpoint, e.g. yolov8s-worldv2.pt (ultralytics/assets releases); '' when absent."
    )
    sam_model_type: Literal["vit_h", "vit_l", "vit_b"] = Field("vit_b", description="Segment Anything backbone.")
    sam_weights: str = Field(
        "", description="SAM checkpoint matching `sam_model_type`, e.g. sam_vit_b_01ec64.pth; '' when absent."
    )


class TextReadingConfig(_Strict):
    """Reading door plates (room numbers) in the colour image; beyond the paper, off by default."""

    enabled: bool = Field(
        True, description="Read text each frame (sim backend: the simulator's door plates; vlm backend: RapidOCR)."
    )
    # auto: the backend's (sim: the simulator's plates with the error model below; vlm, detections: RapidOCR) |
    # rapidocr
    reader: Literal["auto", "sim", "rapidocr"] = Field(
        "auto",
        description="auto: the backend's own (sim: the simulator's plates and error model; vlm, detections: RapidOCR); "
        "rapidocr: "
        "RapidOCR on the colour frames whatever the backend (on simulated frames it reads the printed plates).",
    )
    min_score: float = Field(0.5, ge=0.0, le=1.0, description="OCR: readings below this confidence are dropped.")
    # sim: a 15 cm plate is legible to ~2.4 m at 320 px over 90°
    sim_min_height_px: int = Field(10, ge=1, description="Sim: a plate fewer pixels high than this is not legible.")
    # the sim reader's errors, fitted to RapidOCR on rendered plates over the views the sim
    sim_read_probability: float = Field(
        0.92,
        ge=0.0,
        le=1.0,
        description="Sim: chance that a legible plate is read when its characters are wide in view.",
    )
    # calls legible (tools/calibrate_text_reader.py, docs/perception.md): the read chance by the plate's
    sim_read_char_px: float = Field(
        4.75,
        ge=0.0,
        description="Sim: the plate's width in the image per character of its text at which half that chance is left "
        "(distance and an oblique view both narrow the characters).",
    )
    # width per character in the image (320 x 240 and 640 x 480 pooled); then at 320 x 240
    sim_read_char_scale_px: float = Field(
        0.5,
        gt=0.0,
        description="Sim: how many pixels per character the read chance takes to rise (a logistic's scale).",
    )
    # a character is read as its look-alike ("8" for "B"), as any other, or not at all
    sim_look_alike_rate: float = Field(
        0.06, ge=0.0, le=1.0, description="Sim: chance that each character is read as one it looks like ('8' for 'B')."
    )
    # (640 x 480: 0.024, 0.04, 0.009)
    sim_char_error_rate: float = Field(
        0.07, ge=0.0, le=1.0, description="Sim: chance that each character is read as any other letter or digit."
    )
    sim_drop_rate: float = Field(
        0.03, ge=0.0, le=1.0, description="Sim: chance that each character is not read at all."
    )

    @model_validator(mode="after")
    def _rates_sum_to_at_most_one(self) -> TextReadingConfig:
        if self.sim_look_alike_rate + self.sim_char_error_rate + self.sim_drop_rate > 1.0:
            raise ValueError("sim_look_alike_rate + sim_char_error_rate + sim_drop_rate must not exceed 1")
        return self


class PerceptionConfig(_Strict):
    # auto: sim for a simulated sequence, else detections (SEQ_DIR/detections.jsonl), else yolox | sim | detections |
    # yolox | vlm
    backend: Literal["auto", "sim", "detections", "yolox", "vlm"] = Field(
        "auto",
        description="auto: from what the sequence holds (sim for a simulated one, else detections when it has a "
        "detections file, else yolox); sim: the simulator's instance buffer with an error model; detections: a "
        "detector's detections file (docs/perception.md); yolox: the shipped YOLOX-Nano (COCO classes); vlm: "
        "YOLO-World + SAM + CLIP (weights you provide).",
    )
    device: str = Field("cpu", description="torch device of the vlm backend ('cpu', 'cuda', 'cuda:1').")
    # yolox: the shipped detector's eyes | paper: the paper's open-vocabulary ones | clean | harsh
    # (configs/perception_sim.yaml)
    sim_preset: str = Field(
        "yolox",
        description="Error preset of the sim backend: a name in `sim_presets_file` (yolox: the shipped detector's "
        "eyes; paper: the paper's open-vocabulary ones).",
    )
    # Table of sim error presets, relative to bimfactor/configs/.
    sim_presets_file: ClassVar[str] = "perception_sim.yaml"
    # local weight files (docs/perception.md: where to get them); CLIP's is embed.clip_weights
    vlm: VlmConfig = Field(default_factory=VlmConfig)
    box_threshold: float = Field(0.25, ge=0.0, le=1.0, description="Detector box score threshold (paper: 0.25).")
    text_threshold: float = Field(0.25, ge=0.0, le=1.0, description="Detector text score threshold (paper: 0.25).")
    sim_threshold: float = Field(0.7, ge=-1.0, le=1.0, description="δ_sim, cosine similarity to fuse (paper: 0.7).")
    iou_threshold: float = Field(0.7, ge=0.0, le=1.0, description="δ_IoU, 3D overlap to fuse (paper: 0.7).")
    # Voxel of the instance point sets (downsampling and fusion).
    voxel_size_m: ClassVar[float] = 0.05
    # beyond ~6 m the depth noise (σ ≥ 6 cm) smears instances
    max_depth_m: float = Field(6.0, gt=0.0, description="Depth beyond this is not lifted.")
    max_points: int = Field(3000, ge=1, description="At most this many masked pixels are lifted per detection.")
    # DBSCAN neighbourhood radius (on voxel centres).
    dbscan_eps_m: ClassVar[float] = 0.12
    # DBSCAN core-point neighbour count.
    dbscan_min_points: ClassVar[int] = 4
    # Lifted instances with fewer voxels are dropped.
    min_instance_voxels: ClassVar[int] = 8
    # intersection over the smaller box: a partial view inside a fuller node still fuses
    overlap_measure: Literal["iou", "overlap"] = Field(
        "overlap", description="IoU_3 of the boxes, or their overlap coefficient (intersection / smaller volume)."
    )
    # Boxes are grown by this on every side before the 3D IoU. one voxel: a single-face view is a box, not a sheet
    iou_padding_m: ClassVar[float] = 0.05
    # A node voxel this far behind the observed depth counts as hidden in the current view.
    occlusion_tolerance_m: ClassVar[float] = 0.15
    # Prune the graph every this many frames.
    prune_every: ClassVar[int] = 5
    # Prune nodes with fewer voxels than this × the median node. nodes below a tenth of the median node size are
    # pruned
    prune_size_ratio: ClassVar[float] = 0.1
    # Prune nodes seen once and not for this many frames. nodes seen once and not in the last 10 frames are pruned
    prune_stale_frames: ClassVar[int] = 10
    # Nodes whose centroids are closer than this are joined. as bim.objects.proximity_edge_m
    edge_distance_m: ClassVar[float] = 2.0
    # beyond the paper: read door plates (room numbers; bim/plates.py) where the prior has them
    text: TextReadingConfig = Field(default_factory=TextReadingConfig)

    @model_validator(mode="after")
    def _text_reader_fits_the_backend(self) -> PerceptionConfig:
        if self.backend == "vlm" and self.text.reader == "sim":
            raise ValueError("text.reader 'sim' reads the simulator's plates: with backend vlm use auto or rapidocr")
        return self


class DepthSigmaConfig(_Strict):
    sigma0_m: float = Field(0.0012, ge=0.0, description="Axial depth noise σ(z) = sigma0 + k·(z − z0)², constant term.")
    k_per_m: float = Field(0.0019, ge=0.0, description="Quadratic growth k of the axial noise.")
    z0_m: float = Field(0.4, ge=0.0, description="Depth of least noise z0.")

    def sigma_m(self, depth_m: np.ndarray) -> np.ndarray:
        """Axial depth noise σ(z) = sigma0 + k·(z − z0)², same shape as `depth_m`."""
        return self.sigma0_m + self.k_per_m * (np.asarray(depth_m) - self.z0_m) ** 2


class SensorConfig(_Strict):
    """The RGB-D camera's depth: the simulator renders with this noise, and the estimator models it and uses the same
    band of depth."""

    # axial σ(z) = 0.0012 + 0.0019·(z − 0.4)² m, a RealSense-like camera
    depth_noise: DepthSigmaConfig = Field(
        default_factory=DepthSigmaConfig, description="Axial depth noise σ(z) of the camera."
    )
    # depth below this height is floor (scan and ICP); up to bim.grid.band_min_m
    min_z_m: float = Field(
        0.15,
        description="Depth points below this height above the floor are floor, not obstacles (scan and ICP alike).",
    )
    # beyond ~6 m the depth noise exceeds 6 cm
    max_range_m: float = Field(6.0, gt=0.0, description="Depth returns beyond this horizontal range are not used.")


class ScanConfig(_Strict):
    """The depth frame's horizontal 2-D scan (`localization.measurements.scan.scan_endpoints`), for the filter's
    scan term and the pose graphs' scan factor."""

    beam_deg: float = Field(2.0, gt=0.0, description="One endpoint (the nearest surface) per bearing bin this wide.")
    # A bin's returns within surface_sigmas σ(r) of its nearest one (r), at least surface_min_m and at most this, are
    # its surface; the endpoint is their median. its median return, not the nearest (biased short by ~3σ of the depth
    # noise) ...
    surface_m: ClassVar[float] = 0.3
    # The nearest surface's least depth (see above). ... over the returns within 6σ(r) of the nearest, 2 cm … 0.3 m: a
    # wall's spread, not a
    surface_min_m: ClassVar[float] = 0.02
    # The nearest surface's depth in σ of the depth noise. low table's top seen from above (bench scanmatch on
    # duplex.ifc: p90 12 → 8 cm)
    surface_sigmas: ClassVar[float] = 6.0


class OdometryConfig(_Strict):
    """The robot's odometry noise: the simulator draws it, the pose graphs weigh by it."""

    # α1..α4 (Thrun, Table 5.6): yaw σ ≈ 4.6° per 0.5 m
    alpha: list[FiniteFloat] = Field(
        [0.05, 0.01, 0.05, 0.01],
        min_length=4,
        max_length=4,
        description="α1..α4 of the odometry motion model (Thrun et al., Table 5.6): rot←rot, rot←trans, "
        "trans←trans, trans←rot, as variance ratios.",
    )


class StartConfig(_Strict):
    # [x_m, y_m, yaw_deg]: a Gaussian about a pose guess (AMCL); null: uniform (paper)
    pose: Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)] | None = Field(
        None,
        description="x, y (m, the BIM's world frame), yaw (°) of a pose guess: M particles start from a Gaussian "
        "about it (AMCL's initial pose); null: uniform over all navigable space (global localization, the paper).",
    )
    storey: int = Field(0, ge=0, description="The storey index of `pose`.")
    # [storey, ...]: a start without a pose guess covers only these (the robot knows its floor)
    storeys: Annotated[list[Annotated[int, Field(ge=0)]], Field(min_length=1)] | None = Field(
        None,
        description="Without a pose guess: the storeys the uniform start covers (a robot that knows its floor, as "
        "an elevator tells it); null: every storey. A relocalization still spreads over the whole building.",
    )
    # AMCL's default initial covariance: 0.25 m² in x and y, (π/12)² in yaw
    sigma_xy_m: float = Field(0.5, gt=0.0, description="Standard deviation of the start about `pose` in x and y.")
    sigma_yaw_deg: float = Field(15.0, gt=0.0, description="Standard deviation of the start about `pose` in yaw.")


class MotionConfig(_Strict):
    sigma_trans_m: float = Field(0.2, ge=0.0, description="σ_trans, motion noise per step (paper: 0.2 m).")
    sigma_rot_deg: float = Field(10.0, ge=0.0, description="σ_rot, motion noise per step (paper: 10°).")
    # particles that leave navigable space keep this share of their weight
    off_map_weight: float = Field(
        0.1,
        ge=0.0,
        le=1.0,
        description="Weight factor for a particle outside navigable space after a prediction (1: none).",
    )
    # a particle at a portal's end goes through with this probability per step when no event says the robot did
    portal_share: ClassVar[float] = 0.05
    # ... and with this probability when its step crossed the portal's footprint (a stair's steps): it climbed
    portal_cross_share: ClassVar[float] = 0.5
    # told the robot changed storey, a particle at no portal to that floor keeps this share of its weight
    event_miss_weight: ClassVar[float] = 1e-3


class ResamplerConfig(_Strict):
    # kld: KLD-sampling (Fox 2003, AMCL), M … max_particles as the belief needs | systematic (paper)
    kind: Literal["systematic", "kld"] = Field(
        "kld",
        description="systematic: low-variance resampling of M particles (the paper); kld: KLD-sampling (Fox 2003, "
        "as in AMCL), start with `max_particles` and resample as many as the occupied pose bins need, M at least.",
    )
    # the initial spread: 1000 leave places of 86 x 86 m unsampled (docs/filter.md)
    max_particles: int = Field(5000, ge=1, description="kld: the initial and largest particle count.")
    epsilon: float = Field(0.05, gt=0.0, lt=1.0, description="kld: bound ε on the KL divergence.")
    # kld: z_(1−δ), the standard normal quantile (2.33: δ = 0.01). δ = 0.01
    z: ClassVar[float] = 2.33
    # kld: bin size in x and y. AMCL's bins
    bin_m: ClassVar[float] = 0.5
    # kld: bin size in yaw.
    bin_deg: ClassVar[float] = 10.0


class SemanticTermConfig(_Strict):
    """The paper's measurement model (Sec. II.C, Eqs. 1-4)."""

    # the visibility sector (paper); its radius r is bim.visibility.radius_m
    fov_deg: float = Field(90.0, gt=0.0, le=360.0, description="The visibility sector's field of view (paper: 90°).")
    # in view when any of the object's footprint is; its expected bearing clipped to the FOV
    fov_extent: bool = Field(
        True, description="An object is in view when any of its footprint is (false: its centre, the literal reading)."
    )
    # a node is expected at the nearest point of its object's footprint, not its centre
    footprint_match: bool = Field(
        True,
        description="A node is expected at the point of its object's footprint nearest to it, the seen part's "
        "centroid lying anywhere on a large object (false: at the object's centre, the literal reading).",
    )
    sigma_d_m: float = Field(1.2, gt=0.0, description="σ_d, distance similarity scale (paper: 1.2).")
    kappa_alpha: float = Field(5.0, ge=0.0, description="κ_α, bearing similarity concentration (paper: 5).")
    # softmax: p(label | embedding) over the prior's labels | cosine: the paper's φ_sem
    similarity: Literal["cosine", "softmax"] = Field(
        "softmax", description="φ_sem: the paper's cosine, or the softmax class probability over the prior's labels."
    )
    # τ of the softmax φ_sem (CLIP: 0.01). CLIP's logit scale 100
    softmax_temperature: ClassVar[float] = 0.01
    # φ_sem below this scores 0 (cosine: 0.08, between matched 0.116 and unmatched 0.039)
    threshold: float = Field(
        0.1, ge=0.0, le=1.0, description="Pairs whose φ_sem is below this score 0 (depends on `similarity`)."
    )
    # not in the paper; with the sum 0.15-0.2 best (docs/filter.md); with the paper's mean 0.1
    temperature: float = Field(
        0.2, gt=0.0, description="T in P(z|x) = exp(K^(1−γ) · score / T); the paper gives no value."
    )
    # γ: Σφ over K observations divided by K^γ (1: the paper's mean; 0: the sum)
    count_exponent: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        description="γ: the matched φ summed over K observations is divided by K^γ (1: the paper's mean; 0: the sum).",
    )


class ScanTermConfig(_Strict):
    enabled: bool = Field(
        True,
        description="Also weigh particles by the depth scan against the BIM's likelihood field (beyond the paper).",
    )
    sigma_m: float = Field(0.2, gt=0.0, description="σ of an endpoint's distance to the nearest obstacle.")
    # 0.1 too sharp (wrong rooms of the same shape win), 0.3 best (docs/filter.md)
    temperature: float = Field(0.3, gt=0.0, description="T_scan in P(z_scan|x) = exp(score / T_scan).")


class TextTermConfig(_Strict):
    """Door-plate readings (`perception.text`), beyond the paper."""

    # Each edit (substitution, insertion, deletion) between a reading and a plate's text divides its match by
    # exp(this): one wrong character matches a plate by e^-6 (the sim reader's rates: ln(0.84 / (0.07 / 35))).
    edit_cost: ClassVar[float] = 6.0
    # What a substitution of look-alike characters ('8' for 'B') costs instead (OCR's common misreads;
    # bim.plates.LOOK_ALIKE_GROUPS): e^-3.5, ln(0.84 / (0.06 / 2)).
    look_alike_cost: ClassVar[float] = 3.5
    # ε in P(reading | x) = ε + (1 − ε) · best plate match; the chance that a reading is a misread or a plate the BIM
    # does not know, which bounds what one reading can say. P(reading | x) = ε + (1 − ε)·match: a reading moves the
    # weights by at most 1/ε
    unexplained: ClassVar[float] = 0.02


class AugmentedConfig(_Strict):
    enabled: bool = Field(
        True, description="Augmented MCL random-particle injection (Thrun, Table 8.3), beyond the paper."
    )
    injection: Literal["uniform", "observations"] = Field(
        "observations",
        description="Where the random particles come from: free space, or poses that explain one of the step's "
        "observations (sensor resetting).",
    )
    # Long-term likelihood average rate. Thrun's 0.001 / 0.1 suit high-rate filters; these suit one update per
    # keyframe
    alpha_slow: ClassVar[float] = 0.05
    # Short-term likelihood average rate. 0.3 injected on every bad perception step (docs/filter.md)
    alpha_fast: ClassVar[float] = 0.1


class TextResetConfig(_Strict):
    enabled: bool = Field(
        True,
        description="Redraw particles in front of the plates a door-plate reading names when the belief does not "
        "explain it (sensor resetting), beyond the paper.",
    )
    # The share of the particles redrawn. this share of the particles ...
    share: ClassVar[float] = 0.2
    # A reading is unexplained when the belief's P(reading | x) − ε averages below this share of its most (a particle
    # right before the plate its text matches best). ... when its P − ε averages below this share of its most ...
    below: ClassVar[float] = 0.1
    # Draw this many times as many and keep those the frame's scan favours (1: no screen). ... from 4× as many drawn,
    # those the frame's scan favours (1: no screen)
    oversample: ClassVar[int] = 4


class RelocalizeConfig(_Strict):
    enabled: bool = Field(
        True,
        description="Beyond the paper: when the belief stops explaining the depth scans (a kidnapped robot), spread "
        "the particles over the whole building again, as at the start.",
    )
    # Lost: a sudden drop, the belief's scan fit below this share of its average ... lost: the belief's predicted scan
    # fit under half its running average ...
    fit_ratio: ClassVar[float] = 0.5
    # ... on this many consecutive frames with a scan; or ... ... on 2 frames in a row, or ...
    frames: ClassVar[int] = 2
    # ... a held drop: Page's CUSUM of ln(average fit / fit), less this drift a frame, ... ... the CUSUM of ln(average
    # / fit), less 0.4 a frame, ...
    cusum_drift: ClassVar[float] = 0.4
    # ... exceeds this ... ... above 1.0 (bench paper --scenario kidnap and guess) ...
    cusum_threshold: ClassVar[float] = 1.0
    # ... once the running average has reached this fit (a belief that was tracking). ... once the average reached
    # 0.35 (a belief that tracked; the uniform cloud fits ~0.1)
    min_fit: ClassVar[float] = 0.35
    # Rate of the scan fit's running average. over 1 / 0.1 = 10 frames at least
    fit_alpha: ClassVar[float] = 0.1
    # Frames with fewer scan endpoints say nothing about being lost.
    min_endpoints: ClassVar[int] = 10


class ChallengerConfig(_Strict):
    # the current observations (the look-alike room)
    enabled: bool = Field(
        True,
        description="Beyond the paper: while the belief is converged, a second small filter drawn from the current "
        "observations runs beside it; when it predicts the following frames better by `threshold_nats` (Page's "
        "CUSUM of the log predictive-likelihood ratio) at a place the belief is not, the belief takes its particles.",
    )
    # 250-1000 recover alike
    particles: int = Field(500, ge=1, description="The challenger's particles.")
    # Drawn from this many times as many poses, those the frame's scan favours (1: no screen). drawn from 4× as many
    # poses, those the frame's scan favours
    oversample: ClassVar[int] = 4
    # The CUSUM of ln p(z | challenger) − ln p(z | belief) that hands the belief over. Page's CUSUM of ln p(z |
    # challenger) - ln p(z | belief) that hands over (10 handed a right belief over)
    threshold_nats: ClassVar[float] = 20.0
    # A challenger whose estimate lies within this of the belief's agrees ... within this of the belief's estimate it
    # agrees ...
    agree_m: ClassVar[float] = 1.5
    # ... and is drawn again after agreeing this many frames in a row ... ... and is drawn again after agreeing 3
    # frames in a row ...
    agree_frames: ClassVar[int] = 3
    # ... or after this many frames without winning. ... or after 15 frames without winning
    max_frames: ClassVar[int] = 15


class ConvergedConfig(_Strict):
    pos_std_m: float = Field(0.5, gt=0.0, description="Converged when the position std is below this ...")
    yaw_std_deg: float = Field(15.0, gt=0.0, description="... and the yaw std below this ...")
    storey_share: float = Field(
        0.9, gt=0.0, le=1.0, description="... and the estimated storey holds at least this share of the weight."
    )


class SmclConfig(_Strict):
    """The semantic particle filter (paper Sec. II.C) and its components, one sub-config each."""

    num_particles: int = Field(1000, ge=1, description="M (paper: 1000); with the kld resampler the fewest particles.")
    ess_threshold: float = Field(0.5, gt=0.0, le=1.0, description="δ_ess, resample when ESS < δ_ess·M (paper: 0.5).")
    # the initial belief
    start: StartConfig = Field(default_factory=StartConfig)
    # the prediction step (paper: σ_trans 0.2 m, σ_rot 10° per keyframe)
    motion: MotionConfig = Field(default_factory=MotionConfig)
    resampler: ResamplerConfig = Field(default_factory=ResamplerConfig)
    # the paper's measurement model, Eqs. 1-4
    semantic: SemanticTermConfig = Field(default_factory=SemanticTermConfig)
    # beyond the paper: the depth scan against the BIM's likelihood field (clearance layer)
    scan: ScanTermConfig = Field(default_factory=ScanTermConfig)
    text: ClassVar[TextTermConfig] = TextTermConfig()
    # augmented MCL (Thrun, Table 8.3), beyond the paper
    augmented: AugmentedConfig = Field(default_factory=AugmentedConfig)
    # a reading the belief does not explain redraws particles before the plates it names
    text_reset: TextResetConfig = Field(default_factory=TextResetConfig)
    # beyond the paper: re-spread over the building when the belief stops explaining the scans
    relocalize: RelocalizeConfig = Field(default_factory=RelocalizeConfig)
    # beyond the paper: a converged belief must keep out-predicting a small filter drawn from
    challenger: ChallengerConfig = Field(default_factory=ChallengerConfig)
    # the estimate is reported converged when
    converged: ConvergedConfig = Field(default_factory=ConvergedConfig)

    @model_validator(mode="after")
    def _particle_bounds(self) -> SmclConfig:
        if self.resampler.kind == "kld" and self.resampler.max_particles < self.num_particles:
            raise ValueError(
                f"resampler.max_particles {self.resampler.max_particles} is below num_particles {self.num_particles}"
            )
        return self


class CameraSimConfig(_Strict):
    width: int = Field(320, ge=8, description="Image width in pixels.")
    height: int = Field(240, ge=8, description="Image height in pixels.")
    # the paper's FOV
    hfov_deg: float = Field(90.0, gt=0.0, lt=180.0, description="Horizontal field of view.")
    min_range_m: float = Field(0.3, ge=0.0, description="Depth below this is no return.")
    max_range_m: float = Field(8.0, gt=0.0, description="Depth beyond this is no return.")
    mount_height_m: float = Field(0.5, description="Camera centre above the floor.")
    mount_forward_m: float = Field(0.15, description="Camera centre ahead of the base origin.")
    mount_pitch_deg: float = Field(0.0, description="Camera pitch; positive looks down.")


class DepthDropoutConfig(_Strict):
    grazing_dropout_deg: float = Field(80.0, gt=0.0, le=90.0, description="Incidence angle beyond which returns drop.")
    dropout_prob: float = Field(0.005, ge=0.0, le=1.0, description="Random per-pixel dropout probability.")


class RobotConfig(_Strict):
    # Linear speed limit (Jackal: 2.0).
    max_speed_mps: ClassVar[float] = 0.8
    # Angular speed limit.
    max_turn_rate_deg_s: ClassVar[float] = 90.0
    # Controller / odometry integration step.
    control_dt_s: ClassVar[float] = 0.05


class TrajectorySimConfig(_Strict):
    # Start and goal at least this far apart.
    min_start_goal_m: ClassVar[float] = 8.0
    # Obstacle inflation for path planning.
    inflation_m: ClassVar[float] = 0.35
    # a robot relocalizing looks at things: start and goals with objects in view
    route: Literal["viewpoints", "rooms"] = Field(
        "viewpoints",
        description="viewpoints: start and goals where objects are in view, facing them on arrival; "
        "rooms: any roomy place of another room.",
    )
    # A viewpoint sees objects (not doors) within this distance.
    view_radius_m: ClassVar[float] = 4.0
    # A viewpoint sees at least this many objects.
    min_view_objects: ClassVar[int] = 2


class AsBuiltConfig(_Strict):
    # benchmarks' as-built setting); every door stands open, which the IFC draws closed
    moved_fraction: float = Field(0.1, ge=0.0, le=1.0, description="Share of BIM objects moved in the simulated world.")
    # Largest displacement of a moved object.
    moved_max_m: ClassVar[float] = 1.0
    removed_fraction: float = Field(0.1, ge=0.0, le=1.0, description="Share of BIM objects missing in the world.")
    clutter_count: int = Field(5, ge=0, description="Objects in the world that the BIM does not contain.")


class DoorPlateSimConfig(_Strict):
    """Door plates in the simulated world (`bim.plates`): a room number beside each door into a numbered room."""

    enabled: bool = Field(True, description="Hang the plates (off: the world is the IFC model's elements alone).")
    # Plate width and height.
    size_m: ClassVar[tuple[float, float]] = (0.3, 0.15)
    # Plate centre above the storey's floor.
    height_m: ClassVar[float] = 1.4
    # Gap between the door opening and the plate's near edge.
    beside_m: ClassVar[float] = 0.15


class SimConfig(_Strict):
    # a RealSense-like RGB-D camera on a Clearpath Jackal
    camera: CameraSimConfig = Field(default_factory=CameraSimConfig)
    # the depth noise itself is sensor.depth_noise
    depth_dropout: DepthDropoutConfig = Field(default_factory=DepthDropoutConfig)
    rgb_noise_std: float = Field(3.0, ge=0.0, description="Gaussian RGB noise, in 8-bit levels.")
    robot: ClassVar[RobotConfig] = RobotConfig()
    # keyframes at localization.keyframe_distance_m / keyframe_angle_deg
    trajectory: TrajectorySimConfig = Field(default_factory=TrajectorySimConfig)
    # the world is not the BIM: a tenth of the objects moved, a tenth gone, some clutter (the
    as_built: AsBuiltConfig = Field(default_factory=AsBuiltConfig)
    # room numbers beside the doors into numbered rooms (bim/plates.py), as buildings have them
    door_plates: DoorPlateSimConfig = Field(default_factory=DoorPlateSimConfig)


class RosbagConfig(_Strict):
    rgb_topic: str = Field("", description="sensor_msgs/Image colour topic; '' finds it by message type and encoding.")
    depth_topic: str = Field("", description="sensor_msgs/Image depth topic (16UC1 mm or 32FC1 m); '' finds it.")
    camera_info_topic: str = Field("", description="sensor_msgs/CameraInfo of the colour camera; '' finds it.")
    depth_camera_info_topic: str = Field(
        "", description="CameraInfo of the depth camera, read only when depth is not registered to colour; '' finds it."
    )
    odom_topic: str = Field(
        "", description="nav_msgs/Odometry topic; '' finds it, or without one reads odom_frame → base_frame from /tf."
    )
    # the camera mount is the tf chain base_frame → the colour image's frame_id
    base_frame: str = Field(
        "base_link",
        min_length=1,
        description="The robot's base frame in tf (on the floor): the mount and odometry refer to it.",
    )
    odom_frame: str = Field(
        "odom", min_length=1, description="tf odometry frame, read when the bag has no Odometry topic."
    )
    # a detector's vision_msgs/Detection2DArray; "": found by type when there is one
    detections_topic: str = Field(
        "", description="vision_msgs/Detection2DArray topic of a detector's output (docs/perception.md); '' finds it."
    )
    # std_msgs/Int32 storey-change events (a barometer's, an IMU's or a lift's); "": the bag has none
    storey_topic: str = Field(
        "",
        description="std_msgs/Int32 topic of storey changes: floors up (+) or down (−), each at the next frame "
        "(frames.csv's extra.storey_change); '' reads none.",
    )
    max_sync_dt_s: float = Field(
        0.05, gt=0.0, description="Largest time offset between a colour image and its depth image."
    )
    max_odom_gap_s: float = Field(
        0.5, gt=0.0, description="Longest gap between odometry samples that a colour frame is interpolated across."
    )


class IoConfig(_Strict):
    # topics "" are found by message type (bimfactor convert rosbag prints what it used)
    rosbag: RosbagConfig = Field(default_factory=RosbagConfig)
    # Largest time offset when pairing TUM RGB-D rgb, depth and ground truth. the TUM benchmark's associate.py default
    tum_max_sync_dt_s: ClassVar[float] = 0.02


class RegistrationConfig(_Strict):
    """Fine registration of depth scans against the BIM's structural surfaces (bimfactor.registration)."""

    # Surface sample points per square metre of mesh. one point per 10 x 10 cm
    surface_density_per_m2: ClassVar[float] = 100.0
    # Voxel size of the downsampled scan (the default scale).
    scan_voxel_m: ClassVar[float] = 0.1
    # Scan points above this height above the floor are dropped (ceiling). drop the ceiling: walls only (from
    # sensor.min_z_m)
    scan_max_z_m: ClassVar[float] = 2.2
    submap_keyframes: int = Field(1, ge=1, description="Keyframes stitched into the local submap (1: the scan alone).")
    # Registrars thin the scan to at most this many points (strided). evenly strided; fitness and information use the
    # whole scan
    max_scan_points: ClassVar[int] = 1000
    # Open3D coarse to fine + planar polish: 63/63/46 % success on 3 buildings (planar 42/52/40 %)
    method: Literal["point_to_plane", "planar", "point_to_point", "robust", "gicp", "small_gicp", "kiss_icp"] = Field(
        "point_to_plane",
        description="The fine registrar (bimfactor.registration.icp.REGISTRARS); small_gicp and kiss_icp need "
        "pip install 'bimfactor[registrars]'.",
    )
    max_correspondence_m: float = Field(
        0.6, gt=0.0, description="Largest point-to-surface distance of a correspondence."
    )
    final_correspondence_m: float = Field(
        0.15, gt=0.0, description="The planar registrar shrinks the distance to this."
    )
    max_iterations: int = Field(30, ge=1, description="ICP iterations per scale.")
    # point_to_plane's coarse-to-fine scan voxel schedule. then the planar polish at final_correspondence_m (a third
    # Open3D scale added nothing)
    multiscale_voxels_m: ClassVar[tuple[float, ...]] = (0.4, 0.2)
    # Max correspondence distance per scale (same length as the voxel schedule).
    multiscale_correspondence_m: ClassVar[tuple[float, ...]] = (1.0, 0.5)
    robust_kernel: Literal["tukey", "huber"] = Field("tukey", description="Robust loss of the 'robust' registrar.")
    # Scale of the robust loss.
    robust_k_m: ClassVar[float] = 0.3
    # σ of a point-to-plane residual; information = JᵀJ / σ².
    noise_sigma_m: ClassVar[float] = 0.02
    # The surface is cropped to the scan's reach plus this margin.
    crop_margin_m: ClassVar[float] = 1.0
    # furniture and clutter may hold up to 10 % of the scan
    min_fitness: float = Field(
        0.9, ge=0.0, le=1.0, description="Gate: least share of scan points with a correspondence."
    )
    # depth σ at 6 m is 6 cm; correct fits measured up to 0.056 m
    max_rmse_m: float = Field(0.06, gt=0.0, description="Gate: largest inlier RMSE.")
    max_correction_m: float = Field(1.0, gt=0.0, description="Gate: largest translation away from the initial pose.")
    max_correction_deg: float = Field(15.0, gt=0.0, description="Gate: largest rotation away from the initial pose.")
    # Gate: least λmin/λmax of the translational information (corridor check). a corridor or a single wall: ≈ 0
    min_degeneracy_ratio: ClassVar[float] = 0.08
    # Gate, given the coarse pose's covariance: largest χ² of the correction under it. χ² with 3 DoF at 99 %
    consistency_chi2: ClassVar[float] = 11.34
    # wrong fits in symmetric places: another probe finds a better or equal fit
    ambiguity_probes: bool = Field(
        True, description="Gate: re-register from probe starts around the result; reject if another fit is as good."
    )
    # Probe starts this far along both translational axes ...
    ambiguity_probe_m: ClassVar[float] = 0.6
    # ... and this far in yaw, each way.
    ambiguity_probe_deg: ClassVar[float] = 10.0
    # A probe's fit is another place beyond this ...
    ambiguity_separation_m: ClassVar[float] = 0.1
    # ... or beyond this rotation from the result.
    ambiguity_separation_deg: ClassVar[float] = 1.0
    # Another place is as good when its fitness is at most this much lower ...
    ambiguity_fitness_margin: ClassVar[float] = 0.02
    # ... and its inlier RMSE at most this times the result's.
    ambiguity_rmse_ratio: ClassVar[float] = 1.25
    # Probes register this many scan points (evenly strided). same decisions as the full scan on the 3 comparison
    # buildings; probes 15-40 % faster
    ambiguity_probe_points: ClassVar[int] = 300
    # Fine factor: σ floor added to x and y (ICP overconfident). accepted fits on simulated keyframes: 9 mm RMS error
    # (JᵀJ/σ² says 1 mm)
    factor_min_sigma_m: ClassVar[float] = 0.01
    # Fine factor: σ floor added to yaw. ... and 0.1° RMS (JᵀJ/σ² says 0.02°)
    factor_min_sigma_deg: ClassVar[float] = 0.2
    success_trans_m: float = Field(0.05, gt=0.0, description="Comparison: a registration succeeds below this error ...")
    success_rot_deg: float = Field(1.0, gt=0.0, description="... and below this rotation error.")
    compare_keyframes: int = Field(10, ge=1, description="Comparison: keyframes per building.")
    compare_perturbations: int = Field(12, ge=1, description="Comparison: perturbed starts per keyframe.")
    compare_max_trans_m: float = Field(2.0, ge=0.0, description="Comparison: initial translation errors 0 .. this.")
    compare_max_rot_deg: float = Field(30.0, ge=0.0, description="Comparison: initial rotation errors 0 .. this.")


class ScanFactorConfig(_Strict):
    """The pose graphs' scan factor (`backend.scan_factor`): correlative matching of the keyframe's 2-D scan against
    the BIM's likelihood field about each mode's prediction, beyond the paper."""

    enabled: bool = Field(True, description="Each mode's graph also gets a pose factor from its keyframe's scan.")
    # Search ± this in x and y around the mode's prediction (its last pose moved by odometry: σ ≈ 0.11 m, 4° per
    # 0.5 m) ...
    window_m: ClassVar[float] = 0.5
    # ... and ± this in yaw.
    window_deg: ClassVar[float] = 18.0
    # Online graphs: a match beyond the window restarts the mode's graph there (docs/pose-graphs.md).
    recentre: int = Field(2, ge=0, description="An optimum on the window's edge: search again about it this often.")
    # The coarse search's step in x and y ...
    step_m: ClassVar[float] = 0.1
    step_deg: float = Field(2.0, gt=0.0, description="... and in yaw.")
    # The fine search's step in x and y ...
    fine_step_m: ClassVar[float] = 0.025
    # ... and in yaw (over one coarse cell around its best).
    fine_step_deg: ClassVar[float] = 0.5
    # σ of an endpoint's distance to the BIM's faces.
    sigma_m: ClassVar[float] = 0.1
    # The coarse search's σ (a smoother field, so its steps cannot miss a peak).
    coarse_sigma_m: ClassVar[float] = 0.2
    candidates: int = Field(2, ge=1, description="The best coarse poses the fine search refines.")
    # An endpoint whose ray is inside a wall this far before it scores as an outlier: its ray crossed the wall.
    clear_before_m: ClassVar[float] = 0.15
    # ε in log(f + ε), what an off-BIM endpoint costs.
    outlier: ClassVar[float] = 0.05
    # How many of the endpoints count as independent measurements: 95 % ellipsoids hold 96 % of the true poses
    # (bimfactor bench scanmatch).
    effective_endpoints: ClassVar[float] = 20.0
    # Scans with fewer endpoints are not matched, and a match needs this many endpoints on the BIM's faces. A sparse
    # scan counts each endpoint once (at most `effective_endpoints`), so a 6-endpoint scan is a weak but honest
    # factor: it holds the heading through blind stretches.
    min_endpoints: ClassVar[int] = 6
    min_inliers: ClassVar[int] = 6
    # Floor on the factor's position σ: the grid's walls sit a few cm off the rendered faces in places; refine adds
    # it to every marginal ...
    min_sigma_m: ClassVar[float] = 0.03
    # ... and on its yaw σ.
    min_sigma_deg: ClassVar[float] = 0.5


class BackendConfig(_Strict):
    """Multi-hypothesis back end: particle-filter modes, one GTSAM pose graph per mode."""

    max_modes: int = Field(5, ge=1, description="K, the strongest particle clusters kept as modes each step.")
    # Mean-shift window radius in x, y (also the seed grid cell).
    cluster_radius_m: ClassVar[float] = 1.0
    # Mean-shift window half-width in yaw (wrapped).
    cluster_yaw_deg: ClassVar[float] = 30.0
    # Clusters holding less particle weight are dropped.
    min_cluster_weight: ClassVar[float] = 0.02
    # An unmatched cluster at least this heavy spawns a mode.
    spawn_weight: ClassVar[float] = 0.05
    # A cluster continues a mode whose predicted pose is this close ...
    track_gate_m: ClassVar[float] = 1.0
    # ... and whose yaw differs by less than this.
    track_gate_yaw_deg: ClassVar[float] = 30.0
    # Two modes on one storey closer than this ...
    merge_distance_m: ClassVar[float] = 0.3
    # ... and within this yaw are merged into one.
    merge_yaw_deg: ClassVar[float] = 10.0
    # Modes whose probability falls below this are pruned.
    prune_probability: ClassVar[float] = 0.01
    # Particle weight kept by a mode no cluster continues.
    missed_decay: ClassVar[float] = 0.5
    # Floor on the position σ of a new mode's pose prior. a cluster's spread is cut off by the mean-shift window (±1
    # m, ±30°): floor it
    prior_min_sigma_m: ClassVar[float] = 0.3
    # Floor on the yaw σ of a new mode's pose prior.
    prior_min_sigma_deg: ClassVar[float] = 10.0
    odom_sigma_trans_m: float = Field(0.01, gt=0.0, description="Odometry factor: a floor on the translation σ ...")
    odom_sigma_rot_deg: float = Field(0.5, gt=0.0, description="... and on the yaw σ.")
    # M-estimator on the odometry factors: a wheel slip is an outlier of the motion model. σ is the model's at the
    # measured step: a turn the wheels measured short is 10σ off and
    odom_robust_kernel: ClassVar[Literal["huber", "cauchy", "none"]] = "cauchy"
    # Its width in σ units. more; heavy tails let the landmark and scan factors overrule it (docs/pose-graphs.md)
    odom_robust_k: ClassVar[float] = 2.385
    # sim perception at the true pose: range RMS 0.34 m (nodes sit 0.2 m short of BIM centres), p90 0.6 m
    range_sigma_m: float = Field(0.5, gt=0.0, description="σ of an observed object's range.")
    # ... bearing RMS 7°, p90 11°; bench paper: 95 % coverage 33 → 48 % at the same error
    bearing_sigma_deg: float = Field(10.0, gt=0.0, description="σ of an observed object's bearing.")
    # as-built objects deviate from the BIM; a perceived node is a partial view of its object
    landmark_sigma_m: float = Field(
        0.3, gt=0.0, description="σ tying a BIM landmark to its BIM position (as-built drift)."
    )
    # M-estimator on the landmark factors.
    robust_kernel: ClassVar[Literal["huber", "cauchy", "none"]] = "cauchy"
    # Kernel width in σ units (Huber 1.345, Cauchy 2.385: 95 % efficiency).
    robust_k: ClassVar[float] = 2.385
    # Cap on one observation's χ² in a mode's residual. χ²(2 dof) 99 %
    outlier_chi2: ClassVar[float] = 9.21
    # τ in p_k ∝ w_k · exp(−C_k / (2τ)).
    residual_temperature: ClassVar[float] = 1.0
    # Re-associate when the estimate moves this far ...
    reassociate_distance_m: ClassVar[float] = 0.25
    # ... or turns this much from the pose that associated.
    reassociate_yaw_deg: ClassVar[float] = 5.0
    # ISAM2 relinearization threshold.
    relinearize_threshold: ClassVar[float] = 0.01
    # ISAM2 considers relinearizing every this many updates (1: every keyframe; GTSAM's default 10). GTSAM's default;
    # 1 (every keyframe) took two to three times as long per back-end step, for the same accuracy
    relinearize_skip: ClassVar[int] = 10
    # Levenberg–Marquardt iterations of the offline batch refine.
    lm_max_iterations: ClassVar[int] = 100
    refine_rounds: int = Field(
        1, ge=0, description="Offline refine: rounds of re-association at the refined poses (0: the forward matches)."
    )
    # Offline refine: modes pruned in the forward pass after this many keyframes are refined too (tracked to the end
    # by odometry and scan matching) and compete by their fit to the whole sequence. a pruned mode that lived this
    # long is a refine candidate; the best fit wins
    refine_retired_min_keyframes: ClassVar[int] = 5
    # Offline refine of a relocalized run: the seam between two stretches is searched this many keyframes either side
    # of the lost monitor's change point, where the two stretches' refined trajectories explain the frames best (0:
    # the monitor's point). a relocalized run's seam, searched this far either side of the monitor's change point
    refine_seam_window: ClassVar[int] = 10
    # Offline refine: the searched seam replaces the monitor's only when the frames' log-likelihood is higher there by
    # this much (1: e ≈ 2.7 times as likely). ... and moved only when the frames are e ≈ 2.7 times as likely there
    refine_seam_min_log_ratio: ClassVar[float] = 1.0
    # Offline refine: two stretches of a relocalized run are refined as one where no mode born in them, refined over
    # both, gives way to another (as refine_split judges it): the relocalization was a false alarm. a relocalization
    # that no mode change bears out (as refine_split judges) is joined again
    refine_join: ClassVar[bool] = True
    # Offline refine: a stretch is parted again where one refined mode explains the keyframes before a step and
    # another, born after it, those from it on, by far better than any one mode explains all (a robot carried off
    # while the filter kept tracking, never relocalized). a stretch is parted again where two modes, one after the
    # other, explain it by far best
    refine_split: ClassVar[bool] = True
    # Offline refine: the two modes must explain the frames better than the stretch's best fit by this much log-
    # likelihood (10: e¹⁰ ≈ 22 000 times as likely) ... ... better than its best single mode by this much log-
    # likelihood
    refine_split_min_log_ratio: ClassVar[float] = 10.0
    # ... each explaining its own part better than the other by this much per keyframe on average ... ... each better
    # on its own part than the other by this per keyframe
    refine_split_min_keyframe_log_ratio: ClassVar[float] = 1.0
    # ... and each part must hold this many keyframes. ... each part this long
    refine_split_min_keyframes: ClassVar[int] = 5
    # beyond the paper: the keyframe's 2-D scan against the likelihood field, per mode
    scan_factor: ScanFactorConfig = Field(default_factory=ScanFactorConfig)


LocalizerVariant = Literal["smcl", "smcl+graph", "full"]
"""What localizes online: the paper's particle filter, the filter with one GTSAM pose graph per filter mode, or
that with ICP against the BIM walls fed back into the best mode's graph (full)."""
BenchVariant = Literal[LocalizerVariant, "refine"]
"""What a benchmark scores: an online localizer, or the offline refinement (smcl+graph, then batch smoothing)."""


class LocalizationConfig(_Strict):
    # every stage: smcl (the filter) → smcl+graph (its modes seed the pose graphs of backend:) → full (+ Open3D ICP)
    variant: LocalizerVariant = Field(
        "full",
        description="smcl: the paper's filter; smcl+graph: its modes each seed a pose graph (backend), a mode's "
        "graph pose is the output (`output`); full: smcl+graph with the fine stage (registration) "
        "registering each keyframe's scan from the best mode's pose and feeding accepted fits into its graph.",
    )
    # a step every 0.5 m or 15 deg: the motion noise (smcl.motion) is per step, so the
    keyframe_distance_m: float = Field(
        0.5,
        gt=0.0,
        description="A localizer step (keyframe) every this much travel ... (the motion noise is per step; the "
        "simulator records and `convert` keeps frames at this spacing)",
    )
    # simulator records and `convert` keeps frames at this spacing (T = 50 steps, as the paper)
    keyframe_angle_deg: float = Field(15.0, gt=0.0, description="... or this much rotation.")
    # graph variants: the mode at the particles' geometric median | best_mode: the most probable mode
    output: Literal["best_mode", "belief_median"] = Field(
        "belief_median",
        description="Graph variants' output: the most probable mode's pose, or the mode at the particles' "
        "geometric median (the position minimising the expected position error), the median itself when no mode "
        "is within `output_mode_radius_m` of it.",
    )
    # belief_median: a mode this near the median reports its graph pose.
    output_mode_radius_m: ClassVar[float] = 2.0
    # full: the best mode's covariance times this is what the fine stage's gate sees (consistency χ² and probes); the
    # graph's marginals are overconfident (95 % ellipses cover about half the errors). σ × 2: smcl+graph's 95 %
    # ellipses cover ~48 % of errors; 1.0 rejected correct fits
    fine_covariance_scale: ClassVar[float] = 4.0


class EvaluationConfig(_Strict):
    num_trajectories: int = Field(6, ge=1, description="Trajectories per building (paper: 6).")
    trajectory_length: int = Field(50, ge=1, description="T, steps per trajectory (paper: 50).")
    repeats: int = Field(3, ge=1, description="Runs per trajectory with different seeds (paper: 3).")
    variants: list[BenchVariant] = Field(
        ["smcl", "smcl+graph", "refine"], min_length=1, description="What `bench paper` scores, one table each."
    )
    # global: T steps from the filter's own converged flag (the only reading of Table I its statistics allow; the
    # first T steps are scored too, as from_start) | start: from the uniform cloud
    score_from: Literal["start", "filter_converged"] = Field(
        "filter_converged",
        description="global: where a run's T scored steps begin: at the first step whose filter estimate reports "
        "itself converged (filter_converged, the paper's Table I as its own statistics allow it to have been taken; no "
        "ground truth decides; the trajectory is simulated `warmup_max_steps` longer, a run not converged by then is "
        "scored from there, and the first T steps are scored too, as `from_start`), or at its first frame (start: "
        "from the uniform cloud). guess and kidnap always score from their own start.",
    )
    # filter_converged: a run not converged after this many steps is scored from there
    warmup_max_steps: int = Field(
        30, ge=0, description="filter_converged: the most unscored steps before the T scored."
    )
    # global: from the uniform belief (the paper) | guess: from a pose guess (AMCL's initial pose) | kidnap | active:
    # the localizer's suggestions after the first one, beside the passive route | storeys: routes through a portal
    scenario: Literal["global", "guess", "kidnap", "active", "storeys"] = Field(
        "global",
        description="How a run starts: global (the paper: from the uniform belief over the building), guess (from a "
        "pose guess `guess_offset_m` / `guess_offset_deg` off the first frame's truth, AMCL's initial pose), or "
        "kidnap (from the uniform belief; after `kidnap_at` keyframes the robot is carried, unseen by odometry, to "
        "keyframe `kidnap_resume_at` of the route three further on, and the T steps from there are scored), or "
        "active (from the uniform belief, the route until the localizer first suggests where to look, then its "
        "suggestions (`active`), T keyframes in all; the passive route from the same start runs beside it), or "
        "storeys (from the uniform belief, routes that change floor through a lift or a stair, each run localized "
        "without and with the storey-change event: variants +event).",
    )
    # global, kidnap: the start covers only the storey the robot starts on (it knows its floor)
    known_storey: bool = Field(
        False,
        description="global and kidnap: the robot knows the storey it starts on (the uniform start covers the first "
        "frame's true storey only, `smcl.start.storeys`); false: every storey (the paper's single floor has one).",
    )
    # guess: the guess's distance from the true first position. guess: this far from the first frame's true position,
    # in a seeded direction ...
    guess_offset_m: ClassVar[float] = 1.0
    # guess: its heading error (seeded sign). ... and turned this much, of seeded sign
    guess_offset_deg: ClassVar[float] = 20.0
    # kidnap: after 25 keyframes of route k the robot is carried, unseen by odometry, ...
    kidnap_at: int = Field(25, ge=1, description="kidnap: keyframes driven before the robot is carried off.")
    # ... to keyframe 10 of route k + 3 (mod the routes); the T steps from there are scored
    kidnap_resume_at: int = Field(10, ge=0, description="kidnap: the keyframe of the other route it is put down at.")

    @property
    def scores_from_convergence(self) -> bool:
        """Whether a run's scored steps begin at the filter's own converged flag (`filter_converged`, global only)."""
        return self.scenario == "global" and self.score_from == "filter_converged"

    @property
    def warmup_steps(self) -> int:
        """Keyframes a route is simulated beyond T: `warmup_max_steps` when scored from the filter's convergence."""
        return self.warmup_max_steps if self.scores_from_convergence else 0


class ActiveConfig(_Strict):
    """Where to look next (`bimfactor.active`): the viewpoint whose predicted observations best tell the belief's
    modes apart, less the way there."""

    horizon_m: float = Field(8.0, gt=0.0, description="Candidate viewpoints lie within this path length of the robot.")
    candidates: int = Field(200, ge=8, description="At most this many candidate viewpoints (positions × 8 headings).")
    # each keyframe on the way (0.5 m driven or 15 deg turned) must earn this many nats
    cost_per_keyframe: float = Field(
        0.02,
        ge=0.0,
        description="The travel cost: nats of expected information each keyframe on the way (driven or turned) must "
        "earn.",
    )
    settled_share: float = Field(
        0.95, gt=0.5, le=1.0, description="Nothing to suggest once one mode holds this share of the modes' probability."
    )


class Config(_Strict):
    seed: int = Field(0, ge=0, description="Seed of every random generator in a run (numpy takes no negative seed).")
    bim: BimConfig = Field(default_factory=BimConfig)
    embed: EmbedConfig = Field(default_factory=EmbedConfig)
    perception: PerceptionConfig = Field(default_factory=PerceptionConfig)
    # the RGB-D camera's depth: the simulator renders with this noise; the estimator models it
    sensor: SensorConfig = Field(default_factory=SensorConfig)
    # the depth frame's 2-D scan, for the filter's scan term and the pose graphs' scan factor
    scan: ScanConfig = Field(default_factory=ScanConfig)
    # the robot's wheel odometry: the simulator draws this noise, the pose graphs weigh by it
    odometry: OdometryConfig = Field(default_factory=OdometryConfig)
    # the semantic particle filter (docs/filter.md); each block is one component
    smcl: SmclConfig = Field(default_factory=SmclConfig)
    localization: LocalizationConfig = Field(default_factory=LocalizationConfig)
    # beyond the paper: one GTSAM pose graph per particle-filter mode
    backend: BackendConfig = Field(default_factory=BackendConfig)
    sim: SimConfig = Field(default_factory=SimConfig)
    io: IoConfig = Field(default_factory=IoConfig)
    registration: RegistrationConfig = Field(default_factory=RegistrationConfig)
    evaluation: EvaluationConfig = Field(default_factory=EvaluationConfig)
    # where to look next (docs/active.md): the view that best tells the belief's modes apart
    active: ActiveConfig = Field(default_factory=ActiveConfig)

    @model_validator(mode="after")
    def _scan_within_the_band(self) -> Config:
        if self.sensor.min_z_m > self.bim.grid.band_min_m:
            raise ValueError(
                f"sensor.min_z_m ({self.sensor.min_z_m:g}) is above bim.grid.band_min_m "
                f"({self.bim.grid.band_min_m:g}): the grid would hold surfaces the scan cannot see (a window's sill "
                "reads as the wall's inner face)"
            )
        return self

    def dump_yaml(self) -> str:
        """The resolved configuration as YAML, written next to every output."""
        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False)


ESSENTIAL_KEYS = (
    "seed",
    "bim.ifc.cache_dir",
    "bim.grid.resolution_m",
    "bim.grid.robot_radius_m",
    "bim.rooms.source",
    "embed.text_model",
    "embed.clip_weights",
    "perception.backend",
    "perception.device",
    "perception.vlm.yolo_world_weights",
    "perception.vlm.sam_weights",
    "perception.text.enabled",
    "sensor.min_z_m",
    "sensor.max_range_m",
    "odometry.alpha",
    "smcl.num_particles",
    "smcl.start.pose",
    "smcl.start.storeys",
    "smcl.resampler.kind",
    "smcl.resampler.max_particles",
    "localization.variant",
    "localization.keyframe_distance_m",
    "localization.keyframe_angle_deg",
    "localization.output",
    "backend.max_modes",
    "registration.method",
)
"""The keys a run is most often set by: the robot, the sensor, the detector, the start and the variant. `bimfactor
config` prints them; every other key is an expert key, documented in docs/config-reference.md with its default."""


def leaf_keys(model: type[BaseModel] | None = None, prefix: str = "") -> Iterator[tuple[str, FieldInfo]]:
    """Every leaf key of the config tree (dotted, in declaration order) with its field: what it means and its bounds."""
    for name, field in (model or Config).model_fields.items():
        dotted = f"{prefix}{name}"
        if isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel):
            yield from leaf_keys(field.annotation, f"{dotted}.")
        else:
            yield dotted, field


def value_at(model: BaseModel, dotted: str) -> Any:
    """The value at a dotted key, as the YAML files write it (`value_at(cfg, "smcl.start.pose")`)."""
    node: Any = model.model_dump(mode="json")
    for key in dotted.split("."):
        node = node[key]
    return node


_Model = TypeVar("_Model", bound=BaseModel)


def updated(model: _Model, changes: dict[str, Any]) -> _Model:
    """A validated copy of a config model with its fields at dotted keys replaced, e.g.
    `updated(cfg, {"smcl.start.pose": [1.0, 2.0, 90.0]})` or `updated(cfg.smcl, {"augmented.enabled": False})`."""
    data = model.model_dump()
    for dotted, value in changes.items():
        *parents, leaf = dotted.split(".")
        node = data
        for key in parents:
            node = node[key]
        if leaf not in node:
            raise KeyError(f"{type(model).__name__} has no field {dotted!r}")
        node[leaf] = value
    return type(model).model_validate(data)


def _read_yaml(path: Path) -> dict[str, Any]:
    """The mapping a config file holds; a ConfigError of one line for whatever else the file is."""
    if path.is_dir():
        raise ConfigError(f"{path} is a folder, not a config file")
    if path.exists() and not path.is_file():
        raise ConfigError(f"{path} is not a regular file (a device or a pipe), not a config file")
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    text = read_utf8(path, ConfigError, hint="save the file as UTF-8")
    if not text.strip():
        raise ConfigError(f"{path}: the file is empty; a config file is a YAML mapping of the keys it overrides")
    try:
        data = yaml.safe_load(text)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        what = " ".join(str(exc.problem or exc.context or type(exc).__name__).split())
        raise ConfigError(f"{path}: not valid YAML{where}: {what}") from None
    except yaml.reader.ReaderError as exc:
        line = text.count("\n", 0, exc.position) + 1
        raise ConfigError(
            f"{path}: not valid YAML at line {line}: character {chr(exc.character)!a} ({exc.reason})"
        ) from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({type(exc).__name__})") from None
    if data is None:  # nothing but comments: overrides nothing
        return {}
    if not isinstance(data, dict):
        kind = _yaml_kind(data)
        raise ConfigError(
            f"{path}: top level must be a mapping of config keys (as `bimfactor config --all` prints), not a {kind}"
        )
    return data


def _yaml_kind(value: object) -> str:
    if isinstance(value, list):
        return "list"
    if isinstance(value, str):
        return "string"
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, int | float):
        return "number"
    return type(value).__name__


def _merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _apply_override(data: dict[str, Any], assignment: str) -> None:
    """Apply one `dotted.key=value` override; the value is parsed as YAML (numbers, lists, booleans)."""
    if "=" not in assignment:
        raise ConfigError(f"override '{assignment}' is not of the form key.path=value")
    dotted, raw = assignment.split("=", 1)
    keys = dotted.strip().split(".")
    node = data
    for key in keys[:-1]:
        if not isinstance(node.get(key), dict):
            raise ConfigError(_unknown_key(dotted))
        node = node[key]
    if keys[-1] not in node:
        raise ConfigError(_unknown_key(dotted))
    try:
        node[keys[-1]] = yaml.safe_load(raw)
    except yaml.YAMLError as exc:
        raise ConfigError(f"override '{assignment}': value is not valid YAML") from exc


MOVED_KEYS = {
    "sim.trajectory.keyframe_distance_m": "localization.keyframe_distance_m",
    "sim.trajectory.keyframe_angle_deg": "localization.keyframe_angle_deg",
    "backend.scan_recentre": "backend.scan_factor.recentre",
    "backend.scan_step_deg": "backend.scan_factor.step_deg",
    "backend.scan_candidates": "backend.scan_factor.candidates",
}
"""Keys of earlier versions and where they are now: an old config file's error names the new key."""

KEYS_ELSEWHERE = {
    "perception.vlm.clip_weights": "embed.clip_weights",
    "perception.vlm.clip_model": "embed.clip_model",
}
"""Keys a user may look for in one block that live in another: the error names the one that exists."""


def _unknown_key(dotted: str) -> str:
    moved = MOVED_KEYS.get(dotted)
    if moved:
        return f"unknown config key '{dotted}': it is now '{moved}'"
    elsewhere = KEYS_ELSEWHERE.get(dotted)
    if elsewhere:
        return f"unknown config key '{dotted}': the key is '{elsewhere}' (shared with the text encoder)"
    if _is_fixed(dotted):
        return (
            f"unknown config key '{dotted}': a fixed value of its stage now, not a key "
            "(docs/config-reference.md, 'Fixed values')"
        )
    return f"unknown config key '{dotted}'"


def _is_fixed(dotted: str) -> bool:
    """Whether `dotted` names a ClassVar of the config tree (`backend.scan_factor.window_m`)."""
    *blocks, name = dotted.split(".")
    model: Any = Config
    for block in blocks:
        field = model.model_fields.get(block) if isinstance(model, type) else None
        inner = getattr(model, block, None) if field is None else field.annotation
        model = type(inner) if isinstance(inner, BaseModel) else inner
        if not (isinstance(model, type) and issubclass(model, BaseModel)):
            return False
    return name in model.__class_vars__


def _first_error(exc: ValidationError) -> str:
    err = exc.errors()[0]
    where = ".".join(str(p) for p in err["loc"])
    if err["type"] == "extra_forbidden":
        return _unknown_key(where)
    if err["type"] == "missing":
        return f"missing config key '{where}'"
    if err["type"] == "finite_number":
        return f"config key '{where}': must be a finite number, not {err['input']!r}"
    message = err["msg"].removeprefix("Value error, ")
    return f"config key '{where}': {message}" if where else f"config: {message}"


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """The fields' defaults, then a preset or user file on top, then `key=value` overrides.

    A preset can be named by file path or by its name in `bimfactor/configs/` (`PRESETS`: "paper", "default",
    "fast"). A configuration whose particle sets cannot fit in the memory available now is refused
    (`resources.check_particle_memory`).
    """
    data = Config().model_dump()
    if path is not None and not str(path).strip():
        raise ConfigError(f"the config is named by an empty text: give a preset ({', '.join(PRESETS)}) or a YAML file")
    if path is not None and str(path) != "default":
        candidate = Path(path)
        if not candidate.exists() and not candidate.suffix:
            if str(path) not in PRESETS:  # the folder's data tables (vocabulary, room categories) are no presets
                raise ConfigError(
                    f"config file not found: {path} (no such file, and the presets are {', '.join(PRESETS)})"
                )
            candidate = CONFIG_DIR / f"{path}.yaml"
        data = _merge(data, _read_yaml(candidate))
    for assignment in overrides:
        _apply_override(data, assignment)
    try:
        cfg = Config.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_first_error(exc)) from None
    check_particle_memory(cfg)
    return cfg


def config_file(name: str) -> Path:
    """Path of a data table shipped in bimfactor/configs/ (vocabulary, room categories)."""
    path = CONFIG_DIR / name
    if not path.is_file():
        raise ConfigError(f"config table not found: {path}")
    return path
