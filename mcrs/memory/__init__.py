"""The episodic buffer D_E: compact bit-exact states, an exact grid index, and Algorithm 1 in batch."""

from mcrs.memory.codec import StateCodec
from mcrs.memory.episodic import EpisodicMemory, InsertStats
from mcrs.memory.index import GridIndex, squared_distance
from mcrs.memory.resolution import discounted_returns
from mcrs.memory.transform import EpisodicLookup

__all__ = [
    "EpisodicLookup",
    "EpisodicMemory",
    "GridIndex",
    "InsertStats",
    "StateCodec",
    "discounted_returns",
    "squared_distance",
]
