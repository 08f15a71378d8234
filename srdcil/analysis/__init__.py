"""The analysis of finished (or running) runs: what the library's runs wrote, read back and summarised.

* :mod:`~srdcil.analysis.runs`: the one reader of run directories (``config.yaml``, ``result.json``,
  ``metrics.jsonl``);
* :mod:`~srdcil.analysis.stats`: LOCF curves, steps to solve, IQM with bootstrap CIs, performance
  profiles, the stability after the first success;
* :mod:`~srdcil.analysis.figures`: the report's figures;
* :mod:`~srdcil.analysis.report`: ``runs.csv``, ``summary.md``, ``summary.json`` and the report CLI
  (``python -m srdcil.report``);
* :mod:`~srdcil.analysis.plots`: figures and probes of training checkpoints and run curves, and their
  CLI (``python -m srdcil.plots``);
* :mod:`~srdcil.analysis.task_success`: the task's own success, SR-DCIL runs beside a goal-free baseline
  (``python -m srdcil.analysis.task_success``);
* :mod:`~srdcil.analysis.fetch_diagnosis`: why a Fetch run stalls (``python -m
  srdcil.analysis.fetch_diagnosis``).

The library never imports this package; it imports the library (checkpoints are rebuilt by
:func:`srdcil.policy.load_checkpoint_agent`).
"""
