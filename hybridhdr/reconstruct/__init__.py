"""Reconstruct: the Asynchronous Kalman Filter and its baselines (see issue 3)."""

__all__: list[str] = []
