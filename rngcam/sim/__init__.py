"""Simulation: ground-truth scenes (rngcam.sim.scenes) and simulated capture bundles (rngcam.sim.simulate)."""
