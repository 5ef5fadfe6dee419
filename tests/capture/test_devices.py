"""USB device listing against a test double of ``usb.core.find``."""

from __future__ import annotations

import pytest

from hybridhdr.capture import devices as D
from hybridhdr.cli import main


class FakeUsbDevice:
    """Test double of a pyusb device (only the attributes list_devices reads)."""

    def __init__(self, vid, pid, bus=1, address=2):
        self.idVendor, self.idProduct, self.bus, self.address = vid, pid, bus, address
        self.iSerialNumber = 0


def _patch_find(monkeypatch, devs):
    import usb.core
    calls = []

    def fake_find(find_all=False, backend=None, **kw):  # test double of usb.core.find
        calls.append((find_all, backend))
        return iter(devs)
    monkeypatch.setattr(usb.core, "find", fake_find)
    monkeypatch.setattr(D, "get_backend", lambda: "fake-backend")
    return calls


def test_known_ids_are_identified(monkeypatch):
    calls = _patch_find(monkeypatch, [FakeUsbDevice(0x03E7, 0x2485), FakeUsbDevice(0x046D, 0xC52B),
                                      FakeUsbDevice(0x152A, 0x8419, 3, 7), FakeUsbDevice(0x04B4, 0x00F5),
                                      FakeUsbDevice(0x1E10, 0x3300), FakeUsbDevice(0x04B4, 0x0001)])
    devs = D.list_devices()
    assert calls == [(True, "fake-backend")]
    got = [(d.usb_id, d.maker, d.kind) for d in devs]
    # the Logitech receiver and a generic Cypress chip (04b4:0001) are not cameras
    assert got == [("03e7:2485", "Luxonis", "frame"), ("152a:8419", "iniVation", "event"),
                   ("04b4:00f5", "Prophesee", "event"), ("1e10:3300", "FLIR", "frame")]
    assert devs[1].bus == 3 and devs[1].address == 7
    assert len(D.list_devices(include_unknown=True)) == 6
    table = D.format_devices(devs)
    assert "DVXplorer" in table and table.splitlines()[0].startswith("USB ID")


def test_cli_lists_devices(monkeypatch, capsys):
    _patch_find(monkeypatch, [FakeUsbDevice(0x03E7, 0xF63B)])
    assert main(["capture", "devices", "--json"]) == 0
    assert '"usb_id": "03e7:f63b"' in capsys.readouterr().out


def test_cli_no_device_found_exits_1_without_traceback(monkeypatch, capsys):
    _patch_find(monkeypatch, [FakeUsbDevice(0x046D, 0xC52B)])
    assert main(["capture", "devices"]) == 1
    err = capsys.readouterr().err
    assert "no device found" in err and "Traceback" not in err


def test_real_backend_lookup_does_not_crash():
    # on this machine (container, no USB cameras) the real pyusb path must work end to end
    devs = D.list_devices()
    assert isinstance(devs, list)


def test_identify_vendor_wildcard():
    assert D.identify(0x2676, 0xBA02)[0] == "Basler"
    assert D.identify(0x1234, 0x5678) is None
    with pytest.raises(D.NoDeviceFound):
        raise D.NoDeviceFound("x")


# -- every installed SDK, none required ------------------------------------------------------------
_SDK_MODULES = ("usb", "usb.core", "usb.backend", "usb.backend.libusb1", "usb.util", "libusb_package",
                "dv_processing", "pypylon", "pypylon.pylon", "pypylon.genicam")


def _hide_sdks(monkeypatch):
    """What a `make demo` install lacks: pyusb, dv-processing and pypylon import as missing."""
    import sys
    for m in _SDK_MODULES:
        monkeypatch.setitem(sys.modules, m, None)  # `import m` raises ImportError


def test_devices_json_without_any_sdk_is_an_empty_list(monkeypatch, capsys):
    _hide_sdks(monkeypatch)
    assert main(["capture", "devices", "--json"]) == 0
    out = capsys.readouterr()
    assert out.out.strip() == "[]"
    for extra in ("hybridhdr[capture]", "hybridhdr[dv]", "hybridhdr[pylon]"):
        assert extra in out.err  # which extra lists cameras through which package
    assert "Traceback" not in out.err and "No module named" not in out.err


def test_devices_text_without_any_sdk_exits_0_with_hints(monkeypatch, capsys):
    _hide_sdks(monkeypatch)
    assert main(["capture", "devices"]) == 0
    out = capsys.readouterr()
    assert "no device found by the installed listers" in out.out
    assert "pip install 'hybridhdr[capture]'" in out.err


def test_discover_merges_the_listers(monkeypatch):
    from hybridhdr.capture import discovery, dv_backend, pylon_backend
    _patch_find(monkeypatch, [FakeUsbDevice(0x152A, 0x841A)])
    monkeypatch.setattr(dv_backend, "dv_available", lambda: True)
    monkeypatch.setattr(dv_backend, "list_dv_cameras", lambda: [{"maker": "iniVation", "model": "DAVIS346",
                                                                 "serial": "00000499", "sdk": "dv-processing",
                                                                 "kind": "event+frame",
                                                                 "open_with": "--camera davis:00000499"}])
    monkeypatch.setattr(pylon_backend, "pylon_available", lambda: False)
    devs, notes = discovery.discover()
    assert [d["sdk"] for d in devs] == ["usb", "dv-processing"]
    assert devs[0]["usb_id"] == "152a:841a" and devs[1]["open_with"] == "--camera davis:00000499"
    assert notes == ["pypylon is not installed: pip install 'hybridhdr[pylon]' to list cameras through it"]
    table = discovery.format_device_dicts(devs)
    assert "--camera davis:00000499" in table
