"""Readers and writers of event file formats (imported lazily through :mod:`hybridhdr.io`)."""

__all__: list[str] = []
