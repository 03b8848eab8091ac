"""Tests of the benchmark harness (`evaluation/`, installed as `dvpmvs.evaluation`)."""
