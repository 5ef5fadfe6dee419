"""Every camera the installed SDKs see: USB IDs (pyusb), DAVIS/DVXplorer (dv-processing), pylon.

``hybridhdr capture devices`` runs :func:`discover`. Each lister is optional: one whose package is
missing gives a hint naming the extra that installs it, never an error, so a base or ``[demo]``
install lists nothing and exits 0.
"""

from __future__ import annotations

from . import devices

__all__ = ["discover", "format_device_dicts", "LISTERS"]


#: what each lister needs, and the extra that installs it
LISTERS = {
    "usb": ("pyusb", "capture"),
    "dv-processing": ("dv-processing", "dv"),
    "pypylon": ("pypylon", "pylon"),
}


def _missing_hint(name: str) -> str:
    pkg, extra = LISTERS[name]
    return f"{pkg} is not installed: pip install 'hybridhdr[{extra}]' to list cameras through it"


def discover(*, include_unknown: bool = False, listers=("usb", "dv-processing", "pypylon")) -> tuple[list[dict], list[str]]:
    """Cameras every installed lister sees: USB IDs (pyusb), DAVIS/DVXplorer (dv-processing), pylon.

    A camera can appear twice (by its USB ID and through its SDK); each record says which lister
    (``sdk``) found it. Missing packages are not errors: they give a hint instead.

    Returns
    -------
    devices : list of dict
        ``maker``, ``model``, ``kind``, ``serial``, ``sdk`` and the lister's own fields.
    notes : list of str
        One line per lister that could not run (the package to install, or why it failed).
    """
    devs: list[dict] = []
    notes: list[str] = []
    for name in listers:
        if name not in LISTERS:
            raise ValueError(f"unknown lister {name!r}; expected one of {sorted(LISTERS)}")
        try:
            if name == "usb":
                try:
                    import usb.core  # noqa: F401
                except ImportError:
                    notes.append(_missing_hint(name))
                    continue
                for d in devices.list_devices(include_unknown=include_unknown):  # looked up per call
                    devs.append({**d.to_dict(), "sdk": "usb"})
            elif name == "dv-processing":
                from .dv_backend import dv_available, list_dv_cameras
                if not dv_available():
                    notes.append(_missing_hint(name))
                    continue
                devs += list_dv_cameras()
            else:
                from .pylon_backend import list_pylon_cameras, pylon_available
                if not pylon_available():
                    notes.append(_missing_hint(name))
                    continue
                devs += list_pylon_cameras()
        except (OSError, RuntimeError) as e:  # no libusb, no permission, an SDK that fails to start
            notes.append(f"{name}: could not list devices ({type(e).__name__}: {e})")
    return devs, notes


def format_device_dicts(devs: list[dict]) -> str:
    rows = [("sdk", "maker", "model", "kind", "serial", "open with")]
    rows += [(str(d.get("sdk", "")), str(d.get("maker", "")), str(d.get("model", "")), str(d.get("kind", "")),
              str(d.get("serial", "") or "-"), str(d.get("open_with", "") or d.get("usb_id", "")))
             for d in devs]
    w = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(c.ljust(w[i]) for i, c in enumerate(r)).rstrip() for r in rows)
