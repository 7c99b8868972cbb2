"""Errors of the pose-graph backend."""

from __future__ import annotations

from frontends.errors import SymbioError


class PoseGraphError(SymbioError):
    """A pose-graph call was given invalid input (bad transform, covariance or keyframe id).

    The graph is left exactly as it was before the call.
    """
