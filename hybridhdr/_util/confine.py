"""Files a scene or bench TOML may name: inside its own folder unless the user allows more.

Scene and bench files are closer to programs than to data (``docs/security.md``): a file from
someone else could otherwise read any file you can read (a texture, a mesh, a recording) or write
a cache anywhere. :func:`confine` resolves a path named in such a file the way the file means it
(relative to the file's folder), follows symbolic links and ``..``, and accepts it only when the
result lies inside the file's folder or one of the folders the user allowed on the command line
(``--allow-outside PATH``, repeatable; ``simulate`` and ``evaluate bench``). The error names the
key, the path as written and as resolved, and the flag that allows it.

The check is at load time, on the resolved path the loaders then open; the Python API's
``Scene.from_dict``/``parse_bench`` on a dict are trusted code and not confined.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["OutsideFolderError", "confine", "allowed_roots", "inside_folder"]


class OutsideFolderError(PermissionError):
    """A path named in a scene or bench file resolves outside the folders it may touch."""


def allowed_roots(base_dir, allow_outside=()) -> tuple[Path, ...]:
    """The resolved folders a file in ``base_dir`` may name: ``base_dir`` and ``allow_outside``."""
    roots = [Path(os.path.realpath(base_dir))]
    for a in allow_outside or ():
        roots.append(Path(os.path.realpath(os.fspath(a))))
    return tuple(roots)


def _inside(p: Path, root: Path) -> bool:
    return p == root or root in p.parents


def confine(value, base_dir, allow_outside=(), *, what: str, source: str = "") -> Path:
    """The absolute, resolved path of ``value`` (relative to ``base_dir``) if it lies inside
    ``base_dir`` or an ``allow_outside`` folder; else :class:`OutsideFolderError`.

    ``what`` names the key (``"datasets[0].path"``), ``source`` the file that named it.
    """
    if not isinstance(value, (str, os.PathLike)) or not os.fspath(value):
        raise ValueError(f"{source + ': ' if source else ''}{what}: expected a file or folder path, found {value!r}")
    p = Path(os.fspath(value)).expanduser()
    if not p.is_absolute():
        p = Path(base_dir) / p
    real = Path(os.path.realpath(p))
    roots = allowed_roots(base_dir, allow_outside)
    if any(_inside(real, r) for r in roots):
        return real
    where = f"{source}: " if source else ""
    raise OutsideFolderError(
        f"{where}{what} = {os.fspath(value)!r} resolves to {str(real)!r}, outside the file's folder {str(roots[0])!r}"
        + (f" and the allowed {', '.join(repr(str(r)) for r in roots[1:])}" if len(roots) > 1 else "")
        + f"; if you trust this file, pass --allow-outside {str(real.parent)!r} (docs/security.md)")


def inside_folder(name, folder, *, what: str, source=None) -> Path:
    """A file named by a data file (a list of images, ``timestamps.txt``) as a path inside
    ``folder``: absolute names, ``..`` and symbolic links that lead out of the folder are refused
    with a :class:`~hybridhdr.errors.FormatError` naming ``source`` (data files are untrusted;
    there is no ``--allow-outside`` for them)."""
    from ..errors import FormatError
    text = os.fspath(name)
    p = Path(text)
    root = Path(os.path.realpath(folder))
    real = Path(os.path.realpath(root / p)) if not p.is_absolute() else Path(os.path.realpath(p))
    if p.is_absolute() or not _inside(real, root):
        raise FormatError(source if source is not None else folder,
                          f"{what} {text!r} lies outside the folder {str(root)!r} (resolves to {str(real)!r}); "
                          f"files named by a data file must be inside its folder (docs/security.md)")
    return real
