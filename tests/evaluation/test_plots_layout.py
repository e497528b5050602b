"""Run figures a person reads at a glance: the map zooms onto the route (the whole storey in an inset beside it when
the route covers little of it), the truth is drawn over the estimate, and the error axis has plain metre ticks."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from bimfactor.evaluation.plots import draw_floorplan, error_axis, zoom_to
from tests.localization.handmade import make_prior


def test_the_map_zooms_onto_a_short_route_with_the_whole_storey_beside_it() -> None:
    prior = make_prior()  # x ∈ [-1, 13], y ∈ [-1, 7]
    fig, ax = plt.subplots()
    draw_floorplan(ax, prior, 0, label_objects=False)
    zoom_to(ax, prior, 0, np.array([[2.0, 2.0], [2.5, 3.0], [np.nan, np.nan]]))
    assert ax.get_xlim() == (-1.0, 6.5) and ax.get_ylim() == (-1.0, 7.0)  # 4 m about it, within the building
    (inset,) = ax.child_axes
    assert inset.get_xlim() == tuple(prior.grid.extent[:2]) and inset.get_title() == "whole storey"
    assert inset.get_position().x0 > ax.get_position().x1  # beside the map: it hides none of it
    plt.close(fig)
    fig, ax = plt.subplots()
    draw_floorplan(ax, prior, 0, label_objects=False)
    zoom_to(ax, prior, 0, np.array([[0.0, 0.0], [12.0, 6.0]]))  # a route over the whole storey: no inset
    assert ax.child_axes == []
    plt.close(fig)


def test_the_error_axis_has_plain_metre_ticks() -> None:
    fig, ax = plt.subplots()
    ax.plot([0.004, 0.2, 2.4, 0.05])
    error_axis(ax)
    fig.canvas.draw()
    labels = [t.get_text() for t in ax.get_yticklabels()]
    assert labels == ["0", "0.03", "0.1", "0.3", "1", "3"]
    assert ax.get_ylim()[0] == 0.0 and ax.yaxis.get_minorticklocs().size == 0
    plt.close(fig)


def test_room_names_that_would_collide_are_dropped_the_larger_room_kept() -> None:
    from bimfactor.evaluation.plots import ROOM_LABEL, drop_colliding_labels

    fig, ax = plt.subplots(figsize=(4, 4))
    ax.set_xlim(0, 10)
    ax.set_ylim(0, 10)
    large = ax.text(5.0, 5.0, "living room", gid=ROOM_LABEL)  # drawn first: the larger room's
    small = ax.text(5.2, 5.0, "bathroom", gid=ROOM_LABEL)
    apart = ax.text(1.0, 1.0, "kitchen", gid=ROOM_LABEL)
    outside = ax.text(9.9, 9.9, "meeting room", gid=ROOM_LABEL)
    other = ax.text(5.1, 5.0, "not a room name")
    assert drop_colliding_labels(fig) == 2
    assert large.get_visible() and apart.get_visible() and other.get_visible()
    assert not small.get_visible() and not outside.get_visible()
    plt.close(fig)


def test_object_labels_give_way_to_room_names_and_to_each_other() -> None:
    from bimfactor.evaluation.plots import OBJECT_LABEL, ROOM_LABEL, drop_colliding_labels

    fig, ax = plt.subplots(figsize=(4, 4))
    ax.set_xlim(0, 10)
    ax.set_ylim(0, 10)
    chair = ax.annotate("chair", (5.0, 5.0), gid=OBJECT_LABEL)  # drawn before the room name, placed after it
    room = ax.text(5.0, 5.0, "office", gid=ROOM_LABEL)
    window = ax.annotate("window", (1.0, 1.0), gid=OBJECT_LABEL)
    next_window = ax.annotate("window", (1.3, 1.0), gid=OBJECT_LABEL)
    assert drop_colliding_labels(fig) == 2
    assert room.get_visible() and window.get_visible()
    assert not chair.get_visible() and not next_window.get_visible()
    plt.close(fig)
