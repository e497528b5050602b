"""RGB-D and wheel-odometry simulator over the BIM geometry: world, trajectories, sensors, sequences."""
