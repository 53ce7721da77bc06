"""Test-session settings."""

import torch

# The suite steps small batches: one thread avoids thread start-up and contention costs on shared 2-core
# machines, where the second thread makes small ops slower, not faster.
torch.set_num_threads(1)
