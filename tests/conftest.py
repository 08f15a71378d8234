import os

os.environ.setdefault("WANDB_MODE", "disabled")
os.environ.setdefault("MUJOCO_GL", "egl")

import torch

# One thread: on this 2-core shared machine, two OpenMP threads collapse when the other core is busy.
torch.set_num_threads(1)
