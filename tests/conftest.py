"""Test-session settings."""

import torch
from hypothesis import settings

# The suite steps small batches: one thread avoids thread start-up and contention costs on shared 2-core
# machines, where the second thread makes small ops slower, not faster.
torch.set_num_threads(1)

# Property tests draw the same examples on every run, so CI is reproducible; run with
# `--hypothesis-profile=explore` to draw new random examples.
settings.register_profile("ci", derandomize=True, deadline=None)
settings.register_profile("explore", deadline=None)
settings.load_profile("ci")
