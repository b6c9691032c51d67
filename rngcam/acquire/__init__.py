"""Acquisition: cameras (GenTL, pylon, physics-based mock), the SCPI trigger generator, capture."""
