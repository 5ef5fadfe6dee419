"""Bench runner: ColorVideoVDP JOD per run (display stated in the report), [bench] weights for
the learned methods (E2VID, FireNet) with test-made checkpoints, scored with a gain fit."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hybridhdr.evaluate import bench as B


def _bench(methods, **bench_keys):
    return {"bench": {"name": "t", "seed": 0, "strips": 1, "warmup": False, **bench_keys},
            "datasets": [{"name": "disc", "kind": "procedural", "width": 32, "height": 24, "duration_us": 200_000,
                          "hdr_rate_hz": 50.0, "disc_radius_px": 5.0}],
            "methods": methods,
            "charts": {"speed_accuracy": {"metrics": ["mse", "ssim", "jod", "q"]}}}


def test_parse_weights_and_jod_keys(tmp_path):
    toml = tmp_path / "b.toml"
    toml.write_text('[bench]\nname = "x"\njod_frames = 3\njod = false\nweights = { e2vid = "w/e2vid.pth.tar" }\n'
                    '[[datasets]]\nkind = "procedural"\n[[methods]]\nmethod = "e2vid"\n'
                    '[[methods]]\nmethod = "firenet"\nparams = { weights = "/abs/fire.pth.tar" }\n'
                    '[[methods]]\nmethod = "akf"\n', encoding="utf-8")
    with pytest.raises(PermissionError, match=r"'/abs/fire.pth.tar'.*outside the file's folder.*--allow-outside '/abs'"):
        B.load_bench(toml)  # a bench file reads only inside its folder unless the user allows more
    b = B.load_bench(toml, allow_outside=["/abs"])
    assert b.jod is False and b.jod_frames == 3 and b.weights == {"e2vid": str(tmp_path / "w/e2vid.pth.tar")}
    ms = {m["name"]: m for m in b.methods}
    assert ms["e2vid"]["params"]["weights"] == str(tmp_path / "w/e2vid.pth.tar")   # relative to the bench file
    assert ms["firenet"]["params"]["weights"] == "/abs/fire.pth.tar"
    assert "params" not in ms["akf"]
    runs = {r.name: r for r in B.expand(b)[0][3]}
    assert runs["e2vid"].normalise == runs["firenet"].normalise == "scale" and runs["akf"].normalise == "none"
    for bad in ({"jod": 1}, {"jod_frames": 0}, {"weights": {"akf": "x"}}):
        with pytest.raises(ValueError):
            B.parse_bench(_bench([{"method": "akf"}], **bad))


def test_jod_column_and_report(tmp_path):
    from hybridhdr.evaluate.cvvdp_metric import cvvdp_available
    b = B.parse_bench(_bench([{"name": "akf", "method": "akf"}, {"name": "frames", "method": "frames"}],
                             jod_frames=3), "t")
    rows = B.run_bench(b, workers=0, progress=False)
    assert all(r["status"] == "ok" for r in rows)
    w = B.write_results(rows, tmp_path, b)
    md = w["report_md"].read_text(encoding="utf-8")
    if cvvdp_available():
        assert all(0 < r["jod"] <= 10 and r["jod_frames"] == 3 for r in rows)
        assert "display 'standard_hdr_linear'" in md and "viewing distance 0.7472 m" in md
        assert "at most 3 evenly spaced matched frames" in md
        back = B.read_results(w["csv"])
        assert back[0]["jod"] == pytest.approx(rows[0]["jod"])
    else:
        assert all(math.isnan(r["jod"]) for r in rows) and "n/a (install hybridhdr[evaluate])" in md
    assert "| JOD |" in md
    b2 = B.parse_bench(_bench([{"name": "akf", "method": "akf"}], jod=False), "t")
    assert "jod" not in B.run_bench(b2, workers=0, progress=False)[0]


def test_learned_methods_run_with_bench_weights(tmp_path):
    torch = pytest.importorskip("torch")
    from hybridhdr.reconstruct.learned.networks import ARCHS
    paths = {}
    for method, arch in (("e2vid", "E2VIDRecurrent"), ("firenet", "FireNet")):
        torch.manual_seed(0)
        net = ARCHS[arch]()
        paths[method] = str(tmp_path / f"{method}.pth.tar")
        torch.save({"arch": arch, "model": net.config, "state_dict": net.state_dict()}, paths[method])
    b = B.parse_bench(_bench([{"name": "e2vid", "method": "e2vid", "params": {"device": "cpu"}},
                              {"name": "firenet", "method": "firenet", "params": {"device": "cpu"}},
                              {"name": "akf", "method": "akf"}], weights=paths, jod=False), "t")
    rows = B.run_bench(b, workers=0, progress=False)
    assert [r["status"] for r in rows] == ["ok"] * 3, [r["status"] for r in rows]
    by = {r["method_label"]: r for r in rows}
    assert by["e2vid"]["normalise"] == "scale" and by["akf"]["normalise"] == "none"
    assert np.isfinite(by["firenet"]["mse"]) and by["e2vid"]["time_per_data_s"] > 0
    w = B.write_results(rows, tmp_path / "o", b)
    md = w["report_md"].read_text(encoding="utf-8")
    assert "e2vid (fitted: scale)" in md and "except runs with a fitted normalisation (scale)" in md
    # without weights: the run fails with the message saying where to get them (never a download)
    b3 = B.parse_bench(_bench([{"name": "e2vid", "method": "e2vid"}], jod=False), "t")
    st = B.run_bench(b3, workers=0, progress=False)[0]["status"]
    assert st.startswith("error: WeightsRequiredError") and "never downloads" in st
