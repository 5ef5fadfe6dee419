"""Capture: live data in, recordings out — event/frame sources (file replay, OAK, Prophesee),
USB discovery, trigger synchronisation, the crash-safe recorder, dataset sessions.

File formats (reading, writing, detection) are :mod:`hybridhdr.formats`.

Live capture (``docs/capture.md``): sources (:mod:`.sources`), the crash-safe :class:`Recorder` and
:func:`recover` (:mod:`.recorder`), trigger synchronisation :func:`sync_frames` (:mod:`.sync`),
USB device listing :func:`list_devices` (:mod:`.devices`), the OAK backend
(:mod:`.depthai_backend`), the Prophesee backend (:mod:`.prophesee_backend`) and dataset sessions
(:mod:`.session`). These names are imported lazily, so ``import hybridhdr`` stays light.
"""

_LAZY = {
    "EventSource": "sources", "FrameSource": "sources", "FrameItem": "sources",
    "ReplayEventSource": "sources", "ReplayFrameSource": "sources", "SyntheticEventSource": "sources",
    "Recorder": "recorder", "RecorderStats": "recorder", "recover": "recorder",
    "sync_frames": "sync", "sync_recording": "sync", "SyncReport": "sync",
    "list_devices": "devices", "NoDeviceFound": "devices",
    "DepthaiFrameSource": "depthai_backend", "PropheseeEventSource": "prophesee_backend",
    "create_session": "session", "verify_session": "session",
}

__all__ = [*_LAZY]


def __getattr__(name):
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib
    return getattr(importlib.import_module(f"{__name__}.{mod}"), name)
