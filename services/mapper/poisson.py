"""Images from their differences on an equirectangular grid: columns wrap (longitude), rows do not.

Least squares over pixel differences leads to Laplacians, which transforms diagonalise exactly: an
FFT across the columns (periodic) and a cosine transform (DCT-II) down the rows (zero flux at the poles).
"""

from __future__ import annotations

import numpy as np
import scipy.fft


def differences(gx: np.ndarray, gy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradients given at pixel centres as the differences between neighbours they imply: between column
    i and i + 1 (wrapping; H x W) and between row j and j + 1 (H - 1 x W), each the mean of its two pixels'."""
    return 0.5 * (gx + np.roll(gx, -1, axis=1)), 0.5 * (gy[:-1] + gy[1:])


def divergence(dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Minus the adjoint of taking differences (H x W); divergence(differences of M) is M's Laplacian."""
    div = dx - np.roll(dx, 1, axis=1)
    div[:-1] += dy
    div[1:] -= dy
    return div


def solve_laplacian(rhs: np.ndarray, along_u: float, along_v: float) -> np.ndarray:
    """x with (along_u Dx^T Dx + along_v Dy^T Dy) x = rhs (D: differences), mean zero (the constant is free)."""
    h, w = rhs.shape
    spectrum = scipy.fft.rfft(scipy.fft.dct(np.asarray(rhs, np.float64), type=2, axis=0, norm="ortho"), axis=1)
    rows = 2 - 2 * np.cos(np.pi * np.arange(h) / h)
    cols = 2 - 2 * np.cos(2 * np.pi * np.arange(spectrum.shape[1]) / w)
    eigen = along_v * rows[:, None] + along_u * cols[None, :]
    eigen[0, 0] = 1.0
    spectrum /= eigen
    spectrum[0, 0] = 0.0
    return scipy.fft.idct(scipy.fft.irfft(spectrum, n=w, axis=1), type=2, axis=0, norm="ortho")


def poisson(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """The image M whose differences M[:, i+1] - M[:, i] and M[j+1] - M[j] best fit the gradients (given at
    pixel centres, see `differences`) in least squares; mean zero, float32."""
    return solve_laplacian(-divergence(*differences(gx, gy)), 1.0, 1.0).astype(np.float32)
