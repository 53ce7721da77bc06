"""Losses: the value-factorisation TD loss (QMIX, VDN, QPLEX), a TorchRL ``LossModule``."""

from mcrs.objectives.value_factorisation import ValueFactorisationLoss

__all__ = ["ValueFactorisationLoss"]
