"""Held trials: layout, validation, and recorded-trial files (NPZ, CSV, NWB, memmap)."""

from irc_torchrl.data.io import read_trials, write_trials
from irc_torchrl.data.trajectories import TRIAL_KEYS, validate_trials

__all__ = ["TRIAL_KEYS", "read_trials", "validate_trials", "write_trials"]
