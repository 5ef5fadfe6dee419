"""Dataset sessions: one folder per sequence with a checksummed manifest.

Layout (``docs/capture.md``), like the sequence folders of the paper's HDR dataset::

    SEQUENCE/
      manifest.json            format, version, sequence name, summary, and sha256 + size of every file
      recording.h5             the hybrid recording (events, frames, triggers; hybridhdr container)
      calibration/<file>       stereo/photometric calibration (copied), or referenced by relative path
      profile/<file>           camera profile (docs/camera-profile.md), copied or referenced
      brackets/<name>/         exposure-bracket sets (brackets.json + images) for HDR references

:func:`create_session` writes into ``SEQUENCE.partial/`` and renames it when complete;
:func:`verify_session` re-hashes every file listed (including referenced ones) and reports missing,
changed and unlisted files.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from pathlib import Path

from .._util.atomic import atomic_folder
from .._version import __version__
from ..formats.container import RecordingFile

__all__ = ["create_session", "verify_session", "sha256_file", "MANIFEST", "SESSION_FORMAT"]

MANIFEST = "manifest.json"
SESSION_FORMAT = "hybridhdr-session"


def sha256_file(path, bufsize: int = 1 << 22) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while True:
            b = f.read(bufsize)
            if not b:
                break
            h.update(b)
    return h.hexdigest()


def _entry(root: Path, path: Path, role: str, copied: bool) -> dict:
    rel = os.path.relpath(path, root)
    return {"path": Path(rel).as_posix(), "role": role, "size": path.stat().st_size,
            "sha256": sha256_file(path), "copied": copied}


def _summary(rec_path: Path) -> dict:
    with RecordingFile(rec_path) as r:
        fr = r.read_frames()
        tr = r.time_range_us
        return {"events": r.n_events, "sensor": str(r.sensor_size), "t_first_us": None if tr is None else tr[0],
                "t_last_us": None if tr is None else tr[1], "frames": 0 if fr is None else len(fr),
                "triggers": len(r.read_triggers()),
                "event_camera": r.metadata.event_camera.to_dict(), "frame_camera": r.metadata.frame_camera.to_dict()}


def create_session(folder, recording, *, calibration=None, camera_profile=None, brackets=(),
                   reference: bool = False, name: str | None = None, notes: str = "") -> Path:
    """Write a sequence folder with a manifest.

    Parameters
    ----------
    folder : path-like
        The sequence folder to create (must not exist).
    recording : path-like
        A hybridhdr container (``.h5``); copied to ``recording.h5``.
    calibration, camera_profile : path-like, optional
        Files copied into ``calibration/`` and ``profile/`` — or, with ``reference=True``, kept where
        they are and listed by path relative to the sequence folder with their checksum (shared
        calibrations of a rig used for many sequences).
    brackets : sequence of path-like
        Bracket-set folders (each with ``brackets.json``), copied into ``brackets/<name>/``.
    name : str, optional
        Sequence name (default: the folder name).
    notes : str
        Free text stored in the manifest.
    """
    folder = Path(folder)
    if folder.exists():
        raise FileExistsError(f"{folder} already exists; a session folder is written once")
    rec = Path(recording)
    if not rec.is_file():
        raise FileNotFoundError(f"{rec}: recording not found")
    for label, p in (("calibration", calibration), ("camera profile", camera_profile)):
        if p is not None and not Path(p).is_file():
            raise FileNotFoundError(f"{p}: {label} file not found")
    for b in brackets:
        if not (Path(b) / "brackets.json").is_file():
            raise ValueError(f"{b}: not a bracket-set folder (expected a brackets.json inside; write one with "
                             f"'hybridhdr capture brackets --out')")
    with atomic_folder(folder) as tmp:
        files = []
        shutil.copy2(rec, tmp / "recording.h5")
        files.append(_entry(tmp, tmp / "recording.h5", "recording", True))
        refs = {}
        for role, sub, p in (("calibration", "calibration", calibration), ("camera_profile", "profile", camera_profile)):
            if p is None:
                continue
            p = Path(p)
            if reference:
                # relative to the FINAL folder location, so the manifest stays valid after the rename
                rel = os.path.relpath(p.resolve(), folder.resolve())
                e = {"path": Path(rel).as_posix(), "role": role, "size": p.stat().st_size,
                     "sha256": sha256_file(p), "copied": False}
            else:
                (tmp / sub).mkdir(exist_ok=True)
                shutil.copy2(p, tmp / sub / p.name)
                e = _entry(tmp, tmp / sub / p.name, role, True)
            files.append(e)
            refs[role] = e["path"]
        bnames = []
        for b in brackets:
            b = Path(b)
            dst = tmp / "brackets" / b.name
            if dst.exists():
                raise ValueError(f"two bracket sets are named {b.name!r}; rename one")
            shutil.copytree(b, dst)
            bnames.append(f"brackets/{b.name}")
            for f in sorted(dst.rglob("*")):
                if f.is_file():
                    files.append(_entry(tmp, f, "brackets", True))
        manifest = {"format": SESSION_FORMAT, "version": 1, "name": name or folder.name,
                    "created_by": f"hybridhdr {__version__}",
                    "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "notes": notes,
                    "recording": "recording.h5", "calibration": refs.get("calibration"),
                    "camera_profile": refs.get("camera_profile"), "brackets": bnames,
                    "summary": _summary(tmp / "recording.h5"), "files": files}
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")
    return folder


def verify_session(folder) -> dict:
    """Check every file of a session against its manifest.

    Returns
    -------
    dict
        ``ok`` (bool), ``checked`` (count), ``missing``, ``changed`` (size or sha256 differ) and
        ``unlisted`` (files in the folder that the manifest does not name; informational).
    """
    folder = Path(folder)
    mpath = folder / MANIFEST
    if not mpath.is_file():
        raise FileNotFoundError(f"{folder}: no {MANIFEST} (not a hybridhdr session folder)")
    try:
        m = json.loads(mpath.read_text(encoding="utf-8"))
    except ValueError as e:
        raise ValueError(f"{mpath}: not valid JSON ({e})") from None
    if m.get("format") != SESSION_FORMAT:
        raise ValueError(f"{mpath}: format is {m.get('format')!r}, expected {SESSION_FORMAT!r}")
    missing, changed, listed = [], [], set()
    for e in m.get("files", []):
        p = (folder / e["path"])
        listed.add(os.path.normpath(p.resolve()))
        if not p.is_file():
            missing.append(e["path"])
            continue
        if p.stat().st_size != e["size"]:
            changed.append({"path": e["path"], "why": f"size {p.stat().st_size} != {e['size']}"})
        elif sha256_file(p) != e["sha256"]:
            changed.append({"path": e["path"], "why": "sha256 differs"})
    unlisted = sorted(Path(os.path.relpath(f, folder)).as_posix() for f in folder.rglob("*")
                      if f.is_file() and f.name != MANIFEST and os.path.normpath(f.resolve()) not in listed)
    return {"ok": not missing and not changed, "checked": len(m.get("files", [])), "missing": missing,
            "changed": changed, "unlisted": unlisted, "name": m.get("name")}
