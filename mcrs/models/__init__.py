"""The networks: the recurrent agent and its acting policy, the mixers, the state embeddings phi.

Plain ``nn.Module`` / TorchRL modules that know nothing of training: the loss (``mcrs.objectives``) and
the experiment (``mcrs.experiment``) sit above them. From the environment they read only its layouts.
"""

from mcrs.models.acting import AgentStep, EpsilonGreedy, make_acting_policy, recurrent_primer
from mcrs.models.agent import RecurrentAgent
from mcrs.models.embedding_training import EmbeddingTrainer, embedding_loss
from mcrs.models.embeddings import (
    EMBEDDINGS,
    CNNEmbedding,
    FCEmbedding,
    RandomProjection,
    StateEmbedding,
    make_embedding,
)
from mcrs.models.mixers import (
    MIXERS,
    DMAQMixer,
    MixerModule,
    QMixer,
    QPLEXMixer,
    make_mixer,
    mixer_in_keys,
    mixer_module,
)

__all__ = [
    "EMBEDDINGS",
    "MIXERS",
    "AgentStep",
    "CNNEmbedding",
    "DMAQMixer",
    "EmbeddingTrainer",
    "EpsilonGreedy",
    "FCEmbedding",
    "MixerModule",
    "QMixer",
    "QPLEXMixer",
    "RandomProjection",
    "RecurrentAgent",
    "StateEmbedding",
    "embedding_loss",
    "make_acting_policy",
    "make_embedding",
    "make_mixer",
    "mixer_in_keys",
    "mixer_module",
    "recurrent_primer",
]
