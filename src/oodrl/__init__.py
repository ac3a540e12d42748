"""oodrl: a benchmark of out-of-distribution detectors for RL trajectories.

Score direction, everywhere in oodrl: a larger detector score means more anomalous.
This module imports nothing heavy so that every pipeline stage starts fast.
"""

__version__ = "0.1.0"
