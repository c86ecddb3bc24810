"""Inverse Rational Control as a native TorchRL pipeline."""

from irc_torchrl.theta import Parameter, ThetaSpace

__version__ = "0.1.0"
__all__ = ["Parameter", "ThetaSpace", "__version__"]
