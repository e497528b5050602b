"""Door plates in the simulated world, read back by the sim text reader and placed in the robot frame."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bimfactor.backend.factors import Landmarks
from bimfactor.backend.posegraph import ModeGraph, observation_cost, semantic_associator
from bimfactor.bim.plates import DOOR_PLATE_LABEL, PLATE_REACH_M, door_plates, look_alikes
from bimfactor.config import updated
from bimfactor.localization.filter import SemanticMCL
from bimfactor.localization.measurements import FrameData
from bimfactor.localization.measurements.scan import ScanLikelihood
from bimfactor.localization.measurements.semantic import SemanticLikelihood
from bimfactor.localization.measurements.text import PlateLikelihood
from bimfactor.localization.recovery.text_reset import TextReset
from bimfactor.perception.text import SimTextReader, locate_readings, read_probability
from bimfactor.pipeline import visibility_of
from bimfactor.sim.sensors import RgbdCamera
from bimfactor.sim.simulate import build_world
from bimfactor.sim.world import SimWorld
from bimfactor.types import Frame, Observations, SequenceMeta, TextObservations, se2_compose, wrap_angle

from .conftest import NOISE_OFF, Building, config_with

PLATES_ON = [
    "sim.door_plates.enabled=true",
    "perception.text.enabled=true",
    "perception.text.sim_look_alike_rate=0",
    "perception.text.sim_char_error_rate=0",
    "perception.text.sim_drop_rate=0",
]


@pytest.fixture(scope="module")
def plated(duplex: Building, config_overrides: list[str]):
    always = ["perception.text.sim_read_probability=1", "perception.text.sim_read_char_px=0",
              "perception.text.sim_read_char_scale_px=0.001"]  # fmt: skip
    cfg = config_with(config_overrides, *NOISE_OFF, *PLATES_ON, *always)
    return cfg, build_world(duplex.prior, duplex.model, cfg, seed=0)


def _plate_records(world: SimWorld) -> list[dict]:
    return [rec for rec in world.instances if rec["label"] == DOOR_PLATE_LABEL]


def test_plates_hang_by_default_and_only_then(duplex: Building, plated) -> None:
    assert _plate_records(build_world(duplex.prior, duplex.model, duplex.cfg, seed=0))  # the default hangs them
    plain = build_world(duplex.prior, duplex.model, updated(duplex.cfg, {"sim.door_plates.enabled": False}), seed=0)
    assert _plate_records(plain) == []
    _, world = plated
    records = _plate_records(world)
    numbers = {room.space_number for room in duplex.prior.rooms}
    assert len(records) >= 15
    assert all(rec["text"] in numbers and rec["object_id"] == -1 for rec in records)


def test_a_plate_is_read_from_in_front_and_placed_where_it_hangs(duplex: Building, plated) -> None:
    cfg, world = plated
    camera = RgbdCamera.from_config(world, cfg)
    meta = SequenceMeta("plates", "sim", camera.intrinsics, camera.T_base_camera, instances=world.instances)
    reader = SimTextReader(meta, cfg.perception.text, np.random.default_rng(0))
    read_any = 0
    for plate in door_plates(duplex.prior)[:10]:
        # 2 m in front of the door on the plate's side, facing the wall: the plate is beside the door, in view.
        xy = np.asarray(plate.xy) + 2.0 * np.asarray(plate.normal_xy)
        pose = np.array([*xy, np.arctan2(-plate.normal_xy[1], -plate.normal_xy[0])])
        elevation = duplex.prior.storeys[plate.storey_index].storey.elevation_m
        image = camera.render(pose, elevation)
        frame = Frame(0, 0.0, image.rgb, image.depth_m, np.zeros(3), instance_ids=image.instance_ids)
        readings = reader.read(frame)
        mine = [r for r in readings if r.text == plate.text]
        if not mine:
            continue
        read_any += 1
        located = locate_readings(mine, image.depth_m, camera.intrinsics, camera.T_base_camera, 8.0)
        r, b = located.range_m[0], located.bearing_rad[0]
        seen_xy = se2_compose(pose, np.array([r * np.cos(b), r * np.sin(b), 0.0]))[:2]
        # Beside its door: within the door's half width plus the plate's gap and width of the door's centre.
        assert np.linalg.norm(seen_xy - np.asarray(plate.xy)) < plate.door_width_m / 2 + 0.5
        assert abs(wrap_angle(located.bearing_rad[0])) < np.deg2rad(45)
    assert read_any >= 5


def test_character_errors_and_legibility(duplex: Building, plated) -> None:
    cfg, world = plated
    camera = RgbdCamera.from_config(world, cfg)
    meta = SequenceMeta("plates", "sim", camera.intrinsics, camera.T_base_camera, instances=world.instances)
    plate = door_plates(duplex.prior)[0]
    frames = []
    for distance in (1.8, 6.0):
        xy = np.asarray(plate.xy) + distance * np.asarray(plate.normal_xy)
        pose = np.array([*xy, np.arctan2(-plate.normal_xy[1], -plate.normal_xy[0])])
        image = camera.render(pose, duplex.prior.storeys[plate.storey_index].storey.elevation_m)
        frames.append(Frame(0, 0.0, image.rgb, image.depth_m, np.zeros(3), instance_ids=image.instance_ids))
    exact = SimTextReader(meta, cfg.perception.text, np.random.default_rng(1))
    assert plate.text in [r.text for r in exact.read(frames[0])]
    assert exact.read(frames[1]) == []  # 6 m away a 15 cm plate is a few pixels high: not legible
    ids = {rec["id"] for rec in _plate_records(world) if rec["text"] == plate.text}

    def read_with(**rates: float) -> list[str]:
        reader = SimTextReader(meta, cfg.perception.text.model_copy(update=rates), np.random.default_rng(1))
        return [r.text for r in reader.read(frames[0]) if r.gt_instance_id in ids]

    garbled = read_with(sim_char_error_rate=1.0)
    assert garbled and all(
        len(t) == len(plate.text) and all(a != b for a, b in zip(t, plate.text, strict=True)) for t in garbled
    )
    # Every character that has a look-alike is read as one; one that has none ("K") is read right.
    similar = read_with(sim_look_alike_rate=1.0)
    assert similar and all(
        len(t) == len(plate.text)
        and all(b in look_alikes(a) if look_alikes(a) else a == b for a, b in zip(plate.text, t, strict=True))
        for t in similar
    )
    assert read_with(sim_drop_rate=1.0) == []  # every character lost: no reading
    # The read chance by the plate's width per character: half way at sim_read_char_px, the most when wide.
    p = read_probability(np.array([0.0, 4.0, 5.0, 6.0, 30.0]), 0.8, 5.0, 1.0)
    assert np.all(np.diff(p) > 0) and p[2] == pytest.approx(0.4) and p[-1] == pytest.approx(0.8)
    assert p[1] == pytest.approx(0.8 / (1 + np.e)) and p[0] < 0.01
    assert read_with(sim_read_char_px=1e3) == []  # no plate is that wide: none is read


def _facing(plate, distance: float) -> np.ndarray:
    """The pose `distance` in front of a plate's door, facing it."""
    xy = np.asarray(plate.xy) + distance * np.asarray(plate.normal_xy)
    return np.array([*xy, np.arctan2(-plate.normal_xy[1], -plate.normal_xy[0])])


