"""One physics package for the mock cameras, the simulator and the reconstruction."""
