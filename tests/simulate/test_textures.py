"""Procedural textures: deterministic, soft-edged bright panes, and the Pattern that names them."""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr.simulate.scene import Pattern, SceneError
from hybridhdr.simulate.sensor import SENSOR_TIERS, EventSensorParams, restrict_to_tiers
from hybridhdr.simulate.textures import BORDER_FLOOR, BORDER_MARGIN, TEXTURES, texture


@pytest.mark.parametrize("name", list(TEXTURES))
def test_same_seed_same_bits(name):
    a, b, c = texture(name, 3), texture(name, 3), texture(name, 4)
    assert a.dtype == np.float32 and a.ndim == 2 and np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert np.isfinite(a).all() and a.min() >= 0 and a.max() <= 1.0 + 1e-6


@pytest.mark.parametrize("name", sorted(BORDER_FLOOR))
def test_bright_panes_have_soft_log_borders(name):
    t = texture(name, 1).astype(np.float64)
    floor = BORDER_FLOOR[name]
    # the outermost texels sit at the floor: the texture's own values (>= 0.04 of its peak)
    # times the floor, and the ramp has barely started half a texel in (5 %: the smoothstep's
    # 3d^2 at d = 0.5 texel / the margin's >= 6 texels, times ln(1/floor) <= 3.9)
    edge = np.concatenate([t[0], t[-1], t[:, 0], t[:, -1]])
    assert edge.max() <= floor * 1.05 and edge.min() >= 0.04 * floor
    # the panes reach the bright level (>= 1/4 of the peak; scenery's trees are darker)
    assert np.quantile(t, 0.9) > 0.25
    # log-linear ramps: between neighbouring texels the log changes by at most the ramp's
    # slope (ln(1/floor) over the margin, smoothstep's peak slope 1.5x) plus the texture's own
    # steps (<= ln 20: a tree against the sky, a window in the facade)
    lt = np.log(t)
    cell_px = min(t.shape) / 6  # the smallest pane (facade: six across) in texels, at least
    ramp = 1.5 * np.log(1 / floor) / (BORDER_MARGIN * cell_px)
    step = max(np.abs(np.diff(lt, axis=0)).max(), np.abs(np.diff(lt, axis=1)).max())
    assert step <= ramp + np.log(20)


def test_texture_errors():
    with pytest.raises(ValueError, match="unknown procedural texture"):
        texture("marble")
    with pytest.raises(ValueError, match="seed"):
        texture("wood", -1)


def test_pattern_procedural():
    p = Pattern(40.0, procedural="scenery", seed=2)
    img = p.image()
    assert np.allclose(img, 40.0 * texture("scenery", 2)) and not p.is_constant
    assert Pattern.from_value(p.to_value(), "x.") == p
    with pytest.raises(SceneError, match="procedural"):
        Pattern(procedural="marble")
    with pytest.raises(SceneError, match="not several"):
        Pattern(procedural="wood", checkerboard=(2, 2))
    with pytest.raises(SceneError, match="seed"):
        Pattern.from_value({"procedural": "wood", "seed": -3}, "x.")


def test_restrict_to_tiers():
    full = EventSensorParams(threshold_mismatch_sigma=0.03, refractory_period_us=500, shot_noise_rate_hz=0.5,
                             leak_rate_hz=0.1, photoreceptor_cutoff_hz=30.0)
    d = restrict_to_tiers(full, (1, 2))
    assert d["threshold_mismatch_sigma"] == 0.03 and d["refractory_period_us"] == 500
    assert d["shot_noise_rate_hz"] == 0 and d["leak_rate_hz"] == 0 and d["photoreceptor_cutoff_hz"] is None
    assert EventSensorParams.from_dict(d).refractory_period_us == 500  # still valid parameters
    assert restrict_to_tiers(full, tuple(SENSOR_TIERS)) == full.to_dict()
    with pytest.raises(ValueError, match="tiers"):
        restrict_to_tiers(full, (5,))
