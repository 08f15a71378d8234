"""The authors' Dubins maze: the env (:mod:`.env`), its task for the training loop (:mod:`.task`)
and the kinodynamic RRT that made the shipped demonstration (:mod:`.rrt`)."""
from .env import *  # noqa: F401,F403
from .env import __all__  # noqa: F401
