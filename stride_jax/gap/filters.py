"""Cleaning and estimation on logged trajectories (:mod:`stride_jax.gap.logs`), before replay.

:func:`resample` puts a log onto the control grid (linear for states, normalised linear for
quaternions, zero-order hold for commands and IMU; :func:`interp`, :func:`interp_quat` and
:func:`hold` do it per signal, for logs whose signals have their own clocks); :func:`spikes` and :func:`hampel` remove
outliers; :func:`savgol` smooths and differentiates (:func:`savgol_bandwidth` states its -3 dB
frequency); :func:`noise_std` estimates the white-noise level from second differences.
:class:`Preprocess` configures and :func:`preprocess` applies the cleaning the diagnosis uses;
:func:`acceleration` estimates joint accelerations (the logs hold none).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from stride_jax.gap.logs import Trajectory


def interp(t_src: np.ndarray, x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Linear interpolation of ``x [N, C]`` sampled at increasing ``t_src [N]`` onto ``t [T]``."""
    return np.stack([np.interp(t, t_src, x[:, i]) for i in range(x.shape[1])], axis=1)


def hold(t_src: np.ndarray, x: np.ndarray, t: np.ndarray, dt: float) -> np.ndarray:
    """Zero-order hold: at each ``t`` the last sample of ``x [N, ...]`` at or before it (within
    ``1e-9 dt``; the first sample before the log starts)."""
    return x[np.clip(np.searchsorted(t_src, t + 1e-9 * dt, side="right") - 1, 0, len(t_src) - 1)]


