import numpy as np
import pytest

from bake.core.domains import Disk, Spherical, get_domain
from bake.errors import FlowBSDFError
from bake.maths.geometry import spherical_dir


def random_dirs(n, rng):
    theta = np.arccos(rng.random(n))          # uniform over the hemisphere
    return spherical_dir(theta, rng.uniform(-np.pi, np.pi, n))


@pytest.mark.parametrize("domain", [Disk(), Spherical()])
def test_round_trip(domain):
    wo = random_dirs(10000, np.random.default_rng(1))
    x = domain.from_dir(wo)
    assert np.all(domain.contains(x))
    np.testing.assert_allclose(domain.to_dir(x), wo, atol=1e-12)


@pytest.mark.parametrize("domain", [Disk(), Spherical()])
def test_jacobian_is_solid_angle_per_area(domain):
    """The solid angle of a small square around x equals jacobian(x) * its area."""
    rng = np.random.default_rng(2)
    x = domain.from_dir(random_dirs(200, rng))
    x = x[domain.jacobian(x) < 50]                 # away from the rim, where the map is singular
    h = 1e-6
    corners = [x + np.array(d) * h for d in ([-1, -1], [1, -1], [1, 1], [-1, 1])]
    a, b, c, d = (domain.to_dir(p) for p in corners)
    # Solid angle of the small quad from the cross product of its diagonals.
    area = 0.5 * np.linalg.norm(np.cross(c - a, d - b), axis=-1)
    np.testing.assert_allclose(area / (2 * h) ** 2, domain.jacobian(x), rtol=1e-4)


def test_spherical_phi_wraps():
    s = Spherical()
    np.testing.assert_allclose(s.wrap_phi([np.pi, -np.pi, 3 * np.pi + 0.1]), [-np.pi, -np.pi, -np.pi + 0.1])
    a = s.to_dir([[0.4, np.pi - 1e-9]])
    b = s.to_dir([[0.4, -np.pi + 1e-9]])
    np.testing.assert_allclose(a, b, atol=1e-8)


def test_unknown_domain():
    with pytest.raises(FlowBSDFError, match="unknown domain 'cube'"):
        get_domain("cube")
