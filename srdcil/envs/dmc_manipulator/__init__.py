"""The DeepMind Control Suite's ``manipulator`` / ``bring_ball`` task, single-reset (``env.name=dmc_manipulator``).

* :mod:`.core`: the fixed start state, the observation / achieved-goal layout and the suite's success test
  (plain numpy on a dm_control ``Physics``);
* :mod:`.env`: :class:`~.env.ManipulatorBringBallEnv`, a subclass of torchrl's ``DMControlEnv``, and
  :func:`~.env.make_dmc_manipulator_env` (``batch_size=[n]`` through a ``SerialEnv``);
* :mod:`.task`: the :class:`srdcil.envs.base.Task`;
* :mod:`.scripted_demo`: the IK-scripted demonstration (``srdcil/data/dmc_manipulator_demo.npz``).

Nothing here imports dm_control at import time: it is imported where a suite env is built.
"""
