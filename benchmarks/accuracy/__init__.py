"""Accuracy: the estimators against the truth of the simulated sensor, and the trade of speed against it."""
