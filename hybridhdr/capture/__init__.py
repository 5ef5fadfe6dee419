"""Capture: read and write hybrid recordings in every supported event format; record live data.

Readers and writers are reached through :func:`hybridhdr.read`, :func:`hybridhdr.open_reader`
and :func:`hybridhdr.open_writer`; the formats live in :mod:`hybridhdr.capture.formats`.

Live capture (``docs/capture.md``): sources (:mod:`.sources`), the crash-safe :class:`Recorder` and
:func:`recover` (:mod:`.recorder`), trigger synchronisation :func:`sync_frames` (:mod:`.sync`),
USB device listing :func:`list_devices` (:mod:`.devices`), the OAK backend
(:mod:`.depthai_backend`), the Prophesee backend (:mod:`.prophesee_backend`) and dataset sessions
(:mod:`.session`). These names are imported lazily, so ``import hybridhdr`` stays light.
"""

from ..io import FORMAT_DESCRIPTIONS, detect_format, open_reader, open_writer, read, write

_LAZY = {
    "EventSource": "sources", "FrameSource": "sources", "FrameItem": "sources",
    "ReplayEventSource": "sources", "ReplayFrameSource": "sources", "SyntheticEventSource": "sources",
    "Recorder": "recorder", "RecorderStats": "recorder", "recover": "recorder",
    "sync_frames": "sync", "sync_recording": "sync", "SyncReport": "sync",
    "list_devices": "devices", "NoDeviceFound": "devices",
    "DepthaiFrameSource": "depthai_backend", "PropheseeEventSource": "prophesee_backend",
    "create_session": "session", "verify_session": "session",
}

__all__ = ["FORMAT_DESCRIPTIONS", "detect_format", "open_reader", "open_writer", "read", "write", *_LAZY]


def __getattr__(name):
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib
    return getattr(importlib.import_module(f"{__name__}.{mod}"), name)
