"""Long-horizon world-model evaluation: rollouts, metrics vs horizon, and the report.

Modules:
  ``harness``: :func:`evaluate_videos` (plain arrays in, results out) and :func:`rollout_videos`.
  ``horizon``: per-frame and windowed metric-vs-horizon curves.
  ``results``: :class:`EvalResults` / :class:`ModelResult`.
  ``report``: ``report.md`` / ``report.html`` with tables, plots, strips and GIFs.
"""
