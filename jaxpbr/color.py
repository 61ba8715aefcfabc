"""Colour handling: exposure, tone mapping and display transfer functions.

Every function here takes **linear, scene-referred RGB with Rec.709/sRGB primaries** (the radiance that the
shading kernels produce), shape ``(..., 3)`` unless said otherwise, and returns an array of the same shape.
Output encoding (tone mapping, the sRGB or gamma transfer function, clipping to ``[0, 1]``) happens only in this
module and in :mod:`jaxpbr.io.image`; nothing upstream of them ever sees display-encoded values.

The JAX functions are pure, elementwise (or per-pixel) and safe under ``jax.jit``, ``jax.vmap`` and ``jax.grad``:
they preserve the input's floating dtype (float32 in, float32 out; integer input is promoted to JAX's default
float), use the double-``where`` pattern wherever a branch or a power would produce an infinite or NaN gradient,
and keep NaN inputs NaN rather than silently turning them into numbers.

The ``*_np`` functions are host-side NumPy paths that call colour-science; :func:`jaxpbr.io.image.write` uses
:func:`srgb_encode_np` when it writes sRGB-encoded PNG files.

References
----------
- IEC 61966-2-1:1999, *Default RGB colour space - sRGB* (the piecewise transfer function).
- E. Reinhard et al., "Photographic Tone Reproduction for Digital Images", SIGGRAPH 2002, eq. 3 (``L/(1+L)``);
  applied per channel as in LearnOpenGL, "Advanced Lighting / HDR".
- S. Hill, BakingLab ``ACES.hlsl`` ("ACESFitted"), a fit of the ACES RRT + sRGB ODT.
- K. Narkowicz, "ACES Filmic Tone Mapping Curve" (2016 blog post).
"""

from __future__ import annotations

import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from ._numerics import _eager
from ._numerics import as_float as _as_float
from ._program_cache import LOOP_EMITTERS, cached_jit

__all__ = [
    "TONEMAP_OPERATORS",
    "TRANSFERS",
    "aces_fitted",
    "aces_narkowicz",
    "display",
    "encode",
    "exposure",
    "gamma_decode",
    "gamma_encode",
    "reinhard",
    "srgb_decode",
    "srgb_decode_np",
    "srgb_encode",
    "srgb_encode_np",
    "tonemap",
]

#: Names accepted by :func:`tonemap`.
TONEMAP_OPERATORS = ("none", "clamp", "reinhard", "aces", "aces_narkowicz")
#: Names accepted by :func:`encode` (and by ``jaxpbr.io.image.write(..., encoding=...)``).
TRANSFERS = ("srgb", "gamma2.2", "linear")

# IEC 61966-2-1 constants.
_SRGB_LINEAR_KNEE = 0.0031308  # linear value where the encode switches from the straight line to the power
_SRGB_ENCODED_KNEE = 0.04045  # encoded value where the decode switches (the standard's published threshold)

# Stephen Hill's ACESFitted (BakingLab ACES.hlsl): sRGB -> (ODT_SAT o RRT_SAT) and (ODT_SAT o XYZ -> sRGB).
_ACES_INPUT = (
    (0.59719, 0.35458, 0.04823),
    (0.07600, 0.90834, 0.01566),
    (0.02840, 0.13383, 0.83777),
)
_ACES_OUTPUT = (
    (1.60475, -0.53108, -0.07367),
    (-0.10208, 1.10813, -0.00605),
    (-0.00327, -0.07276, 1.07602),
)


def _check_rgb(c, name):
    if c.ndim == 0 or c.shape[-1] != 3:
        raise ValueError(f"{name} expects linear RGB with shape (..., 3); got shape {tuple(c.shape)}")


def _mat3(m, c):
    """``m @ c`` for a 3x3 tuple-of-Python-floats matrix and ``c: (..., 3)``.

    Written as weighted sums of channels (not ``jnp.matmul``) so the dtype of ``c`` is kept (Python floats are
    weakly typed) and no accelerator runs it as a reduced-precision (TF32) matrix product.
    """
    r, g, b = c[..., 0], c[..., 1], c[..., 2]
    return jnp.stack([row[0] * r + row[1] * g + row[2] * b for row in m], axis=-1)


def _clamp_negative(c):
    """``max(c, 0)`` for tone-map inputs, keeping NaN NaN (``c < 0`` is False for NaN) and gradient 1 at 0.

    Negative radiance is outside the tone maps' domain; the published rational curves are not monotone there
    (Reinhard divides by zero at -1, both ACES fits climb back towards white as ``c -> -inf``).
    """
    return jnp.where(c < 0.0, 0.0, c)


