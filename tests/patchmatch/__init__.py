"""Tests of `dvpmvs/patchmatch`."""
