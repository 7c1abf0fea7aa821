"""Robustness: the daemon under faults, hostile neighbours, floods, signals and its unit's restrictions."""
