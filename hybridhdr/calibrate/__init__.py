"""Calibrate: stereo rig, camera response functions, noise profiles, HDR references (see issue 6)."""

__all__: list[str] = []
