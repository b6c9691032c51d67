"""Sweeps and batches of reconstructions: held-out scoring, successive halving, Ray or in-process."""
