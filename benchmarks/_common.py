"""Helpers shared by the benchmark scripts: compose a recipe config without running hydra's CLI."""
from __future__ import annotations

from pathlib import Path

from hydra import compose, initialize_config_dir

import srdcil.config  # noqa: F401  (registers the typed schema the recipe configs extend)

CONFIG_DIR = Path(__file__).resolve().parents[1] / "recipes" / "config"


def recipe_config(name: str, overrides: list[str] = ()):
    """The recipe config with ``overrides``; fp32 unless they say otherwise (the benchmarks compare against
    fp32 updates, and their figures must not depend on whether this CPU has native bf16)."""
    overrides = list(overrides)
    if not any(o.startswith("precision=") for o in overrides):
        overrides.insert(0, "precision=fp32")
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(config_name=name, overrides=overrides)
