"""The GTSAM pose-graph backend (see the issue tracker for the plan)."""
