"""The one TOML reader."""

from __future__ import annotations

import pytest

from hybridhdr._util.toml import TOMLDecodeError, load_toml, loads_toml


def test_load_and_loads(tmp_path):
    p = tmp_path / "run.toml"
    p.write_text('[akf]\ncontrast_threshold = 0.2\nname = "é"\n', encoding="utf-8")
    assert load_toml(p) == {"akf": {"contrast_threshold": 0.2, "name": "é"}}
    assert loads_toml("a = [1, 2]") == {"a": [1, 2]}
    with pytest.raises(TOMLDecodeError):
        loads_toml("a = ")
