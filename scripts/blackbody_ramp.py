"""A blackbody's colour for Cycles, as volgrad defines it (src/volume/blackbody.rs: Planck's law
normalised to 1 at its peak, as pbrt-v4's BlackbodySpectrum; Wyman, Sloan and Shirley's fit of the
CIE 1931 colour-matching functions; linear sRGB, negative channels clamped to 0), written again
here in numpy from the same formulas.

Cycles' own Blackbody node has another normalisation, so the colour goes into the node tree as a
table: a Color Ramp (at most 32 stops, linear) over u = 1/T of ln(XYZ·T⁵). The peak's radiance is
∝ T⁵ (Planck at λ = b/T), so XYZ·T⁵ is Planck's unnormalised integral, whose logarithm is nearly
linear in 1/T (Wien's tail); the node tree multiplies T⁻⁵ back exactly and applies the sRGB
matrix and the clamp. `ramp_error` says how far the table is from the formula over its range.
"""

import numpy as np

H, C, KB, WIEN = 6.626_070_15e-34, 2.997_924_58e8, 1.380_649e-23, 2.897_771_955e-3
NM = np.arange(360, 831, dtype=np.float64)
XYZ_TO_SRGB = np.array(
    [
        [3.240_454_2, -1.537_138_5, -0.498_531_4],
        [-0.969_266_0, 1.876_010_8, 0.041_556_0],
        [0.055_643_4, -0.204_025_9, 1.057_225_2],
    ]
)
STOPS = 32


def planck(lam, t):
    return 2.0 * H * C * C / (lam**5 * np.expm1(H * C / (lam * KB * t)))


def lobe(x, mean, below, above):
    t = (x - mean) * np.where(x < mean, below, above)
    return np.exp(-0.5 * t * t)


CMF = np.array(
    [
        1.056 * lobe(NM, 599.8, 0.0264, 0.0323)
        + 0.362 * lobe(NM, 442.0, 0.0624, 0.0374)
        - 0.065 * lobe(NM, 501.1, 0.0490, 0.0382),
        0.821 * lobe(NM, 568.8, 0.0213, 0.0247) + 0.286 * lobe(NM, 530.9, 0.0613, 0.0322),
        1.217 * lobe(NM, 437.0, 0.0845, 0.0278) + 0.681 * lobe(NM, 459.0, 0.0385, 0.0725),
    ]
)


def xyz(t):
    """The normalised blackbody's XYZ at `t` kelvin (Y of an equal-energy 1 is 1)."""
    b = planck(NM * 1e-9, t) / planck(WIEN / t, t)
    return CMF @ b / CMF[1].sum()


def srgb(t):
    return np.maximum(XYZ_TO_SRGB @ xyz(t), 0.0)


def ramp(lo, hi):
    """The table over [lo, hi] kelvin: (positions in [0, 1] along u = 1/T from 1/hi to 1/lo,
    each channel's ln(XYZ·T⁵) mapped to [0, 1], and the maps' (offset, span) per channel)."""
    u = np.linspace(1.0 / hi, 1.0 / lo, STOPS)
    logs = np.log(np.array([xyz(1.0 / v) * (1.0 / v) ** 5 for v in u]))
    offset, span = logs.min(axis=0), np.ptp(logs, axis=0)
    return np.linspace(0.0, 1.0, STOPS), (logs - offset) / span, offset, span


def from_ramp(t, lo, hi):
    """What the node tree computes at `t` kelvin (clamped to the ramp's range)."""
    positions, values, offset, span = ramp(lo, hi)
    t = min(max(t, lo), hi)
    fac = (1.0 / t - 1.0 / hi) / (1.0 / lo - 1.0 / hi)
    logs = np.array([np.interp(fac, positions, values[:, c]) for c in range(3)]) * span + offset
    return np.maximum(XYZ_TO_SRGB @ (np.exp(logs) * t**-5.0), 0.0)


def ramp_error(lo, hi):
    """The table's largest difference from the formula over [lo, hi], relative to the brightest
    channel there."""
    worst = 0.0
    for t in np.linspace(lo, hi, 1001):
        exact = srgb(t)
        worst = max(worst, np.abs(from_ramp(t, lo, hi) - exact).max() / max(exact.max(), 1e-300))
    return worst
