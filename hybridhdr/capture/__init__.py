"""Capture: live data in, recordings out — event/frame sources (file replay, OAK, Prophesee),
USB discovery, trigger synchronisation, the crash-safe recorder, dataset sessions.

File formats (reading, writing, detection) are :mod:`hybridhdr.formats`.

Live capture (``docs/capture.md``): sources (:mod:`.sources`), the crash-safe :class:`Recorder` and
:func:`recover` (:mod:`.recorder`), trigger synchronisation :func:`sync_frames` (:mod:`.sync`),
USB device listing :func:`list_devices` (:mod:`.devices`), the OAK backend
(:mod:`.depthai_backend`), the Prophesee backend (:mod:`.prophesee_backend`) and dataset sessions
(:mod:`.session`).
"""

from .depthai_backend import DepthaiFrameSource
from .devices import NoDeviceFound, list_devices
from .prophesee_backend import PropheseeEventSource
from .recorder import Recorder, RecorderStats, recover
from .session import create_session, verify_session
from .sources import (EventSource, FrameItem, FrameSource, ReplayEventSource, ReplayFrameSource,
                      SyntheticEventSource)
from .sync import SyncReport, sync_frames, sync_recording

__all__ = [
    "EventSource", "FrameSource", "FrameItem", "ReplayEventSource", "ReplayFrameSource", "SyntheticEventSource",
    "Recorder", "RecorderStats", "recover", "sync_frames", "sync_recording", "SyncReport",
    "list_devices", "NoDeviceFound", "DepthaiFrameSource", "PropheseeEventSource", "create_session", "verify_session",
]
