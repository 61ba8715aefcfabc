"""The shipped LUTs in luts/: manifest, loading through jp.brdf_lut, agreement with a regenerated
LUT and with the independent float64 reference."""

import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.shading.lut import DEFAULT_SAMPLES, compute_brdf_lut, lut_reference
from jaxpbr.shading.shipped_luts import _load, shipped_manifest


def test_manifest_lists_both_sizes_and_variants_within_target():
    m = shipped_manifest()
    got = {(tuple(e["size"]), e["smith"]) for e in m["luts"]}
    # The manifest keeps the file names it was generated with ("schlick"); shipped_luts maps the
    # current name "schlick_ggx" onto it.
    assert got == {((n, n), s) for n in (128, 256) for s in ("correlated", "schlick")}
    for e in m["luts"]:
        assert e["max_abs_error"] <= 1e-4 and e["error_texels"] == e["size"][0] * e["size"][1]
        assert e["samples"] == DEFAULT_SAMPLES


def test_brdf_lut_serves_the_shipped_file_and_regeneration_agrees():
    lut = np.asarray(jp.brdf_lut(size=128))
    assert lut.shape == (128, 128, 2) and lut.dtype == np.float32
    np.testing.assert_array_equal(lut, _load("brdf_lut_128_correlated.exr"))
    # Regenerate with the same code path: identical up to float32 evaluation order (< 2e-6 is
    # the documented float32-node effect of compute_brdf_lut).
    fresh = np.asarray(compute_brdf_lut(size=128))
    np.testing.assert_allclose(lut, fresh, atol=2e-6, rtol=0)


@pytest.mark.parametrize("smith", ["correlated", "schlick_ggx"])
def test_shipped_256_against_independent_reference_at_sampled_texels(smith):
    lut = np.asarray(jp.brdf_lut(size=256, smith=smith))
    rng = np.random.default_rng(3)
    j = np.concatenate([[0, 0, 255, 255], rng.integers(0, 256, 60)])
    i = np.concatenate([[0, 255, 0, 255], rng.integers(0, 256, 60)])
    ref = lut_reference((i + 0.5) / 256, (j + 0.5) / 256, smith=smith)
    assert np.abs(lut[j, i] - ref).max() <= 1e-4


def test_non_matching_parameters_are_computed():
    a = np.asarray(jp.brdf_lut(size=16, smith="schlick_ggx"))
    np.testing.assert_array_equal(a, np.asarray(compute_brdf_lut(size=16, smith="schlick_ggx")))
    b = np.asarray(jp.brdf_lut(size=128, use_shipped=False, samples=6 * 8**2))
    assert np.abs(b - _load("brdf_lut_128_correlated.exr")).max() > 0  # a different rule was run


def test_schlick_ggx_is_served_from_the_schlick_file_and_the_old_name_still_works():
    lut = np.asarray(jp.brdf_lut(size=128, smith="schlick_ggx"))
    np.testing.assert_array_equal(lut, _load("brdf_lut_128_schlick.exr"))
    with pytest.warns(DeprecationWarning, match="schlick_ggx"):
        old = np.asarray(jp.brdf_lut(size=128, smith="schlick"))
    np.testing.assert_array_equal(old, lut)
    with pytest.warns(DeprecationWarning, match="positionally"):
        np.testing.assert_array_equal(np.asarray(jp.brdf_lut(128, "schlick_ggx")), lut)