def _plate_and_twin(prior):
    """A plate of unit A whose number appears once, and its twin in unit B."""
    plates = door_plates(prior)
    plate = next(p for p in plates if p.text.startswith("A") and sum(q.text == p.text for q in plates) == 1)
    return plate, next(p for p in plates if p.text == "B" + plate.text[1:])


def _reading_only(prior, text: str) -> Observations:
    """A step that detected no object and read `text` 2 m straight ahead."""
    empty = Observations(np.zeros((0, prior.object_embeddings.shape[1]), np.float32), np.zeros(0), np.zeros(0))
    empty.texts = TextObservations([text], np.array([2.0]), np.array([0.0]))
    return empty


def test_plates_face_away_from_their_rooms(duplex: Building) -> None:
    prior = duplex.prior
    plates = door_plates(prior)
    assert len(plates) >= 20 and {p.text[0] for p in plates} == {"A", "B"}  # the two units' numbers
    areas = {room.id: room.area_m2 for room in prior.rooms}
    for plate in plates:
        xy, n = np.asarray(plate.xy), np.asarray(plate.normal_xy)
        inside, outside = prior.room_at(np.array([xy - 0.5 * n, xy + 0.5 * n]), plate.storey_index)
        assert inside == plate.room_id != outside
        assert prior.rooms[plate.room_id].space_number == plate.text
        door = prior.doors[plate.door_id]
        other = door.room_b if door.room_a == plate.room_id else door.room_a
        assert areas.get(other, np.inf) >= areas[plate.room_id]  # between two rooms, the smaller is named
    assert len({p.door_id for p in plates}) == len(plates)
    unnumbered = dataclasses.replace(prior, rooms=[dataclasses.replace(r, space_number="") for r in prior.rooms])
    assert door_plates(unnumbered) == []


