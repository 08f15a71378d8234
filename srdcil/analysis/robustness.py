"""How far from its single start state does a policy still work? Success rate vs start-state noise.

    python -m srdcil.analysis.robustness POLICY... --sigmas 0 0.05 0.1 0.2 --episodes 50 --out robustness.png

Each policy file (``policy_best.pt``) is evaluated with :func:`srdcil.evaluate.evaluate_policy` at each
noise level (the task's own perturbation of s_0: on the maze N(0, sigma^2) on x, y and heading), seeded.
Writes the figure and, beside it, a JSON with every rate and its Wilson 95 % interval.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from srdcil.cli import command

__all__ = ["robustness", "main"]


def robustness(paths, sigmas, episodes: int, seed: int = 0) -> dict:
    from srdcil.evaluate import evaluate_policy
    from srdcil.policy import load_policy

    out = {}
    for path in paths:
        pol = load_policy(path)
        out[str(path)] = {"env": pol.task.name, "env_steps": pol.env_steps, "levels": [
            {k: v for k, v in evaluate_policy(pol, episodes, start_noise=s, seed=seed)["summary"].items()
             if k not in ("policy", "env")} for s in sigmas]}
    return out


# what each task's start_noise perturbs (srdcil/envs/*/task.py)
_NOISE_ON = {"dubins": "x, y in maze units; heading in rad", "fetch": "the object's x, y, metres",
             "dmc_manipulator": "the ball's x, metres"}


def _plot(res: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.6, 3.8))
    for i, (path, r) in enumerate(res.items()):
        s = [lv["start_noise"] for lv in r["levels"]]
        y = [lv["chain_success_rate"] for lv in r["levels"]]
        lo = [max(0.0, lv["chain_success_rate"] - lv["chain_success_ci95"][0]) for lv in r["levels"]]  # rounded CIs
        hi = [max(0.0, lv["chain_success_ci95"][1] - lv["chain_success_rate"]) for lv in r["levels"]]
        name = Path(path).parent.name or Path(path).stem
        ax.errorbar([x + 0.002 * i for x in s], y, yerr=[lo, hi], marker="o", ms=3, lw=1, capsize=2, label=name)
    envs = {r.get("env") for r in res.values()}
    what = _NOISE_ON.get(envs.pop(), "the task's own perturbation") if len(envs) == 1 else "each task's own perturbation"
    ax.set_xlabel(f"start-state noise sigma ({what})")
    ax.set_ylabel("chain success rate (95 % CI)")
    ax.set_ylim(-0.03, 1.03)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


@command
def main(argv=None) -> dict:
    p = argparse.ArgumentParser(prog="python -m srdcil.analysis.robustness", description=__doc__.split("\n\n")[0])
    p.add_argument("policies", nargs="+", type=Path)
    p.add_argument("--sigmas", nargs="+", type=float, default=[0.0, 0.05, 0.1, 0.2])
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("robustness.png"))
    p.add_argument("--debug", action="store_true", help="tracebacks for user errors")
    a = p.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    a.out.parent.mkdir(parents=True, exist_ok=True)  # before the evaluations, not after them
    res = robustness(a.policies, a.sigmas, a.episodes, a.seed)
    _plot(res, a.out)
    a.out.with_suffix(".json").write_text(json.dumps(res, indent=1) + "\n")
    for path, r in res.items():
        print(path, " ".join(f"sigma {lv['start_noise']:g}: {lv['chain_success_rate']:.2f}" for lv in r["levels"]))
    return res


if __name__ == "__main__":
    main()