def _above(x, threshold):
    """``x > threshold`` decided exactly for the real-number ``threshold``, in ``x``'s own dtype.

    Comparing a float32 ``x`` with ``float32(threshold)`` gets the one value ``x == float32(threshold)`` wrong
    whenever the threshold rounded *up*, and at the sRGB knees the two branches differ by ~7e-7 relative. The
    largest representable value ``<= threshold`` gives the exact answer.
    """
    t = np.asarray(threshold, dtype=x.dtype)
    if float(t) > threshold:
        t = np.nextafter(t, np.asarray(-np.inf, dtype=x.dtype))
    return x > t


def _check_gamma(gamma):
    if isinstance(gamma, (int, float, np.number)) and not gamma > 0:
        raise ValueError(f"gamma must be > 0 (e.g. 2.2); got {gamma!r}")


def _one_program(static=(), check=None):
    """Decorator: called outside any transformation, the function runs as one compiled program
    (`jax.jit`, with the arguments named in `static` static), not op by op: one dispatch and one
    compilation per input shape and dtype where op by op it was one of each for every operation
    (a tone map and an encoding of an image: 23 compilations, 0.68 s on a 2-core CPU, against
    one). Traced (inside jit, vmap or grad) it is the plain function, inlined into the caller's
    trace. `check(*args, **kwargs)` validates the non-array arguments before the program is
    looked up (inside it they are tracers). The image is converted by `as_float` first, so Python
    numbers and tuples keep their weak type."""

    def wrap(fn):
        program = jax.jit(fn, static_argnames=static)

        @functools.wraps(fn)
        def call(c, *args, **kwargs):
            if check is not None:
                check(*args, **kwargs)
            if not _eager((c, args, kwargs)):
                return fn(c, *args, **kwargs)
            return program(_as_float(c), *args, **kwargs)

        return call

    return wrap


# ----------------------------------------------------------------------------------------------------- exposure


@_one_program()
def exposure(c, ev):
    """Scale linear radiance by ``2**ev`` (photographic exposure in stops).

    Args:
      c: (...,) linear radiance (any shape, e.g. ``(..., 3)`` RGB).
      ev: exposure value in stops; a scalar or an array that broadcasts against ``c`` (for one exposure per
        image of a batch ``(B, H, W, 3)`` pass ``ev[:, None, None, None]``). It is cast to ``c``'s dtype.

    Returns:
      ``c * 2**ev``, same shape (broadcast) and dtype as ``c``. Integer ``ev`` gives exact powers of two.
    """
    c = _as_float(c)
    ev = jnp.asarray(ev, dtype=c.dtype)
    # 2**ev = 2**n * 2**f with n = floor(ev), f in [0, 1): the integer part is an exact scaling
    # (ldexp) on every backend and f = 0 multiplies by exactly 1, so integer stops are exact.
    # Neither `2.0 ** ev` nor exp2(0) is exact in float64 on a GPU (measured on an H100: one ulp
    # low), only in the CPU's libm.
    finite = jnp.isfinite(ev)
    n = jnp.floor(jnp.where(finite, ev, 0.0))  # double where: ev - floor(ev) is NaN at +-inf
    f = jnp.where(finite, ev, 0.0) - n
    e = jnp.exp2(f)
    # exactly 1 at f = 0 (1 - e is exact there, Sterbenz), with exp2's derivative kept
    e = e + jax.lax.stop_gradient(jnp.where(f == 0, 1.0 - e, 0.0))
    out = _scale_pow2(c * e, n)
    return jnp.where(finite, out, c * 2.0**ev)  # +-inf stops: inf or 0, as 2**ev gives


def _scale_pow2(x, n):
    """x * 2**n, exact wherever the result is a normal float: n (integer-valued, any float dtype)
    is applied as three multiplications by powers of two made from their bit patterns.
    `jnp.ldexp` is not exact off the CPU: it computes the power as a float `2 ** e`."""
    if x.dtype == jnp.float64:
        mant, bias, itype = 52, 1023, jnp.int64
    elif x.dtype == jnp.float32:
        mant, bias, itype = 23, 127, jnp.int32
    else:  # half precisions: through float32, whose range holds every result of theirs
        return _scale_pow2(x.astype(jnp.float32), n).astype(x.dtype)
    step = bias - 1  # 2**k is a normal float for |k| <= bias - 1
    # Past +-(2 step + mant + 2) every finite x is scaled to 0 or inf: three steps reach that far.
    rest = jnp.clip(n, -(2 * step + mant + 2), 2 * step + mant + 2).astype(itype)
    for _ in range(3):
        k = jnp.clip(rest, -step, step)
        x = x * jax.lax.bitcast_convert_type((k + bias) << mant, x.dtype)
        rest = rest - k
    return x