def interp_quat(t_src: np.ndarray, quat: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Normalised linear interpolation of unit quaternions ``[N, 4]`` (signs aligned to the first)."""
    quat = quat * np.sign((quat * quat[:1]).sum(1, keepdims=True))
    out = interp(t_src, quat, t)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def resample(tr: Trajectory, dt: float) -> Trajectory:
    """Onto the uniform grid ``t0 + k dt`` inside the log: states and torques linearly,
    the quaternion by normalised linear interpolation, commands and IMU by zero-order hold."""
    t = tr.t[0] + dt * np.arange(int(np.floor((tr.t[-1] - tr.t[0]) / dt + 1e-9)) + 1)
    if len(t) == len(tr.t) and np.allclose(t, tr.t, atol=1e-6 * dt):
        return tr
    q = interp(tr.t, tr.q, t)
    if tr.q.shape[1] >= 7 and tr.qd.shape[1] == tr.q.shape[1] - 1:  # free joint: renormalise
        q[:, 3:7] = interp_quat(tr.t, tr.q[:, 3:7], t)
    held = lambda x: None if x is None else hold(tr.t, x, t, dt)
    return Trajectory(tr.name, t, q, interp(tr.t, tr.qd, t), held(tr.cmd),
                      None if tr.tau is None else interp(tr.t, tr.tau, t), held(tr.imu))


def hampel(x: np.ndarray, half_window: int = 3, k: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """Hampel outlier filter along axis 0: a sample further than ``k`` robust standard deviations
    (1.4826 MAD) from the median of its ``2 half_window + 1`` neighbours is replaced by that median.

    ``x [T, ...]``; returns ``(cleaned [T, ...], outlier mask [T, ...])``.
    """
    x = np.asarray(x, np.float64)
    pad = np.pad(x, [(half_window, half_window)] + [(0, 0)] * (x.ndim - 1), mode="edge")
    win = np.lib.stride_tricks.sliding_window_view(pad, 2 * half_window + 1, axis=0)
    med = np.median(win, axis=-1)
    mad = 1.4826 * np.median(np.abs(win - med[..., None]), axis=-1)
    out = np.abs(x - med) > k * np.maximum(mad, 1e-12)
    return np.where(out, med, x), out


def savgol(x: np.ndarray, dt: float, window: int, order: int = 3, deriv: int = 0) -> np.ndarray:
    """Savitzky-Golay smoothing (``deriv=0``) or derivative of ``x [T, ...]`` sampled every ``dt`` s.

    ``window`` is an odd number of samples; see :func:`savgol_bandwidth` for the pass band.
    """
    from scipy.signal import savgol_filter

    if window % 2 == 0 or window <= order:
        raise ValueError(f"savgol window must be odd and larger than order {order}, got {window}")
    if len(x) < window:
        raise ValueError(f"savgol needs at least {window} samples, got {len(x)}")
    return savgol_filter(np.asarray(x, np.float64), window, order, deriv=deriv, delta=dt, axis=0,
                         mode="interp")


def savgol_bandwidth(dt: float, window: int, order: int = 3) -> float:
    """The -3 dB frequency (Hz) of the Savitzky-Golay smoother (its centre-point response)."""
    from scipy.signal import freqz, savgol_coeffs

    w, h = freqz(savgol_coeffs(window, order), worN=4096, fs=1.0 / dt)
    below = np.flatnonzero(np.abs(h) < 1 / np.sqrt(2))
    return float(w[below[0]]) if len(below) else float(w[-1])


def noise_std(x: np.ndarray) -> np.ndarray:
    """Robust white-noise level per channel of ``x [T, C]``: 1.4826 MAD of second differences / sqrt(6).

    Exact for white noise on a signal whose second difference is small; an upper bound otherwise.
    """
    d2 = np.diff(np.asarray(x, np.float64), n=2, axis=0)
    return 1.4826 * np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0) / np.sqrt(6.0)


def spikes(x: np.ndarray, k: float = 8.0) -> tuple[np.ndarray, np.ndarray]:
    """Isolated one-sample spikes along axis 0 of ``x [T, C]``, replaced by the mean of their
    neighbours: the sample leaves the neighbours' mean by more than ``k`` robust standard deviations
    of the channel's second difference while the two neighbours agree (within half that jump).
    Steps (impacts: the level changes and stays) are kept, unlike a plain Hampel filter's
    treatment of fast legitimate transients. Returns ``(cleaned, mask)``."""
    x = np.asarray(x, np.float64).copy()
    mask = np.zeros(x.shape, bool)
    if len(x) < 3:
        return x, mask
    mid = 0.5 * (x[:-2] + x[2:])
    dev = x[1:-1] - mid
    sig = 1.4826 * np.median(np.abs(np.diff(x, 2, axis=0)), axis=0) + 1e-12
    hit = (np.abs(dev) > k * sig) & (np.abs(x[2:] - x[:-2]) < 0.5 * np.abs(dev))
    mask[1:-1] = hit
    x[1:-1] = np.where(hit, mid, x[1:-1])
    return x, mask


@dataclasses.dataclass(frozen=True)
class Preprocess:
    """How logged states are cleaned before replay.

    Attributes:
      outliers: replace isolated spikes in the joint/base velocities (:func:`spikes` with ``k``).
      smooth_window: Savitzky-Golay window (samples, odd) for q and qd; 0 disables smoothing.
      smooth_order: its polynomial order.
    """

    outliers: bool = True
    k: float = 8.0
    smooth_window: int = 0
    smooth_order: int = 3

    def bandwidth_hz(self, dt: float) -> float | None:
        return savgol_bandwidth(dt, self.smooth_window, self.smooth_order) if self.smooth_window else None


def preprocess(tr: Trajectory, dt: float, cfg: Preprocess) -> tuple[Trajectory, dict]:
    """Resamples onto the control grid, removes outliers, optionally smooths. Returns the cleaned
    trajectory and a summary (outlier counts, noise estimates)."""
    tr = resample(tr, dt)
    q, qd = tr.q.copy(), tr.qd.copy()
    n_out = 0
    if cfg.outliers:
        qd, m1 = spikes(qd, cfg.k)
        n_out = int(m1.sum())
    if cfg.smooth_window and len(q) >= cfg.smooth_window:
        fb = q.shape[1] == qd.shape[1] + 1
        q = savgol(q, dt, cfg.smooth_window, cfg.smooth_order)
        qd = savgol(qd, dt, cfg.smooth_window, cfg.smooth_order)
        if fb:
            q[:, 3:7] /= np.linalg.norm(q[:, 3:7], axis=1, keepdims=True)
    info = {"outliers_replaced": n_out, "qd_noise_std": noise_std(tr.qd).tolist()}
    return tr._replace(q=q, qd=qd), info


def acceleration(tr: Trajectory, dt: float, window: int = 7, order: int = 3) -> np.ndarray:
    """Joint accelerations ``[T, nv]`` by Savitzky-Golay differentiation of the velocities.

    Pass band: :func:`savgol_bandwidth(dt, window, order)`; meaningless across impacts (the
    velocity jumps), which is why the diagnosis compares one-step replays instead.
    """
    return savgol(tr.qd, dt, window, order, deriv=1)
