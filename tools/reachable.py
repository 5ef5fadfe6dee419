"""Exit 0 if the URL answers within 15 s, else 1 (Makefile: use the PyTorch CPU index only when reachable,
instead of pip retrying it for every package)."""

import sys
import urllib.request

try:
    urllib.request.urlopen(urllib.request.Request(sys.argv[1], method="HEAD"), timeout=15).close()
except Exception:  # noqa: BLE001 - any failure means: not usable now
    sys.exit(1)
