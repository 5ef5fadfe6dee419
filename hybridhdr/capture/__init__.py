"""Capture: live data in, recordings out — event/frame sources (file replay, OAK, Prophesee, DAVIS
and DV network streams through dv-processing, Basler/GenICam through pylon), device discovery, trigger synchronisation, the crash-safe recorder, dataset sessions.

File formats (reading, writing, detection) are :mod:`hybridhdr.formats`.

Live capture (``docs/capture.md``): sources (:mod:`.sources`), the crash-safe :class:`Recorder` and
:func:`recover` (:mod:`.recorder`), trigger synchronisation :func:`sync_frames` (:mod:`.sync`),
USB device listing :func:`list_devices` (:mod:`.devices`), the OAK backend
(:mod:`.depthai_backend`), the Prophesee backend (:mod:`.prophesee_backend`) and dataset sessions
(:mod:`.session`).
"""

from .._util.lazy import lazy_exports

# Lazy (PEP 562): the names below load their module on first use, so that building the command
# line's parser (hybridhdr --help) does not import numba and the kernels (a slow start).
_LAZY = {
    'DepthaiFrameSource': '.depthai_backend',
    'NoDeviceFound': '.devices',
    'list_devices': '.devices',
    'PropheseeEventSource': '.prophesee_backend',
    'Recorder': '.recorder',
    'RecorderStats': '.recorder',
    'recover': '.recorder',
    'create_session': '.session',
    'verify_session': '.session',
    'EventSource': '.sources',
    'FrameItem': '.sources',
    'FrameSource': '.sources',
    'ReplayEventSource': '.sources',
    'ReplayFrameSource': '.sources',
    'SyntheticEventSource': '.sources',
    'SyncReport': '.sync',
    'sync_frames': '.sync',
    'sync_recording': '.sync',
    'DvCapture': '.dv_backend',
    'PylonFrameSource': '.pylon_backend',
    'discover': '.discovery',
    'host_clock_sync_recording': '.rig',
}


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)


__all__ = [
    "EventSource", "FrameSource", "FrameItem", "ReplayEventSource", "ReplayFrameSource", "SyntheticEventSource",
    "Recorder", "RecorderStats", "recover", "sync_frames", "sync_recording", "SyncReport",
    "list_devices", "NoDeviceFound", "DepthaiFrameSource", "PropheseeEventSource", "create_session", "verify_session",
    "DvCapture", "PylonFrameSource", "discover", "host_clock_sync_recording",
]
