"""Plain functions that assemble the parts: Algorithm 1, agent simulation, Algorithm 2.

The experiment runners (:mod:`~irc_torchrl.algorithms.demo`,
:mod:`~irc_torchrl.algorithms.recovery`, :mod:`~irc_torchrl.algorithms.ensemble`) read the
configuration classes and are imported from their modules.
"""

from irc_torchrl.algorithms.dp import greedy_returns, optimal_values
from irc_torchrl.algorithms.fit import FitResult, fit_theta
from irc_torchrl.algorithms.qiteration import QIterationConfig, train_factorised_q
from irc_torchrl.algorithms.simulate import boltzmann_policy, simulate_agents

__all__ = [
    "FitResult",
    "QIterationConfig",
    "boltzmann_policy",
    "fit_theta",
    "greedy_returns",
    "optimal_values",
    "simulate_agents",
    "train_factorised_q",
]
