"""Directions in the local shading frame: z is the normal, wi points away from the surface."""
import numpy as np

# Rec. 709 / sRGB luminance weights (what Mitsuba's luminance() uses for RGB).
LUMINANCE = np.array([0.212671, 0.715160, 0.072169])


def luminance(rgb):
    # As one 2D product: numpy's matmul of a stack (ndim > 2) by a vector loops per row, ~90x
    # slower on the baker's (cells, nodes, 3) arrays; the 2D product gives the same bits.
    rgb = np.asarray(rgb)
    if rgb.ndim <= 2:
        return rgb @ LUMINANCE
    return (rgb.reshape(-1, 3) @ LUMINANCE).reshape(rgb.shape[:-1])


def spherical_dir(theta, phi):
    theta, phi = np.broadcast_arrays(np.asarray(theta, float), np.asarray(phi, float))
    s = np.sin(theta)
    return np.stack([s * np.cos(phi), s * np.sin(phi), np.cos(theta)], axis=-1)


def atan2(y, x):
    """np.arctan2 of contiguous copies: numpy's arctan2 of a strided view (w[:, 1], w[:, 0]) gave
    other bits (1 ulp) in some of the baker's threads than in the main thread, so a bake's tables
    depended on which thread built a bin (measured: 2 bakes in 30 differed; 7 of 720 threaded
    calls on the half vectors of a bin's points); on contiguous arrays, the same bits in every
    thread. For arrays the baker's threads reach; a scalar needs none of it."""
    return np.arctan2(np.ascontiguousarray(y, float), np.ascontiguousarray(x, float))


def theta_phi(w):
    """Elevation in [0, pi] and azimuth in (-pi, pi]; atan2 keeps precision near the pole."""
    x, y, z = (np.ascontiguousarray(w[..., k], float) for k in range(3))
    return atan2(np.hypot(x, y), z), atan2(y, x)


def reflect(wi, m):
    return 2.0 * np.sum(wi * m, axis=-1, keepdims=True) * m - wi


def normalize(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def incident(theta_i_deg, phi_i=0.0):
    """The incident direction for an elevation in degrees (the usual way tests name wi)."""
    return spherical_dir(np.radians(theta_i_deg), phi_i)
