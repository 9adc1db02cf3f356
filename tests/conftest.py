"""Test-wide settings: one torch/BLAS thread (oversubscription made SAC seven times slower on 2 cores)."""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

try:
    import torch

    torch.set_num_threads(1)
except ImportError:  # torch is a hard dependency, but keep collection working without it
    pass
