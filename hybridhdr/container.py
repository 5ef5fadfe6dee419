"""The hybridhdr recording container under the name the README shows
(``from hybridhdr.container import RecordingFile, write_recording``); it lives in
:mod:`hybridhdr.formats.container`.
"""

from .formats.container import FORMAT_VERSION, RecordingFile, RecordingWriter, read_recording, write_recording

__all__ = ["FORMAT_VERSION", "RecordingFile", "RecordingWriter", "read_recording", "write_recording"]
