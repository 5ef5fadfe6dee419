"""hybridhdr: HDR video from hybrid event/frame cameras.

Implements the system of Wang, Ng, Scheerlinck & Mahony, "An Asynchronous Kalman Filter for Hybrid
Event Cameras", ICCV 2021 (doi:10.1109/ICCV48922.2021.00050): capture, calibrate, simulate,
reconstruct and evaluate. ``import hybridhdr`` is light: it never imports h5py, numba, cv2 or
matplotlib; those load with the parts that need them.
"""

from ._version import __version__
from .errors import EventValidationError, FormatError, UnknownFormatError
from .events import (EVENT_DTYPE, TRIGGER_DTYPE, SensorSize, concatenate_events, empty_events,
                     empty_triggers, make_events, make_triggers, slice_time, validate_events,
                     validate_triggers)
from .formats import (DataDropWarning, EventChunk, EventFileReader, EventFileWriter, detect_format,
                      open_reader, open_writer, read, write)
from .model import CameraInfo, Frames, HDRReferences, Metadata, Recording

__all__ = [
    "__version__", "EVENT_DTYPE", "TRIGGER_DTYPE", "SensorSize", "make_events", "empty_events",
    "make_triggers", "empty_triggers", "validate_events", "validate_triggers", "slice_time",
    "concatenate_events", "Frames", "HDRReferences", "CameraInfo", "Metadata", "Recording",
    "FormatError", "UnknownFormatError", "EventValidationError", "DataDropWarning", "EventChunk",
    "EventFileReader", "EventFileWriter", "detect_format", "open_reader", "open_writer", "read", "write",
]
