"""The mosaic's log intensity fitted to the events themselves (a refinement of seed 000's EKF + Poisson).

The gradient filter sees each event through a linearisation: a step of C along the ray's short slide
since the pixel's last event, read as the gradient at one pixel. That is weak where the slide is long or
crosses a sharp edge, and a camera that mostly pans sees its vertical gradients barely at all. Yet
each event states something exact: the log intensity where the pixel's ray points now minus where it
pointed at the pixel's previous event is +-C, however far apart the two are. So a sample of those
pairs (a, b, polarity) pins the panorama L directly: L(b) - L(a) = +-C, L read bilinearly. With the
filter's gradients as a weak prior (they fill what no pair reaches) the least-squares L solves

    (A^T A + w D^T D) L = A^T z + w D^T g

by conjugate gradients, started from the Poisson reconstruction and preconditioned by the same
transforms with the pairs' mean horizontal and vertical reach (A: the pairs, D: pixel differences).
"""

from __future__ import annotations

import numba
import numpy as np
from scipy.sparse.linalg import LinearOperator, cg

from services.mapper.poisson import differences, divergence, solve_laplacian


def fit(pairs: np.ndarray, steps: np.ndarray, gx: np.ndarray, gy: np.ndarray, observed: np.ndarray,
        initial: np.ndarray, prior_weight: float, iterations: int) -> np.ndarray:
    """The log intensity (H x W float32) that fits the pairs (N x 4 float32: u, v of a then of b, panorama
    pixels; b's longitude unwrapped next to a's) and their log-intensity steps (N), with the gradient map
    (gx, gy) weighted by `prior_weight`; `iterations` of conjugate gradients from `initial`."""
    h, w = gx.shape
    pairs = np.ascontiguousarray(pairs, np.float32)
    steps = np.ascontiguousarray(steps, np.float64)
    reach = max(int(observed.sum()), 1)
    along_u = float(np.sum((pairs[:, 2] - pairs[:, 0]).astype(np.float64) ** 2)) / reach
    along_v = float(np.sum((pairs[:, 3] - pairs[:, 1]).astype(np.float64) ** 2)) / reach
    dx, dy = differences(gx, gy)
    rhs = np.zeros((h, w))
    _spread(steps, pairs, rhs)
    rhs -= prior_weight * divergence(dx, dy)
    residual = np.empty(len(pairs))

    def normal(x: np.ndarray) -> np.ndarray:
        L = x.reshape(h, w)
        _steps(L, pairs, residual)
        out = np.zeros((h, w))
        _spread(residual, pairs, out)
        ldx, ldy = np.roll(L, -1, axis=1) - L, L[1:] - L[:-1]
        out -= prior_weight * divergence(ldx, ldy)
        return out.ravel()

    def precondition(r: np.ndarray) -> np.ndarray:
        return solve_laplacian(r.reshape(h, w), along_u + prior_weight, along_v + prior_weight).ravel()

    n = h * w
    x, _ = cg(LinearOperator((n, n), normal), rhs.ravel(), x0=np.asarray(initial, np.float64).ravel(),
              M=LinearOperator((n, n), precondition), maxiter=iterations, rtol=1e-9)
    out = x.reshape(h, w)
    return (out - out[observed].mean() if observed.any() else out).astype(np.float32)


@numba.njit(cache=True, nogil=True, inline="always")
def _corners(u, v, w, h):  # bilinear cells of (u, v): longitude wraps, latitude clamps
    u0, v0 = np.floor(u), np.floor(v)
    iu = int(u0) % w
    iv = min(max(int(v0), 0), h - 1)
    return iu, (iu + 1) % w, iv, min(iv + 1, h - 1), u - u0, v - v0


@numba.njit(cache=True, nogil=True)
def _steps(L, pairs, out):  # noqa: ANN001, ANN202 - numba kernel: out = L(b) - L(a), per pair
    h, w = L.shape
    for e in range(len(pairs)):
        s = 0.0
        for col, sign in ((0, -1.0), (2, 1.0)):
            iu, iu1, iv, iv1, fu, fv = _corners(pairs[e, col], pairs[e, col + 1], w, h)
            s += sign * ((1 - fu) * (1 - fv) * L[iv, iu] + fu * (1 - fv) * L[iv, iu1]
                         + (1 - fu) * fv * L[iv1, iu] + fu * fv * L[iv1, iu1])
        out[e] = s


@numba.njit(cache=True, nogil=True)
def _spread(r, pairs, out):  # noqa: ANN001, ANN202 - numba kernel: the adjoint of _steps, added to out
    h, w = out.shape
    for e in range(len(pairs)):
        for col, sign in ((0, -1.0), (2, 1.0)):
            iu, iu1, iv, iv1, fu, fv = _corners(pairs[e, col], pairs[e, col + 1], w, h)
            x = sign * r[e]
            out[iv, iu] += (1 - fu) * (1 - fv) * x
            out[iv, iu1] += fu * (1 - fv) * x
            out[iv1, iu] += (1 - fu) * fv * x
            out[iv1, iu1] += fu * fv * x
