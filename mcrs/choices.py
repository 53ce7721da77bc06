"""The choices of the training config, each list written once.

The schema's enums (:mod:`mcrs.experiment.schema`) and the modules that implement the choices (the mixers,
the embeddings, the memory's index, the replay, the incentives, the loggers) read them here. This module
imports nothing but the standard library, so composing and checking a config loads neither torch nor
TorchRL, and a mistyped choice is refused in a second.
"""

from __future__ import annotations

#: algo.mixer: qmix (monotonic hypernetwork mixer) | vdn (sum of the agents' values) | qplex (duplex dueling)
MIXERS = ("qmix", "vdn", "qplex")
#: algo.memory.embedding, the state embedding phi: random (EMC's projection) | fc (SEMU) | cnn (CNN-SEMU)
EMBEDDINGS = ("random", "fc", "cnn")
#: algo.memory.delta_rule: volume (delta is eq. 35's key-space volume per entry) | literal (the tolerance)
DELTA_RULES = ("volume", "literal")
#: algo.memory.neighbourhood: ball (Euclidean ball of radius delta) | box (EMU's box of half-side delta)
SHAPES = ("ball", "box")
#: algo.time_limit, the horizon T in TD targets: terminal (no bootstrap, as memory returns) | bootstrap
TIME_LIMITS = ("terminal", "bootstrap")
#: algo.incentive, EMU's episodic incentive: none | fixed (a return threshold) | change (the last evaluation)
INCENTIVES = ("none", "fixed", "change")
#: train.optimizer: rmsprop (pymarl's) | adam
OPTIMIZERS = ("rmsprop", "adam")
#: train.collector: single (one process) | multiprocess (TorchRL's MultiSyncCollector over worker processes)
COLLECTORS = ("single", "multiprocess")
#: model.name, the agent network: gru (the shared recurrent agent)
MODEL_NAMES = ("gru",)
#: logger.backend, where metrics go: csv (files in the run) | wandb (Weights & Biases) | tensorboard
LOGGER_BACKENDS = ("csv", "wandb", "tensorboard")
#: logger.wandb_mode: offline (nothing leaves the machine) | online (sent to the wandb server)
WANDB_MODES = ("offline", "online")

__all__ = [
    "COLLECTORS",
    "DELTA_RULES",
    "EMBEDDINGS",
    "INCENTIVES",
    "LOGGER_BACKENDS",
    "MIXERS",
    "MODEL_NAMES",
    "OPTIMIZERS",
    "SHAPES",
    "TIME_LIMITS",
    "WANDB_MODES",
]
