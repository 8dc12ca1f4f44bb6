"""Allan deviation of a sampled signal (overlapping estimator).

The Allan variance of a rate signal y sampled every ``dt`` seconds, at averaging time
``tau = m dt``, is half the mean square difference of consecutive averages over ``tau``.
With the integrated signal ``theta_k = dt * sum_{j<k} y_j`` (``theta_0 = 0``), the
overlapping estimator uses every start index, not only multiples of ``m``:

    sigma^2(tau) = 1 / (2 tau^2 (N - 2m))
                   * sum_{k=0}^{N-2m-1} (theta_{k+2m} - 2 theta_{k+m} + theta_k)^2

with ``N`` the number of points of ``theta`` (one more than the samples). This is the
estimator of IEEE Std 952-1997 (fiber optic gyros), Annex C, and IEEE Std 1293-2018
(accelerometers), Annex on Allan variance; see also El-Sheimy, Hou and Niu, "Analysis and
modeling of inertial sensors using Allan variance", IEEE Trans. Instrum. Meas. 57(1), 2008.

How to read the slopes (log-log, IEEE 952 Table C.1; ``N``, ``K`` below are the
coefficients in IEEE 952's convention, i.e. two-sided power spectral densities):

    white rate noise (angle/velocity random walk)   sigma = N / sqrt(tau)          slope -1/2
    bias instability (flicker)                       flat floor at 0.664 B          slope 0
    rate random walk (bias random walk)              sigma = K sqrt(tau / 3)        slope +1/2

For a discrete white sequence of standard deviation ``s`` per sample the exact value is
``s / sqrt(m)``; for a discrete random walk with increments of standard deviation ``q`` per
sample it is ``q sqrt((2 m^2 + 1) / (6 m))``. The tests check the estimator against both.
"""

from __future__ import annotations

import numpy as np


def default_cluster_sizes(num_samples: int, points_per_decade: int = 10) -> np.ndarray:
    """Log-spaced cluster sizes m = 1 .. (num_samples - 1) // 2, unique integers."""
    m_max = (num_samples - 1) // 2
    if m_max < 1:
        raise ValueError(f"need at least 3 samples for an Allan deviation, got {num_samples}")
    count = max(2, int(np.ceil(np.log10(m_max) * points_per_decade)) + 1)
    return np.unique(np.round(np.logspace(0.0, np.log10(m_max), count)).astype(int))


def allan_deviation(y, dt: float, cluster_sizes=None):
    """Overlapping Allan deviation of the rate samples ``y`` (IEEE Std 952, Annex C).

    Args:
        y: samples, shape (n,) or (n, k) for k signals (e.g. the three axes of a sensor)
            sampled together; each column is analysed on its own.
        dt: sample period (s).
        cluster_sizes: averaging lengths m in samples (tau = m dt); default
            ``default_cluster_sizes(n)`` (log-spaced up to n / 2).

    Returns:
        ``(tau, adev)``: tau (s) of shape (len(m),) and the Allan deviation in the units of
        ``y``, shape (len(m),) or (len(m), k).
    """
    y = np.asarray(y, dtype=float)
    squeeze = y.ndim == 1
    if squeeze:
        y = y[:, None]
    n = y.shape[0]
    m = default_cluster_sizes(n) if cluster_sizes is None else np.asarray(cluster_sizes, int)
    if np.any(m < 1) or np.any(2 * m > n):
        raise ValueError(f"cluster sizes must lie in [1, {n // 2}] for {n} samples")
    # theta_k = dt * sum_{j<k} y_j, k = 0..n; the mean is removed first because it cancels
    # in the second difference but would cost precision in a long cumulative sum.
    theta = np.zeros((n + 1, y.shape[1]))
    np.cumsum((y - y.mean(axis=0)) * dt, axis=0, out=theta[1:])
    adev = np.empty((len(m), y.shape[1]))
    for i, mi in enumerate(m):
        d = theta[2 * mi:] - 2.0 * theta[mi:-mi] + theta[:-2 * mi]
        tau = mi * dt
        adev[i] = np.sqrt(np.mean(d * d, axis=0) / (2.0 * tau * tau))
    tau = m * dt
    return tau, (adev[:, 0] if squeeze else adev)


def white_noise_coefficient(tau, adev, tau_max: float = 1.0) -> float:
    """Least-squares N of ``adev = N / sqrt(tau)`` over ``tau <= tau_max`` (IEEE 952 units:
    the white-noise level of a two-sided power spectral density)."""
    tau = np.asarray(tau, float)
    adev = np.asarray(adev, float)
    keep = tau <= tau_max
    return float(np.exp(np.mean(np.log(adev[keep] * np.sqrt(tau[keep])))))


def log_log_slope(tau, adev, tau_min: float, tau_max: float) -> float:
    """Slope of log(adev) against log(tau) fitted over [tau_min, tau_max]."""
    tau = np.asarray(tau, float)
    adev = np.asarray(adev, float)
    keep = (tau >= tau_min) & (tau <= tau_max)
    if keep.sum() < 2:
        raise ValueError("fewer than two points in the fitting range")
    return float(np.polyfit(np.log(tau[keep]), np.log(adev[keep]), 1)[0])
