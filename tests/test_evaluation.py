"""The public chained evaluation (``srdcil.evaluation.evaluate_chain``) on a scripted point env."""
import torch
from tensordict.nn import TensorDictModule
from torchrl.envs import TransformedEnv

from point_env import PointEnv
from srdcil.evaluation import evaluate_chain
from srdcil.transforms import GoalSequenceTransform

GOALS = torch.tensor([[0.5, 0.0], [1.0, 0.0], [1.0, 0.5]])


def _greedy(step):
    """Goal-conditioned scripted policy: move towards the current goal, at most ``step`` per axis."""
    return TensorDictModule(lambda o, g: (g - o).clamp(-step, step), in_keys=["observation", "desired_goal"],
                            out_keys=["action"])


def _env(t_max=4):
    return TransformedEnv(PointEnv(dim=2), GoalSequenceTransform(GOALS, 0.1, t_max).set_keys(goal="desired_goal"))


def test_a_policy_that_follows_the_goals_solves_the_chain():
    m, rollout = evaluate_chain(_env(), _greedy(0.25))
    assert m == {"goals_reached": 3, "chain_success": 1.0, "strict_chain_success": 1.0, "n_goals": 3, "steps": 6}
    assert bool(rollout["next", "terminated"][-1])


def test_a_slow_policy_times_out_on_the_first_goal():
    m, rollout = evaluate_chain(_env(t_max=4), _greedy(0.05))  # needs 8 steps to the first goal, has 4
    assert m["goals_reached"] == 0 and m["chain_success"] == 0.0 and m["steps"] == 4
    assert bool(rollout["next", "truncated"][-1])
