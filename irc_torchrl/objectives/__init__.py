"""The inverse objective and its intervals (mirrors ``torchrl.objectives``)."""

from irc_torchrl.objectives.fisher import Intervals, batched_hessian, fisher_intervals
from irc_torchrl.objectives.inverse import InverseRationalLoss
from irc_torchrl.objectives.marginal import marginal_filter, particle_log_likelihood

__all__ = [
    "InverseRationalLoss",
    "Intervals",
    "batched_hessian",
    "fisher_intervals",
    "marginal_filter",
    "particle_log_likelihood",
]
