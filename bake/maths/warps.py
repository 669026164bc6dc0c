"""The maps between the unit square and directions that several modules share, each map
beside its inverse and its Jacobian (as pbrt-v4's util/sampling.h keeps them).

Directions are in the local shading frame (z = normal, wi pointing away from the surface).

    rotate_z(w, angle)          rotation about the normal; isotropic samplers work at
                                phi_i = 0 and turn the result back with it
    half_vector(u)              u in [0,1)² -> half vector m, u = (sqrt(2 theta_m / pi),
                                (phi_m + pi) / 2 pi): the RGL parameterization, whose sqrt
                                puts resolution near the normal, where microfacet lobes live
    u_of_half_vector(m)         its inverse
    dwo_du(wi, m, u1)           |d omega_o / d u| of wo = reflect(wi, m) at u = (u1, .):
                                4 (wi·m) sin(theta_m) pi u1 2 pi, zero where wi·m <= 0
    dwo_du_of(cos_im, sin_theta_m, u1)  the same from wi·m and sin(theta_m) (the ideal table's hot loop)

The ideal sampler (bake/core/ideal.py) tabulates over half_vector's square; the chi-square test
(bake/core/metrics.py) bins samples on it.
"""
import numpy as np

from .geometry import theta_phi

HALF_PI, TWO_PI = 0.5 * np.pi, 2.0 * np.pi


def rotate_z(w, angle):
    """Rotate directions about the normal by `angle` (broadcast per row)."""
    w = np.asarray(w, float)
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * w[..., 0] - s * w[..., 1], s * w[..., 0] + c * w[..., 1], w[..., 2]], axis=-1)


def half_vector(u):
    theta = HALF_PI * u[..., 0] ** 2
    phi = TWO_PI * u[..., 1] - np.pi
    s = np.sin(theta)
    return np.stack([s * np.cos(phi), s * np.sin(phi), np.cos(theta)], axis=-1)


def u_of_half_vector(m):
    theta, phi = theta_phi(m)
    u1 = np.sqrt(np.clip(theta / HALF_PI, 0.0, 1.0))
    u2 = (phi + np.pi) / TWO_PI
    return np.stack([u1, u2 - np.floor(u2)], axis=-1)


def dwo_du(wi, m, u1):
    """Solid angle of wo = reflect(wi, m) per unit area of u (zero where the reflection is invalid)."""
    return dwo_du_of(np.sum(wi * m, axis=-1), np.sin(HALF_PI * u1 * u1), u1)


def dwo_du_of(cos_im, sin_theta_m, u1):
    """dwo_du from wi.m and sin(theta_m) (theta_m = pi/2 u1^2) where the caller has them."""
    return 4.0 * np.maximum(cos_im, 0.0) * sin_theta_m * np.pi * u1 * TWO_PI
