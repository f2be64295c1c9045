"""Tolerances for comparing a kernel with its reference, derived from the precision its matrix
products run in (the same test holds in Pallas' interpreter on a CPU and on a real GPU).

A product of length ``K`` whose inputs are rounded to a unit roundoff ``u`` carries an error of
about ``u * sqrt(K) * |x| |w|``; its value is of size ``sqrt(K) * |x| |w|`` too, so relative
to the output's scale each layer adds about ``u``, and ``layers`` layers compound it. Both
sides of a comparison may round (a GPU's XLA reference also runs float32 products in TF32), so
the bound counts both. ``SAFETY`` covers the constant of "about".

Where a linear solve follows the products (a model step), a condition-number bound is far too
loose to test anything (M's condition number is in the hundreds while the observed error stays
a few ``u``). There the tolerance is measured instead: :func:`rounded` gives the reference's
parameters rounded to the products' precision, and the reference's own change under that
rounding, times ``SAFETY``, bounds the kernel's error (which rounds weights and activations).
Both reference runs then compute in full float32 (:func:`exact`): on a GPU XLA's own products
already round to TF32, which would hide the change.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

SAFETY = 4.0


def roundoff(dtype=jnp.float32) -> float:
    """Unit roundoff of the matrix products as they run here: bfloat16 inputs 2^-8; float32 on a
    GPU in TF32 (10 mantissa bits, 2^-11) unless ``jax_default_matmul_precision`` asks for
    full float32; float32 elsewhere 2^-24."""
    if jnp.dtype(dtype) == jnp.bfloat16:
        return 2.0 ** -8
    precision = str(jax.config.jax_default_matmul_precision or "default").lower()
    if jax.default_backend() == "gpu" and precision not in ("highest", "float32"):
        return 2.0 ** -11
    return 2.0 ** -24


def exact():
    """A context in which XLA's float32 products are full float32 on every platform."""
    return jax.default_matmul_precision("highest")


def rounded(tree, dtype=jnp.float32):
    """``tree``'s floating arrays rounded to the mantissa of the products' precision here (see
    :func:`roundoff`): the reference run with these shows how much that rounding moves it."""
    bits = int(round(-np.log2(roundoff(dtype)))) - 1  # stored mantissa bits
    return jax.tree.map(lambda w: jax.lax.reduce_precision(w, exponent_bits=8, mantissa_bits=bits)
                        if jnp.issubdtype(w.dtype, jnp.floating) else w, tree)


def assert_close(actual, desired, *, floor: float, layers: int = 0, dtype=jnp.float32,
                 sensitivity=None, err_msg: str = "") -> None:
    """``|actual - desired| <= floor + SAFETY * e`` elementwise, where ``e`` is
    ``2 u * layers * max|desired|`` (products of ``layers`` layers, both sides rounding) or the
    measured ``sensitivity`` (``|reference(rounded) - reference|``, broadcast against the arrays).
    ``floor``: the float32 tolerance the comparison needs without any rounding of the products
    (transcendentals, summation order)."""
    actual, desired = np.asarray(actual, np.float64), np.asarray(desired, np.float64)
    assert actual.shape == desired.shape, f"{err_msg}: shape {actual.shape} != {desired.shape}"
    scale = float(np.max(np.abs(desired))) if desired.size else 0.0
    if sensitivity is None:
        assert layers > 0, "give the number of layers or a measured sensitivity"
        e = 2 * roundoff(dtype) * layers * scale
    else:
        e = np.asarray(sensitivity, np.float64)
    atol = np.broadcast_to(floor + SAFETY * e, desired.shape)
    assert np.all(atol < 0.5 * scale + floor), \
        f"{err_msg}: the tolerance ({np.max(atol):.2e}) would not detect an error at scale {scale:.3g}"
    np.testing.assert_array_less(np.abs(actual - desired), atol + np.finfo(np.float32).tiny,
                                 err_msg=f"{err_msg} (u = {roundoff(dtype):.1e}, "
                                         f"max atol {np.max(atol):.2e} at scale {scale:.3g})")