# --------------------------------------------------------------------------------------------------- tone maps


@_one_program()
def reinhard(c):
    """Reinhard tone map ``c / (c + 1)``, per channel (the LearnOpenGL HDR form of Reinhard et al. 2002, eq. 3).

    Args:
      c: (...,) linear radiance, ``>= 0`` (usually ``(..., 3)`` RGB; each channel is mapped independently).

    Returns:
      Values in ``[0, 1]``, same shape and dtype. Negative inputs (outside the domain; ``c = -1`` would divide
      by zero) are mapped to 0 with zero gradient; NaN stays NaN; ``+inf`` maps to 1 (via the exact rewrite
      ``1 / (1 + 1/c)`` used for ``c > 1``).
    """
    c = _clamp_negative(_as_float(c))
    # For c > 1 use the exact rewrite 1 / (1 + 1/c): c / (c + 1) is inf/inf = NaN at c = +inf.
    big = c > 1.0
    inv = 1.0 / jnp.where(big, c, 1.0)
    return jnp.where(big, 1.0 / (1.0 + inv), c / (c + 1.0))


def _rrt_and_odt_fit(v):
    """Hill's ``RRTAndODTFit``: ``(v(v + 0.0245786) - 0.000090537) / (v(0.983729 v + 0.4329510) + 0.238081)``.

    The denominator has no real root, so it is finite for every finite ``v``. For ``|v| > 1`` numerator and
    denominator are divided by ``v**2`` (an exact rewrite) so that huge radiance (``v**2`` overflows float32
    above ~1.8e19) still saturates to ``1/0.983729`` instead of giving ``inf/inf = NaN``.
    """
    big = jnp.abs(v) > 1.0
    vs = jnp.where(big, 1.0, v)  # double where: each branch only ever sees inputs it is finite for
    small = (vs * (vs + 0.0245786) - 0.000090537) / (vs * (0.983729 * vs + 0.4329510) + 0.238081)
    t = 1.0 / jnp.where(big, v, 1.0)
    large = (1.0 + t * (0.0245786 - 0.000090537 * t)) / (0.983729 + t * (0.4329510 + 0.238081 * t))
    return jnp.where(big, large, small)


@_one_program()
def aces_fitted(c):
    """ACES filmic tone map, Stephen Hill's fit of the RRT + sRGB ODT (BakingLab ``ACESFitted``).

    ``out = clamp(M_out · RRTAndODTFit(M_in · c), 0, 1)`` with ``M_in`` (sRGB → RRT_SAT), ``M_out``
    (ODT_SAT → sRGB) and ``RRTAndODTFit(v) = (v(v + 0.0245786) − 0.000090537) / (v(0.983729 v + 0.4329510)
    + 0.238081)`` exactly as published. The result is still *linear* display RGB: apply :func:`srgb_encode`
    afterwards (as BakingLab does).

    Args:
      c: (..., 3) linear scene-referred sRGB/Rec.709 radiance.

    Returns:
      (..., 3) values in ``[0, 1]``, same dtype. Finite for all finite inputs (and for ``+inf``). Negative
      channels (outside the domain) are treated as 0 before the input matrix.
    """
    c = _as_float(c)
    _check_rgb(c, "aces_fitted")
    c = _clamp_negative(c)
    v = _rrt_and_odt_fit(_mat3(_ACES_INPUT, c))
    return jnp.clip(_mat3(_ACES_OUTPUT, v), 0.0, 1.0)


@_one_program()
def aces_narkowicz(c):
    """Krzysztof Narkowicz's ACES curve fit, per channel.

    ``clamp(x(2.51x + 0.03) / (x(2.43x + 0.59) + 0.14), 0, 1)``.

    (Narkowicz applies it to radiance pre-scaled by 0.6; this function does not scale, use :func:`exposure`.)

    Args:
      c: (...,) linear radiance, usually ``(..., 3)``; channels are mapped independently.

    Returns:
      Values in ``[0, 1]``, same shape and dtype; negative inputs (outside the domain) are treated as 0.
      The denominator has no real root; for ``x > 1`` the exact rewrite divided by ``x**2`` is used so huge
      inputs saturate to 1 instead of overflowing to NaN.
    """
    x = _clamp_negative(_as_float(c))
    big = jnp.abs(x) > 1.0
    xs = jnp.where(big, 1.0, x)
    small = xs * (2.51 * xs + 0.03) / (xs * (2.43 * xs + 0.59) + 0.14)
    t = 1.0 / jnp.where(big, x, 1.0)
    large = (2.51 + 0.03 * t) / (2.43 + t * (0.59 + 0.14 * t))
    return jnp.clip(jnp.where(big, large, small), 0.0, 1.0)


