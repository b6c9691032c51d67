"""Acquisition: the rig's values resolved once (`resolve`), one device factory (`factory`: GenTL,
pylon, or the physics-based mock in `mock_backend`), the SCPI trigger generator, capture."""
