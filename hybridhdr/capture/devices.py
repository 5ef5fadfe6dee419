"""Find attached event and frame cameras by USB vendor/product ID (pyusb + libusb).

The table :data:`KNOWN_DEVICES` maps ``(vendor_id, product_id)`` (``product_id`` ``None`` = any
product of that vendor) to a maker, model and kind. Sources of the IDs:

* **Prophesee** EVK3/EVK4 boards: Cypress FX3 ``04b4:00f4`` and ``04b4:00f5``, Treuzell boards
  ``03fd:5832`` and ``1fc9:5838`` — registered by OpenEB's HAL plugins
  (``prophesee-ai/openeb:hal_psee_plugins/src/plugin/psee_universal.cpp``,
  ``TzCameraDiscovery::add_usb_id``); ``31f7:0003`` (Prophesee's own vendor ID, EVK4) listed by
  ``neuromorphic-paris/sepia`` (``psee.hpp`` identities).
* **iniVation**: Thesycon vendor ID ``152a``; ``841a`` DAVIS FX3, ``841b`` DAVIS FX2 (DAVIS240),
  ``8419`` DVXplorer (libcaer ``src/davis.h`` / ``src/dvxplorer.h``, ``*_DEVICE_PID``; the PID
  range ``8400``-``841f`` is reserved for the INI sensors, ``SensorsINI`` ``drivers/readme.txt``).
* **Luxonis OAK** (Intel Movidius vendor ``03e7``): ``2485`` Myriad X not booted, ``2150``
  Myriad 2 not booted, ``f63b`` booted, ``f63c`` bootloader, ``f63d`` flash-booted
  (``luxonis/XLink`` ``usb_host.h``: ``DEFAULT_UNBOOTPID_2485``, ``DEFAULT_OPENPID`` ...).
* **FLIR / Teledyne FLIR** (Point Grey Research): vendor ``1e10``, and ``1724`` in the Spinnaker
  udev rule (``40-flir-spinnaker.rules``).
* **Basler**: vendor ``2676`` (pylon's ``usb.ids`` addition: ``ba02`` ace, ``ba03`` dart,
  ``ba04`` pulse USB3 Vision).
* **Allied Vision** ``1ab2``, **IDS Imaging** ``1409``, **XIMEA** ``20f7``: vendor IDs from the
  linux-usb.org ``usb.ids`` list.

Listing needs a libusb backend: the system's libusb-1.0, or the copy bundled by the
``libusb-package`` wheel when the system has none. Reading serial numbers needs permission to open
the device (udev rules); without it the serial shows as empty.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

__all__ = ["KNOWN_DEVICES", "UsbCamera", "list_devices", "get_backend", "format_devices", "NoDeviceFound"]


class NoDeviceFound(OSError):
    """No supported camera is attached (the CLI prints it and exits 1)."""


#: (vendor_id, product_id or None) -> (maker, model, kind)
KNOWN_DEVICES: dict[tuple[int, int | None], tuple[str, str, str]] = {
    (0x04B4, 0x00F4): ("Prophesee", "EVK3 (Cypress FX3)", "event"),
    (0x04B4, 0x00F5): ("Prophesee", "EVK4 (Cypress FX3)", "event"),
    (0x03FD, 0x5832): ("Prophesee", "Treuzell board", "event"),
    (0x1FC9, 0x5838): ("Prophesee", "Treuzell board", "event"),
    (0x31F7, 0x0003): ("Prophesee", "EVK4", "event"),
    (0x31F7, None): ("Prophesee", "camera", "event"),
    (0x152A, 0x841A): ("iniVation", "DAVIS (FX3)", "event+frame"),
    (0x152A, 0x841B): ("iniVation", "DAVIS240 (FX2)", "event+frame"),
    (0x152A, 0x8419): ("iniVation", "DVXplorer", "event"),
    (0x03E7, 0x2485): ("Luxonis", "OAK (Myriad X, not booted)", "frame"),
    (0x03E7, 0x2150): ("Luxonis", "OAK (Myriad 2, not booted)", "frame"),
    (0x03E7, 0xF63B): ("Luxonis", "OAK (booted)", "frame"),
    (0x03E7, 0xF63C): ("Luxonis", "OAK (bootloader)", "frame"),
    (0x03E7, 0xF63D): ("Luxonis", "OAK (flash booted)", "frame"),
    (0x1E10, None): ("FLIR", "Point Grey / FLIR camera", "frame"),
    (0x1724, None): ("FLIR", "Teledyne FLIR camera", "frame"),
    (0x2676, None): ("Basler", "USB3 Vision camera", "frame"),
    (0x1AB2, None): ("Allied Vision", "USB3 Vision camera", "frame"),
    (0x1409, None): ("IDS Imaging", "uEye camera", "frame"),
    (0x20F7, None): ("XIMEA", "camera", "frame"),
}


@dataclass(frozen=True)
class UsbCamera:
    vendor_id: int
    product_id: int
    maker: str
    model: str
    kind: str
    bus: int | None = None
    address: int | None = None
    serial: str = ""

    @property
    def usb_id(self) -> str:
        return f"{self.vendor_id:04x}:{self.product_id:04x}"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["usb_id"] = self.usb_id
        return d


def identify(vendor_id: int, product_id: int):
    """``(maker, model, kind)`` of a USB ID, or None when it is not a known camera."""
    return KNOWN_DEVICES.get((vendor_id, product_id)) or KNOWN_DEVICES.get((vendor_id, None))


def get_backend():
    """A pyusb libusb-1.0 backend: the system's, else the one bundled by ``libusb-package``."""
    try:
        import usb.backend.libusb1
    except ImportError as e:
        raise ImportError("listing USB devices needs pyusb: pip install pyusb libusb-package") from e
    be = usb.backend.libusb1.get_backend()
    if be is None:
        try:
            import libusb_package
        except ImportError:
            raise OSError("no libusb-1.0 found on this system; install libusb (apt install libusb-1.0-0) "
                          "or pip install libusb-package") from None
        be = libusb_package.get_libusb1_backend()
        if be is None:
            raise OSError("libusb-package is installed but its libusb-1.0 could not be loaded")
    return be


def _serial(dev) -> str:
    try:
        import usb.util
        if getattr(dev, "iSerialNumber", 0):
            return usb.util.get_string(dev, dev.iSerialNumber) or ""
    except Exception:  # no permission / device busy: the serial is optional
        return ""
    return ""


def list_devices(*, backend=None, include_unknown: bool = False) -> list[UsbCamera]:
    """Attached cameras known by :data:`KNOWN_DEVICES` (all devices with ``include_unknown``)."""
    import usb.core
    be = backend if backend is not None else get_backend()
    out = []
    for dev in usb.core.find(find_all=True, backend=be) or []:
        vid, pid = int(dev.idVendor), int(dev.idProduct)
        who = identify(vid, pid)
        if who is None:
            if not include_unknown:
                continue
            who = ("?", "unknown device", "-")
        out.append(UsbCamera(vid, pid, *who, bus=getattr(dev, "bus", None), address=getattr(dev, "address", None),
                             serial=_serial(dev)))
    return out


def format_devices(devs: list[UsbCamera]) -> str:
    rows = [("USB ID", "maker", "model", "kind", "bus:addr", "serial")]
    rows += [(d.usb_id, d.maker, d.model, d.kind, f"{d.bus}:{d.address}", d.serial or "-") for d in devs]
    w = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(c.ljust(w[i]) for i, c in enumerate(r)).rstrip() for r in rows)

