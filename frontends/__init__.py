"""Frontends: dataset readers, synthetic scenes and visual odometry.

This package is the root of the pipeline (frontends -> lcd -> slam_backend -> eval), so it also
holds the types, errors, config and registry helpers every other package uses.
"""
