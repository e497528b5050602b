"""Offline BIM stage: read IFC, build the occupancy grid, rooms and the floor-room-object prior."""
