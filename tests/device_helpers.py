"""The torch devices the tests run on: the CPU always, and CUDA where this machine has it (CI has none, so
the CUDA cases run where a GPU is lent: docs/TRAINING.md, "On a GPU")."""

from __future__ import annotations

import torch


def available_devices() -> list[str]:
    return ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