@_one_program(static=("operator",))
def tonemap(c, operator):
    """Apply a tone-mapping operator by name.

    Args:
      c: (..., 3) linear scene-referred radiance (``"none"``, ``"clamp"``, ``"reinhard"`` and
        ``"aces_narkowicz"`` also accept any shape, they act per channel).
      operator: one of :data:`TONEMAP_OPERATORS` (a static Python string):
        ``"none"`` / ``"clamp"`` — no curve, just clip to ``[0, 1]``; ``"reinhard"`` — :func:`reinhard`;
        ``"aces"`` — :func:`aces_fitted`; ``"aces_narkowicz"`` — :func:`aces_narkowicz`.

    Returns:
      Linear display values in ``[0, 1]``, same shape and dtype; encode them with :func:`encode`.

    Raises:
      ValueError: unknown operator (the message lists the valid names).
    """
    if operator in ("none", "clamp"):
        return jnp.clip(_as_float(c), 0.0, 1.0)
    if operator == "reinhard":
        return reinhard(c)
    if operator == "aces":
        return aces_fitted(c)
    if operator == "aces_narkowicz":
        return aces_narkowicz(c)
    raise ValueError(
        f"unknown tone-mapping operator {operator!r}; choose one of {', '.join(map(repr, TONEMAP_OPERATORS))}"
    )


# ----------------------------------------------------------------------------------------- transfer functions


@_one_program(check=lambda gamma=2.2: _check_gamma(gamma))
def gamma_encode(c, gamma=2.2):
    """Pure power-law display encoding ``max(c, 0) ** (1 / gamma)`` (LearnOpenGL's "gamma correction").

    Args:
      c: (...,) linear values, any shape.
      gamma: display gamma, ``> 0`` (default 2.2).

    Returns:
      Encoded values, same shape and dtype. The gradient at ``c <= 0`` is 0 (the true derivative at 0 is
      infinite; the double-``where`` keeps it finite). NaN stays NaN.
    """
    _check_gamma(gamma)
    return _safe_pow(_as_float(c), 1.0 / gamma)


@_one_program(check=lambda gamma=2.2: _check_gamma(gamma))
def gamma_decode(c, gamma=2.2):
    """Inverse of :func:`gamma_encode`: ``max(c, 0) ** gamma``.

    Args:
      c: (...,) gamma-encoded values, any shape.
      gamma: display gamma, ``> 0`` (default 2.2).

    Returns:
      Linear values, same shape and dtype; gradient 0 at ``c <= 0``; NaN stays NaN.
    """
    _check_gamma(gamma)
    return _safe_pow(_as_float(c), gamma)


def _safe_pow(x, p):
    """``max(x, 0) ** p`` with finite value and gradient (w.r.t. ``x`` and ``p``) everywhere.

    Double where: masking only the output would still differentiate ``0 ** p`` (infinite for ``p < 1``, and
    ``log 0`` in the ``p`` gradient), and ``0 * inf`` is NaN in the chain rule.
    """
    ok = ~(x <= 0.0)  # True for x > 0 and for NaN, so NaN propagates instead of becoming 0
    safe = jnp.where(ok, x, 1.0)
    return jnp.where(ok, safe**p, 0.0)


@_one_program()
def srgb_encode(c):
    """Linear → sRGB-encoded, the exact IEC 61966-2-1 piecewise transfer function (inverse EOTF).

    ``V = 12.92 L`` for ``L <= 0.0031308``, else ``V = 1.055 L**(1/2.4) − 0.055``. Negative inputs follow the
    linear segment (as colour-science does); values above 1 follow the power segment. No clipping.

    Args:
      c: (...,) linear values, any shape.

    Returns:
      Encoded values, same shape and dtype. Gradients are finite everywhere (12.92 at and below the knee).
    """
    c = _as_float(c)
    ok = _above(c, _SRGB_LINEAR_KNEE)
    safe = jnp.where(ok, c, 1.0)  # double where: the power's gradient at 0 is infinite
    return jnp.where(ok, 1.055 * safe ** (1.0 / 2.4) - 0.055, 12.92 * c)


