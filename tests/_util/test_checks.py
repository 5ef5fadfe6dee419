"""Shape, dtype and range checks: what they accept, and the messages they give."""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr._util.checks import check_dtype, check_range, check_shape, describe_shape
from hybridhdr.errors import FormatError


def test_check_shape_alternatives_and_bound_names():
    assert check_shape(np.zeros((2, 3)), "H W | H W 3", "image") == {"H": 2, "W": 3}
    assert check_shape(np.zeros((2, 3, 3)), "H W | H W 3", "image") == {"H": 2, "W": 3}
    assert check_shape((5, 4, 4), "K N N", "stack") == {"K": 5, "N": 4}
    with pytest.raises(ValueError, match=r"^stack must have shape \(K, N, N\), got \(5, 4, 3\)$"):
        check_shape((5, 4, 3), "K N N", "stack")
    with pytest.raises(ValueError, match=r"^image must have shape \(H, W\) or \(H, W, 3\), got \(2, 3, 4\)$"):
        check_shape(np.zeros((2, 3, 4)), "H W | H W 3", "image")


def test_check_shape_with_known_sizes_and_another_error():
    check_shape(np.arange(3), "K", "t_us", sizes={"K": 3})
    with pytest.raises(ValueError, match=r"t_us must have shape \(4,\), got \(3,\)"):
        check_shape(np.arange(3), "K", "t_us", sizes={"K": 4})
    with pytest.raises(FormatError, match=r"f\.h5: triggers/t must have shape \(2,\), got \(1,\)"):
        check_shape((1,), "N", "triggers/t", sizes={"N": 2}, error=lambda m: FormatError("f.h5", m))
    assert describe_shape("H W | H W C", {"H": 2}) == "(2, W) or (2, W, C)"


def test_check_dtype_and_range():
    assert check_dtype(np.zeros(2, np.uint16), "ui", "codes") == np.uint16
    with pytest.raises(TypeError, match="codes must have a unsigned integer or signed integer dtype, got float32"):
        check_dtype(np.zeros(2, np.float32), "ui", "codes")
    assert check_range(2, "fps", lo=0, lo_open=True) == 2.0
    for bad in (0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="fps must be finite and > 0, got"):
            check_range(bad, "fps", lo=0, lo_open=True)
    for bad in ("1", None, True):
        with pytest.raises(TypeError, match="fps must be a number"):
            check_range(bad, "fps", lo=0, lo_open=True)
    with pytest.raises(ValueError, match=r"^gamma must be finite and >= 0.5 and <= 3 \(exponent\), got 4$"):
        check_range(4, "gamma", lo=0.5, hi=3, unit="exponent")
