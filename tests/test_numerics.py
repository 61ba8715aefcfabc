"""jaxpbr._numerics helpers outside the kernels: the host-side row cross product."""

import numpy as np


def test_cross_rows_is_np_cross_bit_for_bit():
    from jaxpbr._numerics import cross_rows

    rng = np.random.default_rng(3)
    for dtype in (np.float32, np.float64):
        a, b = rng.standard_normal((1000, 3)).astype(dtype), rng.standard_normal((1000, 3)).astype(dtype)
        out = cross_rows(a, b)
        assert out.dtype == dtype
        np.testing.assert_array_equal(out, np.cross(a, b))
    np.testing.assert_array_equal(cross_rows(a, b[0]), np.cross(a, b[0]))  # broadcast against one row
