"""Plain functions that assemble the parts: Algorithm 1, agent simulation, Algorithm 2.

The experiment runners (:func:`~irc_torchrl.algorithms.demo.run_demo`,
:func:`~irc_torchrl.algorithms.recovery.recover_agents`,
:func:`~irc_torchrl.algorithms.recover2d.recover_firefly2d`) read the configuration classes of
:mod:`irc_torchrl.config`, which imports this package, so they are imported from their modules.
"""

from irc_torchrl.algorithms.calibration import (
    Calibration,
    calibrate_intervals,
    interval_pivots,
    simulate_at_fits,
)
from irc_torchrl.algorithms.dp import greedy_returns, optimal_values
from irc_torchrl.algorithms.ensemble import (
    critic_slices,
    evaluate_policy,
    load_ensemble_critic,
    load_ensemble_policy,
    stop_sharpness,
    theta_sensitivity,
    train_ensemble,
)
from irc_torchrl.algorithms.fit import (
    FitResult,
    expected_intervals,
    fit_theta,
    particle_check,
    profile_intervals,
    score_check,
)
from irc_torchrl.algorithms.qiteration import QIterationConfig, train_factorised_q
from irc_torchrl.algorithms.simulate import (
    boltzmann_policy,
    first_trial_mask,
    motor_noise_policy,
    simulate_agents,
)

__all__ = [
    "Calibration",
    "FitResult",
    "QIterationConfig",
    "boltzmann_policy",
    "calibrate_intervals",
    "critic_slices",
    "evaluate_policy",
    "expected_intervals",
    "first_trial_mask",
    "fit_theta",
    "greedy_returns",
    "interval_pivots",
    "load_ensemble_critic",
    "load_ensemble_policy",
    "motor_noise_policy",
    "optimal_values",
    "particle_check",
    "profile_intervals",
    "score_check",
    "simulate_agents",
    "simulate_at_fits",
    "stop_sharpness",
    "theta_sensitivity",
    "train_ensemble",
    "train_factorised_q",
]
