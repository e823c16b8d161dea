"""The method: captures, model, rendering, training, relighting, meshes, evaluation, command line."""

import os

# OpenMP threads that find no work sleep instead of spinning (libgomp reads this once, when
# torch loads it, so it is set here, before anything imports torch). With the default spin, a
# 2-thread training step on a machine where another process holds one of the two cores took 8x
# the 1-thread step (320x180, 60k Gaussians: 1.66 s against 0.21 s); passive, the same as one
# thread, and 0-13% slower than the spinning default on an idle machine (docs/design.md 5.12).
# A value the user set is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__all__: list[str] = []