def test_reading_likelihood_by_hand(duplex: Building) -> None:
    cfg = duplex.cfg.smcl
    plate, twin = _plate_and_twin(duplex.prior)
    # Only these two rooms keep their numbers, so no third plate's near-miss text enters the values below.
    rooms = [
        r if r.id in (plate.room_id, twin.room_id) else dataclasses.replace(r, space_number="")
        for r in duplex.prior.rooms
    ]
    model = PlateLikelihood(dataclasses.replace(duplex.prior, rooms=rooms), cfg)
    eps, c = cfg.text.unexplained, cfg.text.edit_cost
    at_plate, at_twin = _facing(plate, 2.0), _facing(twin, 2.0)
    behind = np.array([*(np.asarray(plate.xy) - 2.0 * np.asarray(plate.normal_xy)), at_plate[2] + np.pi])
    poses = np.stack([at_plate, at_twin, behind])
    storeys = np.array([plate.storey_index, twin.storey_index, plate.storey_index])
    reading = TextObservations([plate.text.lower()], np.array([2.0]), np.array([0.0]))
    got = model.log_likelihood(poses, storeys, reading)
    # In front of the plate, where it was read: q = 1. At the twin unit's plate one character differs: e^-c.
    # Behind the wall nothing explains it: ε alone.
    # (The other unit's plate, metres away and off the bearing, adds under 1e-3 to the last.)
    np.testing.assert_allclose(got, np.log([1.0, eps + (1 - eps) * np.exp(-c), eps]), atol=1e-3)
    # The twin's letter read as its look-alike ("8" for "B"): a likely misread of the twin's plate, and two unlikely
    # edits from this one ("8" for "A"); the look-alike's cost is the cheaper one.
    misread = TextObservations(["8" + plate.text[1:]], np.array([2.0]), np.array([0.0]))
    got = model.log_likelihood(poses[:2], storeys[:2], misread)
    expected = eps + (1 - eps) * np.exp(-np.array([c, cfg.text.look_alike_cost]))
    assert cfg.text.look_alike_cost < c
    np.testing.assert_allclose(got, np.log(expected), atol=1e-3)
    # Read 1 m nearer than it is and 20° off: the paper's φ_dist and φ_ang.
    off = TextObservations([plate.text], np.array([1.0]), np.array([np.deg2rad(20)]))
    q = np.exp(-1.0 / cfg.semantic.sigma_d_m) * np.exp(cfg.semantic.kappa_alpha * (np.cos(np.deg2rad(20)) - 1))
    np.testing.assert_allclose(model.log_likelihood(at_plate[None], storeys[:1], off), np.log(eps + (1 - eps) * q))
    # A reading no plate matches moves no particle against another.
    nothing = TextObservations(["EXIT"], np.array([2.0]), np.array([0.0]))
    np.testing.assert_allclose(model.log_likelihood(poses, storeys, nothing), np.log(eps), rtol=1e-12)


def test_the_filter_tells_the_twin_units_apart_by_a_plate(duplex: Building) -> None:
    """The duplex's units are one turned by 180°: objects and walls cannot tell them apart, a plate can."""
    cfg = duplex.cfg.smcl
    plate, twin = _plate_and_twin(duplex.prior)
    filt = SemanticMCL(duplex.prior, visibility_of(duplex.prior, duplex.cfg), cfg, np.random.default_rng(0))
    filt.initialize_around(_facing(plate, 2.0), plate.storey_index, 0.3, np.deg2rad(5))
    half = filt.num_particles // 2
    filt.particles[half:] = _facing(twin, 2.0)
    filt.storeys[half:] = twin.storey_index
    filt.weights[:] = 1.0 / filt.num_particles
    empty = _reading_only(duplex.prior, plate.text)
    filt.update(FrameData(empty))
    assert filt.weights[:half].sum() > 0.9


def _text_reset(filt: SemanticMCL) -> TextReset:
    return next(r for r in filt.recoveries.injections if isinstance(r, TextReset))


