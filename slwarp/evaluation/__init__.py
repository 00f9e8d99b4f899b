"""Evaluation and outputs: depth metrics (metrics) and pictures (viz)."""
