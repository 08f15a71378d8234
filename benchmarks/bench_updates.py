"""Updates per second of one SAC update at batch 256, 1 thread.

Compares, on the same networks (srdcil.networks cores) and the same batch:
  plain     hand-written PyTorch SAC update, no V (twin-Q MSBE with the DCIL clipped target, actor loss
            with detached Q weights, one backward, fused Adam, Polyak via torch._foreach_lerp_): the limit
  dcil      DCILUpdater(DCILSACLoss(actor, qvalue))            (vanilla / db variants)
  plain_vc  hand-written SAC-v1 with V and value cloning (same losses as DCILSACLoss with V)
  dcil_vc   DCILUpdater(DCILSACLoss(actor, qvalue, value))     (vc variants)

Methods are timed in interleaved blocks (the machine is shared; interleaving spreads the noise);
each method gets >= --seconds in total; the reported rate is the median over its blocks and the
ratio is the median of the per-round ratios.

    python benchmarks/bench_updates.py [--seconds 3] [--fetch] [--sequential] [--compile]
    python benchmarks/bench_updates.py --device cuda --compile --cudagraphs --bf16 --fetch   # eager/compiled/graph/bf16
"""
from __future__ import annotations

import argparse
import math
import statistics
import time

import torch
from tensordict import TensorDict
from torch.nn import functional as F

from srdcil.networks import make_actor, make_qvalue, make_value
from srdcil.objectives import DCILSACLoss
from srdcil.updater import DCILUpdater

GAMMA, ALPHA, TAU, CLIP = 0.9, 1e-3, 0.005, (0.0, 5.0)


def make_batch(B, obs, goal, N, act, demo_frac=0.2, seed=0):
    g = torch.Generator().manual_seed(seed)
    td = TensorDict(
        observation=torch.randn(B, obs, generator=g), goal=torch.randn(B, goal, generator=g),
        goal_idx=torch.randint(0, N, (B, 1), generator=g), action=torch.rand(B, act, generator=g) * 2 - 1,
        is_demo=torch.rand(B, 1, generator=g) < demo_frac, demo_return=torch.rand(B, 1, generator=g) * 3,
        batch_size=[B],
    )
    td["next"] = TensorDict(
        observation=torch.randn(B, obs, generator=g), goal=torch.randn(B, goal, generator=g),
        goal_idx=torch.randint(0, N, (B, 1), generator=g),
        reward=(torch.rand(B, 1, generator=g) < 0.3).float(),
        terminated=torch.rand(B, 1, generator=g) < 0.05, done=torch.rand(B, 1, generator=g) < 0.1,
        batch_size=[B],
    )
    return td


class PlainSAC:
    """Hand-written SAC update on the bare core networks (no TensorDict, no LossModule)."""

    def __init__(self, dims, hidden, with_value=False, lr=1e-3, device="cpu"):
        obs, goal, N, act = dims
        self.actor = make_actor(obs, goal, N, act, hidden).module[0].module.to(device)  # GaussianPolicyNet
        self.q = make_qvalue(obs, goal, N, act, hidden).module.to(device)  # TwinQ
        self.v = make_value(obs, goal, N, hidden).module.to(device) if with_value else None
        nets = [self.q] + ([self.v] if with_value else [])
        self.srcs = [p for n in nets for p in n.parameters()]
        self.tgts = [p.detach().clone() for p in self.srcs]
        nq = len(list(self.q.parameters()))
        self.q_tgt, self.v_tgt = self.tgts[:nq], self.tgts[nq:]
        params = list(self.actor.parameters()) + self.srcs
        self.opt = torch.optim.Adam(params, lr=lr, fused=True)

    def sample(self, o, g, i):
        loc, scale = self.actor(o, g, i)
        eps = torch.randn_like(loc)
        u = loc + scale * eps
        logp = (-0.5 * eps.pow(2) - scale.log() - 0.5 * math.log(2 * math.pi)
                - 2.0 * (math.log(2.0) - u - F.softplus(-2.0 * u))).sum(-1, keepdim=True)
        return torch.tanh(u), logp

    def step(self, t):
        o, g, i, a = t["o"], t["g"], t["i"], t["a"]
        r, notterm = t["r"], t["nt"]
        with torch.no_grad():
            if self.v is None:
                a2, _ = self.sample(t["o2"], t["g2"], t["i2"])
                boot = self.q.q_all(t["o2"], t["g2"], t["i2"], a2, self.q_tgt).amin(0)
            else:
                boot = self.v(t["o2"], t["g2"], t["i2"], params=self.v_tgt)
            y = r + GAMMA * notterm * boot.clamp(*CLIP)
        q = self.q.q_all(o, g, i, a)
        a_pi, logp = self.sample(o, g, i)
        q_pi = self.q.q_all(o, g, i, a_pi, [p.detach() for p in self.q.parameters()]).amin(0)
        if self.v is None:
            lq = (q - y).pow(2).sum(0).mean()
            la = (ALPHA * logp - q_pi).mean()
            total = lq + la
        else:
            train, demo = t["train"], t["demo"]
            nt, nd = t["n_train"], t["n_demo"]
            lq = ((q - y).pow(2).sum(0) * train).sum() / nt
            la = ((ALPHA * logp - q_pi) * train).sum() / nt
            v = self.v(o, g, i)
            vt = (q_pi - ALPHA * logp).detach()
            lv = ((v - vt).pow(2) * train).sum() / nt
            lvc = ((v - t["ret"]).pow(2) * demo).sum() / nd
            total = lq + la + lv + lvc
        total.backward()
        self.opt.step()
        self.opt.zero_grad(set_to_none=True)
        torch._foreach_lerp_(self.tgts, self.srcs, TAU)
        return total.detach()