def test_a_reading_the_belief_cannot_explain_redraws_particles_before_its_plate(duplex: Building) -> None:
    """Sensor resetting: a belief wholly in the wrong unit holds no particle that a plate read explains, so weighing
    cannot move it there; the reading redraws `text_reset.share` of the particles in front of its plate, and the next
    reading carries the weight over."""
    cfg = duplex.cfg.smcl
    plate, twin = _plate_and_twin(duplex.prior)
    filt = SemanticMCL(duplex.prior, visibility_of(duplex.prior, duplex.cfg), cfg, np.random.default_rng(0))
    filt.initialize_around(_facing(twin, 2.0), twin.storey_index, 0.3, np.deg2rad(5))
    reset = _text_reset(filt)
    empty = FrameData(_reading_only(duplex.prior, plate.text))
    filt.update(empty)
    assert reset.unexplained == [0]
    resampled, injected = filt.resample(empty)
    M = filt.num_particles
    assert resampled and injected == round(cfg.text_reset.share * M)
    # Redrawn 2 m from the plate (the read range), on its side of the wall, turned towards it.
    offset = filt.particles[:, :2] - np.asarray(plate.xy)
    sigma = cfg.motion.sigma_trans_m
    near = (np.abs(np.hypot(*offset.T) - 2.0) < 4 * sigma) & (offset @ np.asarray(plate.normal_xy) > 0)
    assert near[filt.fresh].mean() > 0.95 and not near[~filt.fresh].any()
    assert (filt.storeys[filt.fresh] == plate.storey_index).all()
    filt.update(empty)  # read again: the redrawn particles in front of the plate explain it, the others do not
    assert filt.weights[filt.storeys == plate.storey_index][near[filt.storeys == plate.storey_index]].sum() > 0.5
    assert reset.unexplained == []
    # A reading that names no plate ("EXIT") redraws nothing, and neither does one the belief explains.
    filt.initialize_around(_facing(twin, 2.0), twin.storey_index, 0.3, np.deg2rad(5))
    for text in ("EXIT", twin.text):
        filt.update(FrameData(_reading_only(duplex.prior, text)))
        assert reset.unexplained == []
    # A look-alike misread ("4" for "A") where its plate hangs is judged as the text it reads: explained.
    filt.initialize_around(_facing(plate, 2.0), plate.storey_index, 0.3, np.deg2rad(5))
    filt.update(FrameData(_reading_only(duplex.prior, "4" + plate.text[1:])))
    assert reset.unexplained == []


def test_the_redraw_is_screened_by_the_frame_scan(duplex: Building, fixed_value) -> None:
    """Redrawn on the arc before the plate (±60° of its normal), the particles kept from four times as many drawn
    (`text_reset.oversample` 4) fit the frame's scan (the plate's wall square ahead at the read range) better than
    those drawn without the screen (1), and still explain the reading."""
    plate, twin = _plate_and_twin(duplex.prior)
    wall = np.column_stack([np.full(9, 2.0), np.linspace(-0.4, 0.4, 9)])  # the plate's wall, 2 m straight ahead
    reading = _reading_only(duplex.prior, plate.text)
    fit = {}
    for oversample in (1, 4):
        fixed_value("smcl.text_reset.oversample", oversample)
        cfg = updated(duplex.cfg.smcl, {"augmented.enabled": False})
        filt = SemanticMCL(duplex.prior, visibility_of(duplex.prior, duplex.cfg), cfg, np.random.default_rng(0))
        filt.initialize_around(_facing(twin, 2.0), twin.storey_index, 0.3, np.deg2rad(5))
        filt.update(FrameData(reading))
        assert filt.resample(FrameData(reading, wall))[1] == round(cfg.text_reset.share * filt.num_particles)
        drawn, storeys = filt.particles[filt.fresh], filt.storeys[filt.fresh]
        offset = drawn[:, :2] - np.asarray(plate.xy)
        assert np.median(np.abs(np.hypot(*offset.T) - 2.0)) < 3 * cfg.motion.sigma_trans_m
        fit[oversample] = ScanLikelihood(duplex.prior, cfg.scan).scores(drawn, storeys, wall).mean()
    assert fit[4] > fit[1] + 0.05  # 0.58 against 0.49


