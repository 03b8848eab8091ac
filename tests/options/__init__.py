"""Tests of `dvpmvs/options`: each options module beside its test module."""
