"""Evaluation: the ``symbio`` CLI, metrics, benchmarks and the paper's experiments."""
