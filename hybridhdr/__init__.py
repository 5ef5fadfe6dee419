"""hybridhdr: HDR video from hybrid event/frame cameras.

Implements the system of Wang, Ng, Scheerlinck & Mahony, "An Asynchronous Kalman Filter for Hybrid
Event Cameras", ICCV 2021 (doi:10.1109/ICCV48922.2021.00050): capture, calibrate, simulate,
reconstruct and evaluate. ``import hybridhdr`` is light: it imports neither numpy nor h5py, numba,
cv2 or matplotlib. The top-level names below load their module on first use (PEP 562), so
``import hybridhdr as hh; hh.read(...)`` works as before while ``hybridhdr --help`` starts
without numpy (``benchmarks/cli_start.py``).
"""

from ._util.lazy import lazy_exports
from ._version import __version__
from .errors import EventValidationError, FormatError, UnknownFormatError

_LAZY = {
    **{name: ".events" for name in (
        "EVENT_DTYPE", "TRIGGER_DTYPE", "IMU_DTYPE", "SensorSize", "concatenate_events", "empty_events",
        "empty_triggers", "empty_imu", "validate_imu", "make_events", "make_triggers", "slice_time", "validate_events",
        "validate_triggers")},
    **{name: ".formats" for name in (
        "DataDropWarning", "EventChunk", "EventFileReader", "EventFileWriter", "detect_format",
        "open_reader", "open_writer", "read", "write")},
    **{name: ".model" for name in ("CameraInfo", "Frames", "HDRReferences", "Metadata", "Recording")},
}

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

__all__ = [
    "__version__", "EVENT_DTYPE", "TRIGGER_DTYPE", "IMU_DTYPE", "SensorSize", "make_events", "empty_events",
    "make_triggers", "empty_triggers", "empty_imu", "validate_events", "validate_triggers", "validate_imu",
    "slice_time",
    "concatenate_events", "Frames", "HDRReferences", "CameraInfo", "Metadata", "Recording",
    "FormatError", "UnknownFormatError", "EventValidationError", "DataDropWarning", "EventChunk",
    "EventFileReader", "EventFileWriter", "detect_format", "open_reader", "open_writer", "read", "write",
]
