"""Benchmark harness: datasets, metrics, reports and leaderboard submissions.

Installed as ``dvpmvs.evaluation``. It knows datasets; the core (``dvpmvs``) does not import it.
"""