def plain_inputs(td):
    demo = td["is_demo"].float()
    return {
        "o": td["observation"], "g": td["goal"], "i": td["goal_idx"], "a": td["action"],
        "o2": td["next", "observation"], "g2": td["next", "goal"], "i2": td["next", "goal_idx"],
        "r": td["next", "reward"], "nt": (~td["next", "terminated"]).float(),
        "train": 1 - demo, "demo": demo, "ret": td["demo_return"],
        "n_train": (1 - demo).sum().clamp_min(1), "n_demo": demo.sum().clamp_min(1),
    }


def _sync():
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize()


def time_block(fn, seconds):
    n, t0 = 0, time.perf_counter()
    while True:
        fn()
        n += 1
        if n % 8:
            continue
        _sync()  # GPU work is asynchronous: count only finished updates
        dt = time.perf_counter() - t0
        if dt >= seconds:
            return n / dt


def run_size(name, dims, hidden, seconds, sequential=False, compiled=False, B=256, device="cpu",
             cudagraphs=False, bf16=False):
    torch.manual_seed(0)
    obs, goal, N, act = dims
    td = make_batch(B, obs, goal, N, act).to(device)
    pin = plain_inputs(td)
    methods = {}

    def dcil(value=False, **kw):
        v = make_value(obs, goal, N, hidden) if value else None
        loss = DCILSACLoss(make_actor(*dims, hidden), make_qvalue(*dims, hidden), v).to(device)
        return DCILUpdater(loss, **kw)

    plain = PlainSAC(dims, hidden, device=device)
    methods["plain"] = lambda: plain.step(pin)
    up = dcil()
    methods["dcil"] = lambda: up.step(td)
    plain_vc = PlainSAC(dims, hidden, with_value=True, device=device)
    methods["plain_vc"] = lambda: plain_vc.step(pin)
    up_vc = dcil(value=True)
    methods["dcil_vc"] = lambda: up_vc.step(td)
    if sequential:
        up_s = dcil(mode="sequential")
        methods["dcil_sequential"] = lambda: up_s.step(td)
    if bf16:
        from srdcil.updater import bf16_supported

        print(f"bf16_native_{name}: {int(bf16_supported(device))} (1 = yes)")
        bf16 = bf16_supported(device)  # emulated bf16 is many times slower than fp32: not timed
    for label, kw, wanted in (("compiled", {"compile": True}, compiled),
                              ("cudagraph", {"cudagraphs": True}, cudagraphs),
                              ("bf16", {"precision": "bf16"}, bf16)):
        if not wanted:
            continue
        up_x = dcil(**kw)
        t0 = time.perf_counter()
        for _ in range(3):
            up_x.step(td)
        _sync()
        print(f"{label}_setup_time_{name}: {time.perf_counter() - t0:.1f} s")
        methods[f"dcil_{label}"] = (lambda u: lambda: u.step(td))(up_x)
    if bf16:  # bf16 in the recipes' update order and with V (value cloning) too
        extra = {"dcil_vc_bf16": dcil(value=True, precision="bf16")}
        if sequential:
            extra["dcil_sequential_bf16"] = dcil(mode="sequential", precision="bf16")
        for k, u in extra.items():
            methods[k] = (lambda u: lambda: u.step(td))(u)
    for fn in methods.values():  # warm-up
        for _ in range(5):
            fn()
    block = 1.0
    rounds = max(3, math.ceil(seconds / block))
    rates = {k: [] for k in methods}
    for _ in range(rounds):
        for k, fn in methods.items():
            rates[k].append(time_block(fn, block))
    for k, r in rates.items():
        print(f"updates_per_s_{k}_{name}: {statistics.median(r):.1f} updates/s")
    pairs = [("dcil", "plain"), ("dcil_vc", "plain_vc")]
    if sequential:
        pairs.append(("dcil_sequential", "plain"))
    if compiled:
        pairs.append(("dcil_compiled", "plain"))
        pairs.append(("dcil_compiled", "dcil"))
    if cudagraphs:
        pairs.append(("dcil_cudagraph", "plain"))
        pairs.append(("dcil_cudagraph", "dcil"))
    if bf16:
        pairs.append(("dcil_bf16", "plain"))
        pairs.append(("dcil_bf16", "dcil"))
        pairs.append(("dcil_vc_bf16", "dcil_vc"))
        if sequential:
            pairs.append(("dcil_sequential_bf16", "dcil_sequential"))
    for a, b in pairs:
        ratio = statistics.median(x / y for x, y in zip(rates[a], rates[b]))
        print(f"ratio_{a}_to_{b}_{name}: {ratio:.2f} x")


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=3.0, help="time per method (>= 3 s)")
    p.add_argument("--fetch", action="store_true", help="also run the Fetch size (slower)")
    p.add_argument("--sequential", action="store_true", help="also time DCILUpdater(mode='sequential')")
    p.add_argument("--compile", action="store_true", help="also time DCILUpdater(compile=True)")
    p.add_argument("--cudagraphs", action="store_true",
                   help="also time DCILUpdater(cudagraphs=True) (CUDA-graph capture; needs --device cuda)")
    p.add_argument("--bf16", action="store_true",
                   help="also time DCILUpdater(precision='bf16') (only where bf16 is native)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    if args.cudagraphs and not str(args.device).startswith("cuda"):
        p.error("--cudagraphs captures CUDA graphs: use it with --device cuda")
    torch.set_num_threads(args.threads)
    print(f"torch_threads: {torch.get_num_threads()} threads")
    kw = dict(sequential=args.sequential, compiled=args.compile, device=args.device, cudagraphs=args.cudagraphs,
              bf16=args.bf16)
    run_size("dubins", (3, 2, 19, 1), (400, 300), args.seconds, **kw)
    if args.fetch:
        run_size("fetch", (268, 6, 7, 9), (512, 512, 512), args.seconds, **kw)


def plain_rate_for_recipe(cfg, seconds: float = 5.0) -> float:
    """Plain-PyTorch update rate (the limit) for the networks and batch of a recipe config."""
    from srdcil.tasks import make_task
    from srdcil.methods import get_method

    task = make_task(cfg.env)
    dims = (task.obs_dim, task.goals.goals.shape[-1], len(task.goals), task.action_dim)
    hidden = tuple(cfg.network.hidden)
    vc = get_method(cfg.method).value_cloning
    torch.manual_seed(0)
    td = make_batch(int(cfg.optim.batch_size), *dims).to(cfg.device)
    pin = plain_inputs(td)
    plain = PlainSAC(dims, hidden, with_value=vc, device=cfg.device)
    for _ in range(5):
        plain.step(pin)
    return statistics.median(time_block(lambda: plain.step(pin), 1.0) for _ in range(max(3, int(seconds))))


if __name__ == "__main__":
    main()