def test_the_pose_graphs_take_a_read_plate_as_a_landmark(duplex: Building) -> None:
    """A plate read is a bearing-range factor to the plate's landmark at the pose that explains it, and a reading no
    plate explains at a mode's pose costs that mode an outlier's χ²."""
    prior, cfg = duplex.prior, duplex.cfg
    plates = door_plates(prior)
    plate_index = next(
        k for k, p in enumerate(plates) if p.text.startswith("A") and sum(q.text == p.text for q in plates) == 1
    )
    plate = plates[plate_index]
    twin = next(p for p in plates if p.text == "B" + plate.text[1:])
    likelihood = SemanticLikelihood(prior, visibility_of(prior, cfg), cfg.smcl.semantic)
    plate_model = PlateLikelihood(prior, cfg.smcl)
    landmark = plate_model.first_landmark_id + plate_index
    landmarks = Landmarks.from_prior(prior)
    assert len(landmarks.xy) == plate_model.first_landmark_id + len(plates)
    np.testing.assert_allclose(landmarks.xy[landmark], plate.xy)
    # Along its wall the plate may hang anywhere beside its door; across the wall it is where the wall is.
    along = float(np.abs(np.asarray(plate.axis_xy)) @ landmarks.size[landmark])
    across = float(np.abs(np.asarray(plate.normal_xy)) @ landmarks.size[landmark])
    assert along == pytest.approx(plate.door_width_m + 2 * PLATE_REACH_M) and across < 1e-9

    observed = Observations(np.zeros((1, prior.object_embeddings.shape[1]), np.float32), np.ones(1), np.zeros(1))
    observed.texts = TextObservations([plate.text], np.array([2.0]), np.array([0.0]))
    associate = semantic_associator(likelihood, plate_model, observed)
    at_plate, at_twin = _facing(plate, 2.0), _facing(twin, 2.0)
    assert (1, landmark) in associate(at_plate, plate.storey_index)  # measurement 1: past the one node
    assert all(k != 1 for k, _ in associate(at_twin, twin.storey_index))  # one character off: no factor
    bcfg = cfg.backend
    xy = {landmark: landmarks.xy[landmark]}
    cost_here = observation_cost(at_plate, xy, observed, [(1, landmark)], bcfg)
    cost_twin = observation_cost(at_twin, xy, observed, [], bcfg)
    assert cost_here == pytest.approx(bcfg.outlier_chi2)  # the unmatched node; the plate fits exactly
    assert cost_twin == pytest.approx(2 * bcfg.outlier_chi2)

    # A mode 0.6 m too near the door (a loose prior) is pushed back by the reading's range: the factor is in.
    near = at_plate.copy()
    near[:2] -= 0.6 * np.asarray(plate.normal_xy)
    graph = ModeGraph(0, 0, near, np.diag([1.0, 1.0, 0.01]), landmarks, bcfg, cfg.odometry, plate.storey_index)
    graph.add_keyframe(0, observed, [(1, landmark)])
    before = float(np.hypot(*(near[:2] - plate.xy)))
    after = float(np.hypot(*(graph.pose[:2] - graph.landmark_estimate(landmark))))
    assert before == pytest.approx(1.4) and abs(after - 2.0) < 0.5 * abs(before - 2.0)


def test_rendered_plates_show_their_text_to_a_real_ocr_engine(duplex: Building, config_overrides: list[str]) -> None:
    """The world prints each plate's number on its face (`PlateTexture`): RapidOCR reads it from a 640 × 480 frame
    1.5 m in front of the plate, left to right, and a far pixel sees the print's average grey, not a texel of ink."""
    RapidOcrReader = pytest.importorskip("bimfactor.perception.ocr").RapidOcrReader
    pytest.importorskip("rapidocr_onnxruntime")
    cfg = config_with(config_overrides, *NOISE_OFF, *PLATES_ON, "sim.camera.width=640", "sim.camera.height=480")
    world = build_world(duplex.prior, duplex.model, cfg, seed=0)
    camera = RgbdCamera(world, cfg.sim.camera, cfg.sensor.depth_noise, cfg.sim.depth_dropout, 0.0)
    ocr = RapidOcrReader(0.5)
    read = []
    for rec in [r for r in world.instances if r["label"] == DOOR_PLATE_LABEL][:3]:
        face, right = np.asarray(rec["plate_face_m"]), np.asarray(rec["plate_right_xy"])
        out = np.array([right[1], -right[0]])
        pose = np.array([*(face[:2] + 1.5 * out), np.arctan2(-out[1], -out[0])])
        elevation = duplex.prior.storeys[rec["storey_index"]].storey.elevation_m
        image = camera.render(pose, elevation)
        on_plate = image.rgb[image.instance_ids == rec["id"]].mean(axis=1)
        assert on_plate.min() < 60 and on_plate.max() > 150  # ink on paper
        frame = Frame(0, 0.0, image.rgb, image.depth_m, np.zeros(3))
        read.append(rec["text"] in [r.text for r in ocr.read(frame)])
    assert sum(read) >= 2
    texture = world.textures[rec["id"]]
    # Along the text's middle line: sharp ink and paper texels up close; one grey from 20 m away (the coarsest level).
    along = np.linspace(-0.1, 0.1, 41)[:, None] * texture.right_xy
    line = np.column_stack([texture.face_m[:2] + along, np.full(41, texture.face_m[2])])
    near, far = texture.sample(line, np.full(41, 1e-4)), texture.sample(line, np.full(41, 20 / 160))
    assert near.min() < 0.3 and near.max() > 0.8
    assert np.ptp(far) < 0.2
