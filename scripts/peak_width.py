"""How sharp a measured file's specular peak is: at theta_i 15/30/45 deg, the luminance of f along
the plane of incidence around the mirror direction (0.05 deg steps over +-20 deg), its full
width at half maximum above the file's floor (f 20 deg off the mirror), where the peak sits
relative to the mirror and how far it rises over the floor. Names the files with a near-mirror
peak (FWHM of a few degrees, 1000x its floor), which closures cannot follow (issue 51).

    .venv/bin/python scripts/peak_width.py [--rgl DIR] [NAME ...]
"""
import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bake.maths.geometry import luminance  # noqa: E402
from bake.materials import open_material  # noqa: E402


def peak(material, theta_i_deg, reach=20.0, step=0.05):
    """(FWHM deg, peak offset from the mirror deg, peak / floor) in the plane of incidence."""
    t = np.radians(theta_i_deg)
    wi = np.array([np.sin(t), 0.0, np.cos(t)])
    off = np.radians(np.arange(-reach, reach + 1e-9, step))
    to = t + off
    wo = np.stack([-np.sin(to), np.zeros_like(to), np.cos(to)], -1)
    f = luminance(material.eval(wi, wo))
    floor = min(f[0], f[-1])
    k = int(np.argmax(f))
    half = floor + 0.5 * (f[k] - floor)
    lo = hi = k
    while lo > 0 and f[lo] > half:
        lo -= 1
    while hi < len(f) - 1 and f[hi] > half:
        hi += 1
    return float(np.degrees(off[hi] - off[lo])), float(np.degrees(off[k])), float(f[k] / max(floor, 1e-9))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*")
    ap.add_argument("--rgl", type=Path, default=ROOT.parent / "shared" / "data" / "rgl")
    args = ap.parse_args()
    paths = [args.rgl / f"{n}_rgb.bsdf" for n in args.names] or sorted(args.rgl.glob("*_rgb.bsdf"))
    for path in paths:
        material = open_material(str(path))
        cells = [(ti, *peak(material, ti)) for ti in (15.0, 30.0, 45.0)]
        print(f"{path.stem[:-4]:20s} " + "  ".join(f"ti {ti:.0f}: FWHM {w:5.2f} deg, peak at {o:+.2f}, {r:7.1f}x floor"
                                                  for ti, w, o, r in cells), flush=True)


if __name__ == "__main__":
    main()
