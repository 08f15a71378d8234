"""Hydra entry point shared by the recipe scripts in ``recipes/`` (one config file each).

Before hydra starts, the command line is checked: the overrides must parse and compose, and every
config they give -- every job of a multirun, with the experiment's sweep -- must pass
:func:`srdcil.config.validate`; else one line ``srdcil: error: ...`` and exit code 2 (hydra's own
errors included), before any job starts. During a run, a user error
(:class:`srdcil.errors.UserError`: config, demonstration, checkpoint, run dir, a failed write, a
non-finite loss) prints one line and exits with code 2, without a traceback (``debug=true`` shows
it); in a multirun the failing job prints its line and the others go on. A run stopped by SIGINT /
SIGTERM exits with 128 + the signal number after writing its checkpoint; Ctrl-C before the run has
started exits with 130.
"""
from __future__ import annotations

import logging
import os
import shutil
import sys
from pathlib import Path

import srdcil.config  # noqa: F401  - registers the typed schema before hydra composes
from srdcil.cli import fail

log = logging.getLogger("srdcil")

_NO_CHECK = ("-h", "--help", "--hydra-help", "--info", "-i", "--cfg", "-c", "--resolve", "--shell-completion",
             "-sc", "--version")


def hydra_main(config_name: str, config_dir: str | Path):
    """A ``main()`` that checks the command line, then runs :func:`srdcil.training.train` through hydra
    on ``config_dir/config_name.yaml``."""
    import hydra

    config_dir = Path(config_dir).resolve()

    @hydra.main(version_base="1.3", config_path=str(config_dir), config_name=config_name)
    def run(cfg) -> None:
        _run_job(cfg)

    def main() -> None:
        argv = sys.argv[1:]
        try:
            if not any(a.split("=")[0] in _NO_CHECK for a in argv):
                precheck(config_name, config_dir, argv)
            run()
        except KeyboardInterrupt:
            print("srdcil: interrupted", file=sys.stderr, flush=True)
            sys.exit(130)

    return main


def _run_job(cfg) -> None:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from srdcil.errors import EXIT_USER_ERROR, UserError
    from srdcil.training import train

    hc = HydraConfig.get()
    run_dir = Path(hc.runtime.output_dir)
    try:
        result = train(cfg, run_dir=run_dir)
    except UserError as e:
        if cfg.debug:
            raise
        _drop_empty_run_dir(run_dir, f"{hc.job.name}.log")
        print(f"srdcil: error: {e}", file=sys.stderr, flush=True)
        if hc.mode == RunMode.MULTIRUN:  # the other jobs of the sweep go on
            return
        sys.exit(EXIT_USER_ERROR)
    if result.get("stop_reason") == "interrupted":
        sys.exit(128 + int(result["signal"]))
    print({k: v for k, v in result.items() if k != "ags_thresholds"})


def precheck(config_name: str, config_dir: Path, argv: list[str]) -> int:
    """Compose and validate every config the command line gives (each job of a multirun); one line
    and exit 2 on the first that fails. Returns the number of configs checked."""
    from hydra import compose, initialize_config_dir
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from srdcil.config import validate
    from srdcil.errors import UserError

    multirun = any(a in ("-m", "--multirun") for a in argv)
    overrides = [a for a in argv if not a.startswith("-")]
    debug, jobs, job = "debug=true" in argv, [], []
    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
        with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
            jobs = _jobs(parsed, config_name, compose) if multirun else [_not_hydra(overrides)]
            for job in jobs:
                validate(compose(config_name=config_name, overrides=job))
    except UserError as e:
        fail(f"job {' '.join(job)}: {e}" if multirun else str(e), debug=debug, exc=e)
    except (HydraException, OmegaConfBaseException, ValueError) as e:
        why = [e] + ([e.__cause__] if e.__cause__ is not None else [])  # hydra wraps OmegaConf's reason
        lines = [ln.strip() for x in why for ln in str(x).splitlines()[:1] if ln.strip()]
        fail(": ".join(lines) or type(e).__name__, debug=debug, exc=e)
    return len(jobs)


def _not_hydra(overrides: list[str]) -> list[str]:
    """The overrides of the run's own config (hydra.* and hydra/<group>= ones configure hydra)."""
    return [o for o in overrides if not o.lstrip("+~").startswith("hydra")]


def _jobs(parsed, config_name: str, compose) -> list[list[str]]:
    """The override lists of a multirun's jobs: the config's ``hydra.sweeper.params`` (e.g. an
    experiment's grid) and the command line's sweeps, expanded as hydra's basic sweeper does."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    plain = [o.input_line for o in parsed if not o.is_sweep_override()]
    base = compose(config_name=config_name, overrides=plain, return_hydra_config=True)
    params = base.hydra.sweeper.get("params") or {}
    given = {o.get_key_element() for o in parsed}
    extra = [f"{k}={v}" for k, v in params.items() if k not in given]
    allp = list(parsed) + OverridesParser.create().parse_overrides(extra)
    batches = BasicSweeper.split_arguments(allp, None)[0]
    return [_not_hydra(job) for job in batches]


def _drop_empty_run_dir(run_dir: Path, log_name: str) -> None:
    """Remove a run dir that holds nothing but hydra's own files (the run never started)."""
    if not run_dir.is_dir():
        return
    own = {".hydra", log_name, ".lock"}
    if all(p.name in own for p in run_dir.iterdir()):
        shutil.rmtree(run_dir, ignore_errors=True)
        try:
            os.rmdir(run_dir.parent)  # the env's folder under runs/, if this was its only run
        except OSError:
            pass
