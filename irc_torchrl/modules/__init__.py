"""Policies, value networks and action likelihoods (mirrors ``torchrl.modules``)."""

from irc_torchrl.modules.actor_critic import (
    FeaturePolicy,
    censored_action_model,
    make_actor,
    make_critic,
)
from irc_torchrl.modules.factorised_q import FactorisedQ
from irc_torchrl.modules.lapse import Lapse
from irc_torchrl.modules.likelihood import BoltzmannActionModel, CensoredGaussianActionModel
from irc_torchrl.modules.pursuit import BeliefPursuit

__all__ = [
    "BeliefPursuit",
    "BoltzmannActionModel",
    "CensoredGaussianActionModel",
    "FactorisedQ",
    "FeaturePolicy",
    "Lapse",
    "censored_action_model",
    "make_actor",
    "make_critic",
]
