"""The report's figures (matplotlib, Agg backend): ``ablation.png``, ``iqm.png``, ``profiles.png``.

* :func:`plot_ablation`, in the style of the paper's Fig. 4: (a) chain success averaged over the seeds
  of a method, band mean +- std/2; (b) the fraction of seeds solved by t; (c) normalised goals reached,
  mean +- std/2. (a) and (c) may first smooth each run over its last evaluations.
* :func:`plot_iqm`: IQM of normalised goals at each budget with its bootstrap CI.
* :func:`plot_profiles`: performance profiles at the last budget with their bootstrap bands.

Each method keeps its colour and line style across the figures (:func:`method_styles`).
"""
from __future__ import annotations

import numpy as np

from srdcil.analysis.stats import LOCF_RULE, mean_band, solved_fraction

__all__ = ["fmt_steps", "method_colors", "method_styles", "plot_ablation", "plot_iqm", "plot_profiles"]


def fmt_steps(x) -> str:
    """Env steps as the tables and figures write them: ``25k``, ``500``; None is "not reached"."""
    if x is None:
        return "not reached"
    x = float(x)
    return f"{x / 1000:g}k" if x >= 1000 else f"{x:g}"


def method_colors(methods) -> dict:
    """A tab10 colour per method, in order."""
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return {m: cmap(i % 10) for i, m in enumerate(methods)}


def method_styles(methods) -> dict:
    """Line style and width per method, so that curves lying on top of each other stay visible."""
    ls = ("-", "--", "-.", ":")
    n = len(methods)
    return {m: dict(ls=ls[i % 4], lw=2.6 - 1.4 * i / max(n - 1, 1)) for i, m in enumerate(methods)}


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_ablation(by_method: dict, grid, path, budget, smooth: int = 1) -> None:
    """``{method: runs}`` on the env-step ``grid`` (x axis up to ``budget``), as the module docstring says."""
    plt = _pyplot()
    colors, styles = method_colors(by_method), method_styles(list(by_method))
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8))
    x = np.asarray(grid, float) / 1000
    for m, runs in by_method.items():
        c, label = colors[m], f"{m} (n={len(runs)})"
        for ax, field in ((axes[0], "chain"), (axes[2], "goals_norm")):
            mean, half, _ = mean_band(runs, grid, field, smooth)
            ax.plot(x, mean, color=c, label=label, **styles[m])
            ax.fill_between(x, mean - half, mean + half, color=c, alpha=0.18, lw=0)
        axes[1].plot(x, solved_fraction(runs, grid), color=c, label=label, **styles[m])
    per = f"\neach run's mean over its last {smooth} evaluations" if smooth > 1 else ""
    titles = ("(a) success rate (final goal reached)" + per, "(b) fraction of seeds solved by t",
              "(c) normalised goals reached" + per)
    ylabels = ("chain success, mean ± std/2", "fraction of seeds", "goals reached / n goals, mean ± std/2")
    for ax, t, yl in zip(axes, titles, ylabels):
        ax.set_title(t, fontsize=11)
        ax.set_xlabel("env steps (thousands)")
        ax.set_ylabel(yl)
        ax.set_xlim(0, budget / 1000)
        ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 7), frameon=False, fontsize=10,
               bbox_to_anchor=(0.5, 0.07))
    fig.text(0.5, 0.015, LOCF_RULE, ha="center", va="bottom", fontsize=8.5, color="0.3", wrap=True)
    fig.tight_layout(rect=(0, 0.16, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_iqm(iqm: dict, budgets, path) -> None:
    """``iqm[method][budget] = (point, lo, hi)`` (or None): one group of error bars per budget."""
    plt = _pyplot()
    methods = list(iqm)
    colors = method_colors(methods)
    fig, ax = plt.subplots(figsize=(max(7, 1.6 * len(budgets) + 0.5 * len(methods)), 4.6))
    width = 0.8 / max(len(methods), 1)
    for i, m in enumerate(methods):
        xs, ys, lo, hi = [], [], [], []
        for j, b in enumerate(budgets):
            est = iqm[m].get(b)
            if est is None:
                continue
            xs.append(j - 0.4 + width * (i + 0.5))
            ys.append(est[0])
            lo.append(est[0] - est[1])
            hi.append(est[2] - est[0])
        ax.errorbar(xs, ys, yerr=[lo, hi], fmt="o", color=colors[m], capsize=3, ms=5, lw=1.5, label=m)
    ax.set_xticks(range(len(budgets)), [f"{fmt_steps(b)} env steps" for b in budgets])
    for j in range(1, len(budgets)):
        ax.axvline(j - 0.5, color="0.85", lw=0.8)
    ax.set_ylim(-0.03, 1.05)
    ax.set_ylabel("IQM of normalised goals reached")
    ax.set_title("IQM of normalised goals reached at fixed budgets (95% stratified-bootstrap CI, LOCF)",
                 fontsize=10.5)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_profiles(taus, profiles: dict, n_runs: dict, budget, path) -> None:
    """``profiles[method] = (profile, lo, hi)`` over ``taus``, at ``budget``; ``n_runs[method]`` in the legend."""
    plt = _pyplot()
    colors, styles = method_colors(list(profiles)), method_styles(list(profiles))
    fig, ax = plt.subplots(figsize=(7.5, 4.6))
    for m, (p, lo, hi) in profiles.items():
        ax.plot(taus, p, color=colors[m], label=f"{m} (n={n_runs[m]})", drawstyle="steps-post", **styles[m])
        ax.fill_between(taus, lo, hi, color=colors[m], alpha=0.15, lw=0, step="post")
    ax.set_xlabel(r"normalised goals reached threshold $\tau$")
    ax.set_ylabel(r"fraction of runs with score > $\tau$")
    ax.set_title(f"Performance profiles at {fmt_steps(budget)} env steps (95% bootstrap bands, LOCF)",
                 fontsize=10.5)
    ax.set_xlim(0, 1)
    ax.set_ylim(-0.03, 1.03)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
