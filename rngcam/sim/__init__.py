"""Simulation: ground-truth scenes (rngcam.sim.scenes), the static targets mock cameras show for
calibration (rngcam.sim.targets) and simulated capture bundles (rngcam.sim.simulate)."""
