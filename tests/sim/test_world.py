"""The simulated world: its instance table, its floors, and the as-built deviations it records."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.bim.ifc import FIXED_OBJECT_CLASSES
from bimfactor.bim.plates import DOOR_PLATE_LABEL
from bimfactor.sim.simulate import build_world
from bimfactor.sim.trajectory import SimTrajectory
from bimfactor.sim.world import CEILING_LABEL, CLUTTER_LABEL, FLOOR_LABEL, SimWorld, is_physical

from .conftest import Building, config_with

AS_BUILT = ["sim.as_built.moved_fraction=0.2", "sim.as_built.removed_fraction=0.1", "sim.as_built.clutter_count=5"]


@pytest.fixture(scope="module")
def world(building: Building) -> SimWorld:
    return build_world(building.prior, building.model, building.cfg, seed=0)


@pytest.fixture(scope="module")
def as_built_world(building: Building, config_overrides: list[str]) -> SimWorld:
    return build_world(building.prior, building.model, config_with(config_overrides, *AS_BUILT), seed=0)


def _down(world: SimWorld, xy: np.ndarray, z: float) -> tuple[float, int]:
    """Distance and instance of the first hit of a ray straight down from (x, y, z)."""
    t, instance, _ = world.cast(np.array([[xy[0], xy[1], z, 0.0, 0.0, -1.0]], np.float32))
    return float(t[0]), int(instance[0])


def test_instance_table_is_the_physical_elements(building: Building, world: SimWorld) -> None:
    physical = [e for e in building.model.elements if is_physical(e)]
    objects = {o.guid: o for o in building.prior.objects}
    assert [rec["id"] for rec in world.instances] == list(range(len(world.instances)))
    plates = [rec for rec in world.instances if rec["label"] == DOOR_PLATE_LABEL]  # hung by default, not IFC elements
    assert all(not rec["guid"] and rec["object_id"] == -1 for rec in plates)
    plate_ids = {rec["id"] for rec in plates}
    records = [rec for rec in world.instances if rec["id"] not in plate_ids]
    assert all(set(rec) == {"id", "guid", "ifc_class", "object_id", "label"} for rec in records)
    from_ifc = [rec for rec in world.instances if rec["guid"]]
    assert sorted(rec["guid"] for rec in from_ifc) == sorted(e.guid for e in physical)
    assert not {"IfcDoor", "IfcSpace", "IfcOpeningElement"} & {rec["ifc_class"] for rec in from_ifc}
    for rec in from_ifc:
        obj = objects.get(rec["guid"])
        assert rec["object_id"] == (obj.id if obj else -1)
        if obj is not None:
            assert rec["label"] == obj.label
    walls = [rec["id"] for rec in from_ifc if rec["label"] == "wall"]
    floors = [rec["id"] for rec in world.instances if rec["label"] in (FLOOR_LABEL, "slab")]
    assert walls and floors
    assert world.albedo[walls].mean() > world.albedo[floors].mean()  # walls light grey, floors darker
    assert world.albedo.shape == (len(world.instances), 3) and world.changes == []


def test_the_robot_stands_on_a_floor(
    building: Building, world: SimWorld, six_trajectories: list[SimTrajectory]
) -> None:
    synthetic = {rec["label"] for rec in world.instances if not rec["guid"]}
    if building.name == "paper-floor":  # the synthetic floor has no slab
        assert {FLOOR_LABEL, CEILING_LABEL} <= synthetic
    for trajectory in six_trajectories:
        elevation = building.prior.storeys[trajectory.storey_index].storey.elevation_m
        for pose in trajectory.keyframe_poses[::10]:
            t, instance = _down(world, pose[:2], elevation + 0.5)
            assert t == pytest.approx(0.5, abs=0.1)
            if building.name == "duplex":  # the real model's slabs carry the robot
                assert world.instances[instance]["ifc_class"] in ("IfcSlab", "IfcCovering")


def test_as_built_changes_are_recorded_and_real(building: Building, world: SimWorld, as_built_world: SimWorld) -> None:
    changes = as_built_world.changes
    movable = [o for o in building.prior.objects if o.ifc_class not in FIXED_OBJECT_CLASSES]
    kinds = [c["kind"] for c in changes]
    assert kinds.count("removed") == round(0.1 * len(movable)) > 0
    assert kinds.count("moved") == round(0.2 * len(movable)) > 0
    assert kinds.count("clutter") == 5
    elevation = {s.storey.index: s.storey.elevation_m for s in building.prior.storeys}
    by_guid = {rec["guid"]: rec["id"] for rec in world.instances if rec["guid"]}
    checked = 0
    for change in changes:
        if change["kind"] == "removed":
            assert not as_built_world.instance_ids_of_guid(change["guid"])
            mesh = world.meshes[by_guid[change["guid"]]]
            xy, top = mesh.bounds.mean(axis=0)[:2], mesh.bounds[1, 2] + 0.02
            t_before, hit_before = _down(world, xy, top)
            if world.instances[hit_before]["guid"] != change["guid"]:
                continue  # nothing of the object lies under its centre (a table's legs, an L-shaped sofa)
            t_after, hit_after = _down(as_built_world, xy, top)
            assert as_built_world.instances[hit_after]["guid"] != change["guid"]
            assert t_after > t_before + 0.01  # the ray now passes where the object was
            checked += 1
        elif change["kind"] == "moved":
            [iid] = as_built_world.instance_ids_of_guid(change["guid"])
            old, new = world.meshes[by_guid[change["guid"]]], as_built_world.meshes[iid]
            shift, pivot, yaw = np.asarray(change["shift_xy_m"]), np.asarray(change["pivot_xy_m"]), change["yaw_rad"]
            assert np.linalg.norm(shift) <= 1.0 + 1e-9
            rotation = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
            expected = (old.vertices[:, :2] - pivot) @ rotation.T + pivot + shift
            np.testing.assert_allclose(new.vertices[:, :2], expected, atol=1e-9)
            np.testing.assert_array_equal(new.vertices[:, 2], old.vertices[:, 2])
            assert as_built_world.instances[iid]["object_id"] == change["object_id"]
        else:
            iid = change["instance_id"]
            rec = as_built_world.instances[iid]
            assert (rec["guid"], rec["object_id"], rec["label"]) == ("", -1, CLUTTER_LABEL)
            x, y, z = change["position_m"]
            top = z + change["size_m"][2] / 2
            assert top - change["size_m"][2] == pytest.approx(elevation[change["storey_index"]])
            t, hit = _down(as_built_world, np.array([x, y]), top + 0.2)
            assert hit == iid and t == pytest.approx(0.2, abs=1e-4)
            assert _down(world, np.array([x, y]), top + 0.2)[0] > 0.25  # the BIM has nothing there
    assert checked >= 1


def test_as_built_world_is_reproducible(building: Building, as_built_world: SimWorld, config_overrides) -> None:
    again = build_world(building.prior, building.model, config_with(config_overrides, *AS_BUILT), seed=0)
    other = build_world(building.prior, building.model, config_with(config_overrides, *AS_BUILT), seed=1)
    assert again.changes == as_built_world.changes
    assert other.changes != as_built_world.changes
