"""Reconstruction: baselines, 3-D TV, STFM, one shared solver loop, metrics and outputs."""
