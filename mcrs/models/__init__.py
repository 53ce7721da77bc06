"""The networks: the recurrent agent and its acting policy, the mixers and the state embeddings phi.

They know nothing of training, and read only the layouts of the environment."""

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
