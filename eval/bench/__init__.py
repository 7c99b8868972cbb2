"""Benchmarks: each prints the ratios and tables it measures in one run (``python -m eval.bench.NAME``;
``make bench`` runs them all). Synthetic scenes come from ``eval.bench.scenes``."""