@_one_program()
def srgb_decode(c):
    """sRGB-encoded → linear, the exact IEC 61966-2-1 EOTF.

    ``L = V / 12.92`` for ``V <= 0.04045``, else ``L = ((V + 0.055) / 1.055) ** 2.4``. Negative inputs follow
    the linear segment. (colour-science switches at ``12.92 * 0.0031308 = 0.040449936`` instead of the published
    0.04045; inside that 6.4e-8-wide sliver the two differ by at most 2.4e-9.)

    Args:
      c: (...,) encoded values, any shape (e.g. 8-bit PNG code values divided by 255).

    Returns:
      Linear values, same shape and dtype; gradients finite everywhere.
    """
    c = _as_float(c)
    ok = _above(c, _SRGB_ENCODED_KNEE)
    safe = jnp.where(ok, c, 1.0)
    return jnp.where(ok, ((safe + 0.055) / 1.055) ** 2.4, c / 12.92)


@_one_program(static=("transfer",))
def encode(c, transfer):
    """Apply a display transfer function by name.

    Args:
      c: (...,) linear display values (usually the output of :func:`tonemap`).
      transfer: one of :data:`TRANSFERS` (a static Python string): ``"srgb"`` — :func:`srgb_encode`;
        ``"gamma2.2"`` — :func:`gamma_encode` with gamma 2.2; ``"linear"`` — unchanged.

    Returns:
      Encoded values, same shape and dtype (not clipped).

    Raises:
      ValueError: unknown transfer (the message lists the valid names).
    """
    if transfer == "srgb":
        return srgb_encode(c)
    if transfer == "gamma2.2":
        return gamma_encode(c, 2.2)
    if transfer == "linear":
        return _as_float(c)
    raise ValueError(f"unknown transfer function {transfer!r}; choose one of {', '.join(map(repr, TRANSFERS))}")


# ------------------------------------------------------------------------------------ host side (colour-science)


def _colour():
    """Import colour-science lazily (it takes ~1.5 s and warns about optional matplotlib on import)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Mm]atplotlib.*")
        import colour
    return colour


def _np_float(c):
    c = np.asarray(c)
    if not np.issubdtype(c.dtype, np.floating):
        c = c.astype(np.float64)
    return c


def _cctf_np(c, function_name: str):
    """Apply colour-science's sRGB ``cctf_encoding`` / ``cctf_decoding`` in float64, keeping c's float dtype."""
    colour = _colour()
    c = _np_float(c)
    with colour.domain_range_scale("ignore"):
        out = getattr(colour, function_name)(c.astype(np.float64), function="sRGB")
    return np.asarray(out, dtype=c.dtype)


def srgb_encode_np(c):
    """Host-side linear → sRGB encoding through colour-science (``colour.cctf_encoding(c, function="sRGB")``).

    This is the exact IEC 61966-2-1 inverse EOTF (see :func:`srgb_encode`), evaluated in float64 by
    colour-science; :func:`jaxpbr.io.image.write` uses it for ``encoding="srgb"``.

    Args:
      c: array-like of linear values, any shape (NumPy or JAX array).

    Returns:
      NumPy array of encoded values, same shape; same floating dtype as the input (integers give float64).
    """
    return _cctf_np(c, "cctf_encoding")


def srgb_decode_np(c):
    """Host-side sRGB-encoded → linear through colour-science (``colour.cctf_decoding(c, function="sRGB")``).

    Args:
      c: array-like of encoded values in ``[0, 1]`` scale, any shape.

    Returns:
      NumPy array of linear values, same shape; same floating dtype as the input (integers give float64).
    """
    return _cctf_np(c, "cctf_decoding")


_tonemap = tonemap  # `display`'s keyword of the same name hides the function inside it


def _display(hdr, ev, *, tonemap: str, encoding: str):
    """Linear HDR -> display values: `exposure` by `ev` stops, `tonemap`, then `encode`, as one
    compiled program (op by op they were a dozen compilations; the host-side sRGB of
    `jaxpbr.io.image.write` imports colour-science). Kept on disk with the render stages where the
    command line keeps them (`jaxpbr._program_cache`)."""
    return encode(_tonemap(exposure(hdr, ev), tonemap), encoding)


display = cached_jit(_display, static_argnames=("tonemap", "encoding"), cpu_options=LOOP_EMITTERS)
