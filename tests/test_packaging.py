"""Packaging: ranges not pins, licence metadata in the PEP 639 form, a build without
setuptools deprecation warnings, and an installed PyTorch kept by ``pip install hybridhdr[learned]``."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.specifiers import SpecifierSet
from packaging.version import Version

from hybridhdr._util.toml import load_toml

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = load_toml(ROOT / "pyproject.toml")

#: Upper bounds allowed in pyproject.toml, each for a known break (name -> reason). Empty: none is
#: known. A new one needs its reason here and in a comment beside it in pyproject.toml.
KNOWN_BREAKS: dict[str, str] = {}


def _requirements():
    """(where, Requirement) for every requirement the library declares, build-system included."""
    out = [("build-system.requires", Requirement(r)) for r in PYPROJECT["build-system"]["requires"]]
    out += [("dependencies", Requirement(r)) for r in PYPROJECT["project"]["dependencies"]]
    for extra, reqs in PYPROJECT["project"]["optional-dependencies"].items():
        out += [(f"[{extra}]", Requirement(r)) for r in reqs]
    return out


def test_no_pins_every_dependency_has_a_lower_bound():
    text = (ROOT / "pyproject.toml").read_text()
    assert "==" not in text, [ln for ln in text.splitlines() if "==" in ln]  # as grep -n '==' would find a pin
    reqs = _requirements()
    assert len(reqs) > 30  # all of them parsed, not an empty table
    for where, r in reqs:
        if r.name == "hybridhdr":  # an extra of our own: no version
            assert not r.specifier, (where, str(r))
            continue
        ops = {s.operator for s in r.specifier}
        assert not ops & {"==", "===", "~="}, f"{where}: {r} pins a version; libraries declare ranges"
        assert ops & {">=", ">"}, f"{where}: {r} has no lower bound"
        if ops & {"<", "<="}:
            assert r.name in KNOWN_BREAKS, f"{where}: {r} has an upper bound without a known break"


@pytest.mark.parametrize("extra", ["evaluate", "learned"])
def test_torch_range_admits_the_versions_users_have(extra):
    (torch,) = [Requirement(r) for r in PYPROJECT["project"]["optional-dependencies"][extra]
                if Requirement(r).name == "torch"]
    spec: SpecifierSet = torch.specifier
    # 2.1 (oldest claimed) ... 2.13 (CI, CPU build) ... 2.14 (newest on our index) and later: CPU and CUDA
    # builds alike (a local version label such as +cpu or +cu121 is admitted by a range)
    for v in ("2.1.0", "2.4.1", "2.5.1+cu121", "2.13.0", "2.13.0+cpu", "2.14.1", "3.0.0"):
        assert spec.contains(Version(v)), (extra, str(spec), v)
    assert not spec.contains(Version("2.0.1")) and not spec.contains(Version("1.13.1"))


def test_licence_metadata_is_pep639():
    proj = PYPROJECT["project"]
    assert proj["license"] == "BSD-3-Clause"
    assert proj["license-files"] == ["LICENSE"]
    lic = (ROOT / "LICENSE").read_text()
    assert lic.startswith("BSD 3-Clause License") and "hybridhdr developers" in lic
    (st,) = [r for w, r in _requirements() if w == "build-system.requires" and r.name == "setuptools"]
    # setuptools 77 is the first to accept a licence expression string and license-files
    assert st.specifier.contains("77.0.0") and not st.specifier.contains("76.1.0")


def _prepare_metadata(root: Path, out: Path) -> subprocess.CompletedProcess:
    """setuptools' PEP 517 metadata hook on ``root``, every warning an error, in a child process."""
    code = ("import sys, warnings\nwarnings.simplefilter('error')\n"
            "import setuptools.build_meta as b\nprint(b.prepare_metadata_for_build_wheel(sys.argv[1]))\n")
    return subprocess.run([sys.executable, "-c", code, str(out)], cwd=root, capture_output=True, text=True,
                          timeout=120)


def test_build_metadata_without_deprecation_warnings(tmp_path):
    import setuptools
    if Version(setuptools.__version__) < Version("77"):
        pytest.fail(f"setuptools {setuptools.__version__} here; the test extra installs setuptools>=77")
    r = _prepare_metadata(ROOT, tmp_path)
    log = r.stdout + r.stderr
    assert r.returncode == 0, log[-3000:]
    assert "deprecat" not in log.lower(), log[-3000:]
    (dist_info,) = tmp_path.glob("hybridhdr-*.dist-info")
    meta = (dist_info / "METADATA").read_text()
    assert "License-Expression: BSD-3-Clause" in meta and "License-File: LICENSE" in meta
    assert re.search(r"^Requires-Dist: torch>=2\.1; extra == \"learned\"$", meta, re.M), meta


def test_the_metadata_check_fails_on_the_old_licence_table(tmp_path):
    """The check above has teeth: the pre-PEP 639 ``license = { text = ... }`` is refused."""
    proj = tmp_path / "proj"
    (proj / "pkg").mkdir(parents=True)
    (proj / "pkg" / "__init__.py").write_text("")
    (proj / "pyproject.toml").write_text('[build-system]\nrequires = ["setuptools>=77"]\n'
                                         'build-backend = "setuptools.build_meta"\n[project]\nname = "pkg"\n'
                                         'version = "0"\nlicense = { text = "BSD-3-Clause" }\n')
    r = _prepare_metadata(proj, tmp_path)
    # deprecated until 2027-02-18, refused after: either way the check fails
    assert r.returncode != 0 and "license" in (r.stdout + r.stderr).lower(), r.stdout + r.stderr


def _pip_dry_run(tmp_path, *reqs) -> list[dict]:
    rep = tmp_path / f"report{len(list(tmp_path.glob('report*')))}.json"
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--dry-run", "--quiet", "--no-build-isolation",
                        "--report", str(rep), *reqs], capture_output=True, text=True, timeout=600,
                       env={**os.environ, "PIP_DISABLE_PIP_VERSION_CHECK": "1"})
    if r.returncode != 0:
        pytest.skip(f"pip could not resolve here (no index reachable?): {r.stderr.strip()[-500:]}")
    return json.loads(rep.read_text())["install"]


@pytest.mark.slow
def test_installing_learned_keeps_the_installed_torch(tmp_path):
    """``pip install hybridhdr[learned]`` beside an installed PyTorch (here the test venv's CPU build)
    leaves it alone: pip's dry-run installs no torch. Control: a requirement that excludes the
    installed version makes pip pick another torch, so the first answer is not vacuous (another
    release is within reach). About 30 s (two resolutions and the editable metadata build)."""
    try:
        have = metadata.version("torch")
    except metadata.PackageNotFoundError:
        pytest.skip("no PyTorch installed here")
    plan = _pip_dry_run(tmp_path, "-e", f"{ROOT}[learned]")
    names = {i["metadata"]["name"].lower(): i["metadata"]["version"] for i in plan}
    assert "hybridhdr" in names and "torch" not in names, (have, names)
    other = _pip_dry_run(tmp_path, "--no-deps", "-e", f"{ROOT}[learned]", f"torch!={have}")  # no CUDA libraries
    picked = {i["metadata"]["name"].lower(): i["metadata"]["version"] for i in other}.get("torch")
    assert picked is not None and picked != have, (have, picked)
