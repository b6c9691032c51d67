"""Reconstruction methods: STFM, 3-D TV, plug-and-play, the GS-only baselines, coarse to fine."""
