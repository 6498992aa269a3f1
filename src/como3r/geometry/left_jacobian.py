"""The left Jacobian ``W(zeta, omega)`` of SE(3) and Sim(3): its scalar coefficients.

``W = A I + B Omega + C Omega^2`` with ``Omega = [omega]_x``, ``theta = |omega|`` (its
closed forms are in :mod:`como3r.geometry.lie`'s docstring). ``W`` acts on the rotation
axis as ``A`` and on the plane orthogonal to it as the complex number
``phi(zeta + i theta)``, ``phi(z) = (e^z - 1) / z``; this view gives both the numerically
careful evaluation below and the closed-form inverse used by ``Log``:

    W^-1 = (1/A) I - (B / den) Omega + ((B^2 - A C + C^2 theta^2) / (A den)) Omega^2,
    den = (A - C theta^2)^2 + (B theta)^2 = |phi(zeta + i theta)|^2.

The scalar coefficients are evaluated in float64 and cast back by the caller, which keeps
float32 exp/log accurate in the coupled small-angle / small-``zeta`` regime, where the
closed forms cancel catastrophically in single precision.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

# Below this |zeta| the float64 Sim(3) coefficients use a 10-term Taylor series (error < 3e-18);
# above it the closed forms lose at most ~1e-13 relative, which the callers multiply away.
_ZETA_SERIES = 0.1
# Below this rotation angle the float64 Sim(3) coefficients B, C take their theta -> 0 limits
# (truncation error theta^2 / 24 relative, i.e. < 1e-11, and B, C enter W multiplied by
# theta and theta^2). Above it the complex-exponential evaluation is accurate to
# eps / theta (B) and eps / theta^2 (C), again multiplied away.
_THETA_LIMIT = 1e-5
_SERIES_TERMS = 10


def _taylor_coefficients(order: int) -> list[float]:
    """Taylor coefficients of phi^(order)(zeta) / order!, phi(zeta) = (e^zeta - 1) / zeta."""
    return [
        math.comb(k + order, order) / math.factorial(k + order + 1) for k in range(_SERIES_TERMS)
    ]


_PHI_SERIES = torch.tensor([_taylor_coefficients(order) for order in range(3)], dtype=torch.float64)


def _horner(coefficients: Tensor, x: Tensor) -> Tensor:
    """The polynomials of the rows of ``coefficients`` ``(k, T)`` at ``x``, ``(k, *x.shape)``:
    all k in one pass, each entry the same float operations as one polynomial alone."""
    shape = (coefficients.shape[0],) + (1,) * x.ndim
    result = coefficients[:, -1].reshape(shape).expand(-1, *x.shape)
    for t in range(coefficients.shape[1] - 2, -1, -1):
        result = result * x + coefficients[:, t].reshape(shape)
    return result


def _branches(mask: Tensor) -> tuple[bool, bool]:
    """Whether any and whether every entry of ``mask`` holds, as far as it matters: off the
    CPU ``(True, False)`` (both sides of a ``torch.where`` computed, no device sync)."""
    if mask.device.type != "cpu":
        return True, False
    return bool(mask.any()), bool(mask.all())


def _phi_derivatives(zeta: Tensor, orders: int = 3) -> tuple[Tensor, ...]:
    """``phi(zeta)``, ``phi'(zeta)``, ``phi''(zeta) / 2`` for ``phi(z) = (e^z - 1) / z``, the
    first ``orders`` of them.

    ``phi`` is ``A``; its derivatives are the ``theta -> 0`` limits of ``B`` and ``C``
    (``phi' = int_0^1 u e^(u zeta) du``, ``phi'' / 2 = int_0^1 u^2 / 2 e^(u zeta) du``).
    Float64 in and out. A side of a ``torch.where`` that no entry takes is not computed (a
    solver's steps: every ``zeta`` in the series; the where then returns the same values).
    """
    small = zeta.abs() < _ZETA_SERIES
    any_small, all_small = _branches(small)
    series: tuple[Tensor, ...] = ()
    if any_small:
        z_series = torch.where(small, zeta, torch.zeros_like(zeta))
        series = tuple(_horner(_PHI_SERIES[:orders].to(zeta.device), z_series).unbind(0))
    if all_small:
        return series
    z = torch.where(small, torch.ones_like(zeta), zeta)
    exp_z, expm1_z = z.exp(), z.expm1()
    closed = (
        expm1_z / z,
        (z * exp_z - expm1_z) / (z * z),
        (z * z * exp_z - 2.0 * z * exp_z + 2.0 * expm1_z) / (2.0 * z * z * z),
    )[:orders]
    if not any_small:
        return closed
    return tuple(torch.where(small, s, value) for s, value in zip(series, closed))


def left_jacobian_coefficients(zeta: Tensor, theta_sq: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``A, B, C`` of ``W = A I + B Omega + C Omega^2`` (:mod:`como3r.geometry.lie` docstring). Float64 in and out.

    ``phi(zeta + i theta) = expm1(zeta + i theta) / (zeta + i theta)`` is evaluated with
    ``Re expm1(zeta + i theta) = expm1(zeta) cos(theta) - 2 sin^2(theta / 2)`` so that both of
    its parts are accurate to a few ulps of ``|zeta + i theta|`` for any small argument. As
    in :func:`_phi_derivatives`, a side of a ``torch.where`` no entry takes is skipped.
    """
    small = theta_sq < _THETA_LIMIT**2
    any_small, all_small = _branches(small)
    a, *limits = _phi_derivatives(zeta, 3 if any_small else 1)
    if all_small:
        b_limit, c_limit = limits
        return a, torch.where(small, b_limit, b_limit), torch.where(small, c_limit, c_limit)
    theta_sq = torch.where(small, torch.ones_like(theta_sq), theta_sq)
    theta = theta_sq.sqrt()
    re_expm1 = zeta.expm1() * theta.cos() - 2.0 * (0.5 * theta).sin() ** 2
    im_expm1 = zeta.exp() * theta.sin()
    abs_sq = zeta * zeta + theta_sq
    re_phi = (re_expm1 * zeta + im_expm1 * theta) / abs_sq
    im_phi = (im_expm1 * zeta - re_expm1 * theta) / abs_sq
    b, c = im_phi / theta, (a - re_phi) / theta_sq
    if any_small:
        b, c = torch.where(small, limits[0], b), torch.where(small, limits[1], c)
    return a, b, c


def left_jacobian_inverse_coefficients(
    zeta: Tensor, theta_sq: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Coefficients of ``W^-1`` (:mod:`como3r.geometry.lie` docstring); free of cancellation for small theta."""
    a, b, c = left_jacobian_coefficients(zeta, theta_sq)
    in_plane_real = a - c * theta_sq
    den = in_plane_real * in_plane_real + b * b * theta_sq
    return 1.0 / a, -b / den, (b * b - a * c + c * c * theta_sq) / (a * den)


def coefficient_inputs(omega: Tensor, zeta: Tensor | None) -> tuple[Tensor, Tensor]:
    theta_sq = (omega.double() ** 2).sum(-1, keepdim=True)
    zeta64 = torch.zeros_like(theta_sq) if zeta is None else zeta.double()
    return zeta64, theta_sq
