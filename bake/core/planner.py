"""Planning baked tables (plan_tables): the resolution, the azimuths (anisotropic), the incident bins
and the cells' layout between them that a material needs within the memory budget, each chosen by
probes (tables built from the ideal tabulation's points by tabulate.py's builder) measured against
their targets; then the planned tables are built.

    plan_tables         the steps in order; their results in tables.meta
    _plan_resolution    step 1: RESOLUTIONS probed at a few angles (anisotropic: _plan_phi_bins too)
    _plan_bins          step 2: the incident bins, split where a midpoint loses most (SPLIT_LOSS)
    _plan_layout        step 3: the cells' placement between bins (_between_bins, LAYOUT_WINDOWS, groups)
    _plan_in_turns      plans over several coordinates (ISO_PLANNED), a round each
    bin_bytes, ...      what tables cost (the memory budget's arithmetic)

How a single table is built (edges, masses, profiles; ISO_COORDS, SHARES) is tabulate.py's.
"""
import numpy as np

from ..errors import FlowBSDFError
from ..io.threads import parallel as _parallel
from ..maths.fasttables import one_blas_thread
from ..maths.geometry import spherical_dir
from .settings import BakeSettings
from .tabulate import (ISO_COORDS, _row_knots, build_grouped, build_tables, default_phi_bins, group_sizes, join_groups,
                       prefetch_points)

ISO_PLANNED = ("wo", "halfpolar")     # the coordinates plan_tables tries for isotropic tables, in turn
RESOLUTIONS = (16, 24, 32, 48, 64)
# Anisotropic tables spend memory on azimuths before cells: 32^2 cells x 32 phi bins hold a 1:25
# or 1:50 GGX within 0.6-1.6x the 256^2 ideal's rv at theta_i 80 between phi bins, where 64^2 x 8
# (the same memory) reached 3-10x (measured; the half vector's cap turns with phi_i at grazing).
ANISO_RESOLUTIONS = (16, 24, 32)
# At theta_i 86 a 1:25 GGX needs 64 (32: 3.5x the ideal's rv half-way, 64: 1.3x; measured).
PHI_COUNTS = (8, 16, 32, 64)
PHI_PROBE_DEG = (80.0, 86.0)
# A cell's bytes in every bin: its mass as float32, its two profiles (NSEG logs each) and RGB
# weight as float16 (_finish_bin). Its edges belong to the bin's layout, stored once for all the
# bins that share it (Tables.layouts: a layout group's bins, one layout for all bins).
CELL_BYTES = 22
ANISO_BUDGET = 4         # anisotropic tables' share of memory_budget, all their azimuths together


def bin_bytes(resolution):
    """The bytes of one incident bin's resolution² cells (their edges aside: layout_bytes)."""
    return CELL_BYTES * resolution * resolution


def layout_bytes(resolution):
    """The bytes of one layout of resolution² cells: its edges as float32 (each row's columns,
    the rows), stored once for the bins that share it."""
    return 4 * (resolution * (resolution + 1) + resolution + 1)


def bins_within(memory_budget, resolution, layouts=2):
    """How many incident bins of resolution² cells fit the budget beside `layouts` layouts
    (2: two layout groups, what _between_bins mostly keeps); at least 2."""
    return max(2, int((memory_budget - layouts * layout_bytes(resolution)) // bin_bytes(resolution)))


# Isotropic resolutions leave the budget room for MIN_BINS incident angles: 64² x 17 (28-byte cells
# at 2 MB) lost 7-53x the ideal's rv between bins on the sharp shared files, 64² x 27 (3.11 MB) still
# 53x on satin_rosaline at 85 deg, where 48² x 31 lost 6x (measured); 36 excludes 64² from 2 MB of
# 18-byte cells (27 angles) and keeps it at 4 MB (54), where 64² x 34 beat 48² x 62 of 28-byte cells
# on malachite, ilm and irid. With 26-byte cells (profiles, the edges in every bin) 33 kept 48² at
# 2 MB (33 angles: 46 of the 50 acceptance cells within 1.5x the ideal's rv; on satin_rosaline and
# chm_mint 32² x 54-74 held 5 of their 10 cells, 48² x 33 held 6) and 64² at 4 MB (37); with the
# edges once per layout (22 bytes a cell in each bin) the same: 48² x 39 at 2 MB, 64² x 44 at 4 MB.
MIN_BINS = 33


# Carried tables (carried.py) hold between bins further apart: chm_mint's plan over 32² cells was
# done (every midpoint within its target) at 27 bins where the fixed-cell blend's filled 64.
MIN_BINS_CARRIED = 24


def _resolutions_within(memory_budget, min_bins=MIN_BINS):
    """RESOLUTIONS whose tables fit min_bins incident angles in the budget (all of them when
    not even the smallest does: the budget then decides alone)."""
    fits = [r for r in RESOLUTIONS if bins_within(memory_budget, r) >= min_bins]
    return fits or list(RESOLUTIONS)


ISO_TOL = 0.0004     # isotropic: rv 2e-4 is near the ideal tabulation's best (1e-4 to 5e-3 on the shared files)
ANISO_TOL = 0.004
BROAD = 0.3     # lobes wider than this (radians) get no lobe zones: cells follow the mass alone
# The planner splits while an interval's midpoint loses more than this times its target beyond
# the better of its bins (interval_loss): a midpoint then ends within 1.5x of that, the issue's
# aim. At 1.0 (up to 2x) the shared files that stop under the budget lost at 85 deg (measured
# against the ideal, 2 MB: paper_white 2.46x -> 1.55x, 1.05 -> 1.24 MB; colodur 4.36x -> 2.80x,
# 1.36 -> 1.79 MB; 4 MB paper_white 7.87x -> 2.43x); the files that fill the budget plan alike.
SPLIT_LOSS = 0.5
# An interval's middle angle is probed too where its cos-midpoint sits this far above it (near
# the normal: interval_loss's probes).
PROBE_APART = np.radians(1.0)


def lobe_width_of(material, ideal):
    """The angular half-width of the lobe zones: 4 alpha of the material's fitted GGX lobe,
    or None for a broad material."""
    from .baselines import fit_ggx
    fit = fit_ggx(material, ideal)
    width = max(4.0 * fit.alpha_x, 0.03)
    return None if width > BROAD or fit.diffuse >= 0.9 else float(width)


@one_blas_thread()
def plan_tables(material, source, settings=BakeSettings(), log=None, coords="auto", blend="fixed",
                placement="compare", theta_max_deg=89.9, min_gap_deg=0.2, **options):
    """Tables with only the resolution and incident bins this material needs, planned in three
    steps: the resolution (_plan_resolution; anisotropic: and the azimuths, _plan_phi_bins), the
    incident bins (_plan_bins) and the cells' layout between them (_plan_layout); then built.
    `settings` (BakeSettings: a manifest's [bake] table) holds what a bake may set; the other
    arguments are the planner's own (tests and scripts set them), `options` go to build_tables.

    The probes build tables from the ideal tabulation's points (`ideal`: the plan depends on
    the material, and a flow's points cost ~20x as much per incident angle: 6 s for 512²
    with its Jacobians); the planned tables are built from `source`'s.

    Targets: at an incident angle, `ideal_ratio` times the rv of the ideal tabulation there
    (what f·cos tabulated at that very angle on the ideal's grid reaches), but never below
    tol / 2 (default ISO_TOL: the rv below which an angle needs nothing more). Anisotropic
    materials, or ideal_ratio 0 or None: tol / 2 everywhere (default ANISO_TOL).

    Coordinates (isotropic): "auto" plans the tables over each of ISO_PLANNED and keeps the plan
    whose midpoints are typically closest to their targets: the geometric mean over its intervals,
    weighted by their width in theta_i, of each midpoint's rv over its target (1 where within it;
    when both reach their targets: the smaller). The worst midpoint alone chose wo for
    cc_green_malachite, worse at 0-84 deg (1.5-4.5x its targets where the half vector's plan
    was 0.2-2x) for being better in the last 5 deg (5x vs 9x): 1 of theta_i 0/30/60/75/85 within
    1.5x the ideal's rv instead of 4 (measured, 2 MB).
    The plans run in turns, a round of splits each (_plan_in_turns): a plan stops once it has as
    many cells as another that reached its targets and still splits (it could only end bigger: the
    same choice, sooner; a Lambert bakes 2x sooner), and one whose midpoints are typically PLAN_DROP
    times further over their targets than the other's, three rounds in, is dropped (the wo plans
    of sharp files, which end above their targets: satin_rosaline, chm_mint, ...).
    Neither wins everywhere: over the half vector a lobe stays put between bins, over wo a
    diffuse base is the same at every theta_i (2 MB plans: the half vector for 9 of the 10 shared
    files since its columns split at the quarter turns, wo for colodur_napoli_4f, a Lambert and a
    plastic of alpha 0.3).

    blend: how the tables will be sampled between bins, which the probes measure: "fixed" (Tables:
    at fixed cells) or "carried" (an isotropic RGL file's tables carried along its own coordinates,
    bake/core/carried.py: the bins may lie further apart, the budget counts the file's warp data and
    the resolutions need room for MIN_BINS_CARRIED bins; numpy only; tables.meta["blend"] and
    ["carried"], absent for "fixed", whose tables stay as before, byte for byte).
    settings.carry: with the fixed blend's plan, also say per interval whether carrying samples closer
    (tables.meta["carried"], carried.choose_intervals: a back end that can carry, OSL, does so
    there; the others blend at fixed cells, what the plan was made for); the budget counts the
    file's warp data as for "carried", and where that data would take over half of it (a preview
    bake), the tables do not carry. Isotropic RGL files only.

    Anisotropic materials: their tables may take ANISO_BUDGET times `memory_budget`, all azimuths
    together (16 MB at the default).
    """
    from .ideal import IdealSampler
    log = log or (lambda *_: None)
    if blend not in ("fixed", "carried"):
        raise FlowBSDFError(f"blend {blend!r}: 'fixed' or 'carried'")
    if placement not in ("rule", "compare"):
        raise FlowBSDFError(f"placement {placement!r}: 'rule' or 'compare'")
    carrier = _carrier(material) if blend == "carried" else (lambda tables: tables)
    carry, memory_budget = settings.carry, settings.memory_budget
    if blend == "carried" or carry:      # the file's warp data is read beside the tables: within the budget
        from .carried import check_carriable
        check_carriable(material)
        if blend == "fixed" and material.warp_nbytes > memory_budget / 2:
            log(f"carried blend off: the file's warp data ({material.warp_nbytes / 1e6:.2f} MB) would take over "
                f"half the memory budget ({memory_budget / 1e6:.2f} MB)")
            carry = False
        else:
            memory_budget -= material.warp_nbytes
    ideal = source if isinstance(source, IdealSampler) else IdealSampler(material, resolution=settings.ideal_resolution)
    lobe_width = lobe_width_of(material, ideal) if settings.lobe_width == "auto" else settings.lobe_width
    aniso = not material.isotropic
    tol = (ANISO_TOL if aniso else ISO_TOL) if settings.tol is None else settings.tol
    candidates = ([None] if aniso else list(ISO_PLANNED)) if coords == "auto" else [coords]
    plan = _Planning(material, ideal, settings, memory_budget, tol, lobe_width, blend, carrier, theta_max_deg,
                     min_gap_deg, {"grid": settings.grid, **options}, log)

    def plan_over(coords, say, beat):
        """A plan over coords (None: build_tables' default): a generator of its rounds, as
        _plan_bins, which ends it."""
        opts = plan.opts(coords)
        resolution, worst_phi, probe_phis = _plan_resolution(plan, opts, say)
        phi_bins = _plan_phi_bins(plan, opts, resolution, probe_phis, say)
        return (yield from _plan_bins(plan, opts, coords, resolution, phi_bins, worst_phi, len(candidates) > 1,
                                      say, beat))

    plans = _plan_in_turns(candidates, plan_over, log)
    # The plan closest to its targets over its midpoints' typical excess; when both reach them,
    # the smaller.
    coords = min(plans, key=lambda c: (plans[c][4][1], len(plans[c][1]) * plans[c][0] ** 2))
    resolution, bins, phi_bins, worst_phi, _, extend = plans[coords]
    if len(candidates) > 1:
        log(f"coordinates: {coords} (midpoints over their targets, typical / worst: " + ", ".join(
            f"{c} {p[4][1]:.2f}x / {p[4][0]:.2f}x" for c, p in plans.items()) + ")")
    opts, bins, resolution, compared = _plan_layout(plan, coords, bins, resolution, phi_bins, extend, placement)
    log(f"tables: building {len(bins)} angles" + (f" x {len(phi_bins)} azimuths" if phi_bins is not None else ""))
    every = [0]

    def built(done, total):     # about ten lines, whatever the count
        if done == total or done * 10 // total > every[0]:
            every[0] = done * 10 // total
            log(f"tables: built {done} of {total}")
    if source is ideal and compared is not None:       # the comparison built them from the source's points
        tables = compared
        built(len(bins), len(bins))
    else:   # from the source's own points: the probes' are the ideal's
        tables = build_grouped(material, source, bins, resolution, phi_bins=phi_bins, progress=built,
                               **{**opts, "cache": plan.cache if source is ideal else {}})
    if blend == "carried" or carry:
        from .carried import choose_intervals
        tables.meta["carried"] = choose_intervals(material, tables, ideal)
        log(f"carried: {sum(tables.meta['carried'])} of {len(tables.meta['carried'])} intervals carry")
    tables.meta.update(resolution=resolution if np.ndim(resolution) == 0 else [int(r) for r in resolution],
                       lobe_width=lobe_width, tol=tol, ideal_ratio=settings.ideal_ratio,
                       window=opts.get("window", 1),
                       groups=int(np.sum(np.diff(bins) == 0)) + 1, **({"blend": blend} if blend != "fixed" else {}))
    if phi_bins is not None:
        tables.meta.update(phi_count=len(phi_bins), planned_at_phi=float(worst_phi))
    return tables


class _Planning:
    """What plan_tables' steps share: the material, its ideal tabulation, the settings and what the
    planner made of them (the budget, tol, lobe width), and the probes: tables built from the
    ideal's points (cached per bin and coordinates, for every plan) and their rv at an angle
    against its target."""

    def __init__(self, material, ideal, settings, memory_budget, tol, lobe_width, blend, carrier, theta_max_deg,
                 min_gap_deg, options, log):
        from .metrics import relative_variance
        self.relative_variance = relative_variance
        self.material, self.ideal, self.settings = material, ideal, settings
        self.memory_budget, self.tol = memory_budget, tol
        self.lobe_width, self.blend, self.carrier, self.options, self.log = lobe_width, blend, carrier, options, log
        self.theta_max_deg, self.min_gap_deg = theta_max_deg, min_gap_deg
        self.aniso = not material.isotropic
        self.cache = {}         # the probes' points per bin and coordinates (_Once), shared by the plans
        self.targets = {}

    def opts(self, coords):
        """build_tables' options of the probes over coords."""
        return dict(lobe_width=self.lobe_width, cache=self.cache, coords=coords, **self.options)

    def build(self, opts, resolution, thetas, phi=0.0, phis=None):
        """A probe; phis: all azimuths, else the single azimuth phi (anisotropic)."""
        if self.aniso:
            phis = [phi] if phis is None else phis
        return self.carrier(build_tables(self.material, self.ideal, thetas, resolution, resolution, phi_bins=phis,
                                         **opts))

    def rv_at(self, tab, theta, phi=0.0):
        return self.relative_variance(self.material, tab, spherical_dir(theta, phi), n=self.settings.samples)[0]

    def target(self, theta):
        if self.aniso or not self.settings.ideal_ratio:
            return 0.5 * self.tol
        if theta not in self.targets:
            self.targets[theta] = max(self.settings.ideal_ratio * self.rv_at(self.ideal, theta), 0.5 * self.tol)
        return self.targets[theta]


def _plan_resolution(plan, opts, say):
    """Step 1: (resolution, the azimuth probed worst, the azimuths probed). The resolution given,
    else the smallest of RESOLUTIONS (within the budget: _resolutions_within) whose single-bin
    tables reach their target at a few elevations (isotropic: a resolution's probe stops at its
    first failing elevation; when none does, the one that comes closest). Anisotropic: of
    ANISO_RESOLUTIONS, probed at 4 azimuths; the bins are planned at the azimuth that did worst."""
    material, aniso = plan.material, plan.aniso
    probe_phis = list(np.arange(4) * (material.phi_period / 4)) if aniso else [0.0]
    resolution, worst_phi = plan.settings.resolution, 0.0
    if resolution is None:
        probe = np.radians([86.0, 75.0, 10.0, 45.0])     # grazing first: where coarse tables fail first

        def probe_rv(resolution, phi):   # the worst rv / target over the probe angles (isotropic: to the first above 1)
            def ratio(t):
                return plan.rv_at(plan.build(opts, resolution, [t], phi), t, phi) / plan.target(t)
            # Isotropic: the first (grazing) angle alone, where most resolutions fail; when it
            # holds, the others in threads (read in turn as before: a failure among them ends it).
            ratios = list(_parallel(ratio, probe)) if aniso else [ratio(probe[0])]
            if not aniso and ratios[0] <= 1.0:
                ratios += list(_parallel(ratio, probe[1:]))
            worst = 0.0
            for r in ratios:
                worst = max(worst, r)
                if worst > 1.0 and not aniso:
                    break
            return worst

        # Isotropic: one angle above its target decides that a resolution fails (the rest need
        # not be built). Anisotropic: the worst azimuth is needed, so every angle is.
        tried = {}
        for resolution in (ANISO_RESOLUTIONS if aniso else _resolutions_within(
                plan.memory_budget, MIN_BINS_CARRIED if plan.blend == "carried" else MIN_BINS)):
            by_phi = {phi: probe_rv(resolution, phi) for phi in probe_phis}
            worst_phi, worst = max(by_phi.items(), key=lambda kv: kv[1])
            tried[resolution] = worst
            say(f"resolution {resolution}: single-bin rv {worst:.2f}x the target"
                + (" or more" if worst > 1 and not aniso else "")
                + (f" (at phi_i {np.degrees(worst_phi):.1f} deg)" if aniso else ""))
            if worst <= 1.0:
                break
        if worst > 1.0 and not aniso:
            # None reaches its target: the closest one. More cells are not always closer (aurora
            # at theta_i 86: 48² 3.2x, 64² 8.0x; sharp files fail every resolution at the first
            # probe angle, so they compare there), and fewer leave room for more bins.
            resolution = min(tried, key=lambda r: (tried[r], -r))
            say(f"resolution {resolution}: none reaches the target; this one comes closest")
    elif aniso:
        t = np.radians(75.0)
        worst_phi = max(probe_phis, key=lambda phi: plan.rv_at(plan.build(opts, resolution, [t], phi), t, phi))
    return resolution, worst_phi, probe_phis


def _plan_phi_bins(plan, opts, resolution, probe_phis, say):
    """Step 1, anisotropic: the azimuths (None for isotropic tables): `phi_count` evenly spaced
    over the material's period (default_phi_bins); "auto": the fewest of PHI_COUNTS whose blend
    half-way between two bins at each theta_i of PHI_PROBE_DEG loses at most the bin's own rv plus
    tol / 2 (at the probed azimuths)."""
    if not plan.aniso:
        return None
    material, count = plan.material, plan.settings.phi_count
    if count == "auto":
        probes = [(np.radians(t), phi) for t in PHI_PROBE_DEG for phi in probe_phis]
        for count in PHI_COUNTS:
            step = material.phi_period / count
            pairs = list(_parallel(lambda tp: plan.build(opts, resolution, [tp[0]], phis=[tp[1], tp[1] + step]),
                                   probes))
            loss = max(plan.rv_at(tab, t, phi + 0.5 * step) - 2.0 * plan.rv_at(tab, t, phi)
                       for tab, (t, phi) in zip(pairs, probes))
            say(f"phi bins {count}: the blend half-way loses {loss:.4f}")
            if loss <= 0.5 * plan.tol:
                break
    return default_phi_bins(material, count)


def _plan_bins(plan, opts, coords, resolution, phi_bins, worst_phi, compared, say, beat):
    """Step 2: the incident bins. A generator: after each round of the split loop it yields (bins,
    cells, the typical excess of the midpoints over their targets so far); it returns (resolution,
    bins, phi_bins, worst_phi, (the worst midpoint's rv over its target, the typical excess),
    extend) of the tables over coords. beat["cells"], set by the caller between rounds: the cells
    of a plan that reached its targets; once this one has as many and still splits, it ends bigger
    and cannot be kept: it stops there (worst midpoint inf). compared: other plans are compared
    with this one (the intervals of its last split are scored too).

    Start from `first_bins` evenly spaced elevations from 0 to `theta_max_deg` (89.9: past the last
    bin the tables keep its layout; with it at 89.5, four shared files lost 19-42x the ideal's rv
    at 89.9, 4-5x with it at 89.9, measured at 2 MB) and, isotropic, the material's measured
    incident angles (`measured_theta_i`: measured data interpolate between them, so f·cos has a
    kink in theta_i at each, which interpolating across loses; measured at 2 MB on
    cm_military_green: the worst of 11 angles 3.56x the ideal's rv -> 1.95x); while the memory
    budget allows another bin, split the interval whose interpolated midpoint (its cos-midpoint,
    near the normal also its middle angle: the one that loses more) loses most against the better
    of its two bins (interval_loss) relative to the midpoint's target, until no interval loses
    more than SPLIT_LOSS times its target. Anisotropic: planned at the azimuth where the probe did
    worst and shared by all azimuths."""
    material, aniso, memory_budget, options = plan.material, plan.aniso, plan.memory_budget, plan.options
    rv_at, target = plan.rv_at, plan.target
    if phi_bins is None:    # at most (a bin's layout may be its own: fits)
        max_bins = bins_within(memory_budget, resolution)
    else:       # every theta bin once per azimuth, and the one closing the period, each its own layout
        per_bin = (bin_bytes(resolution) + layout_bytes(resolution)) * (len(phi_bins) + 1)
        max_bins = max(2, int(memory_budget * ANISO_BUDGET // per_bin))
    # Without a window given, _between_bins may split the bins into two groups: room for the
    # second group's layout is kept.
    second = 0 if "window" in options else layout_bytes(resolution)

    def fits(bins):
        if phi_bins is not None:
            return True
        return groups_bytes([(bins, resolution)], coords or ISO_COORDS, plan.lobe_width,
                            options.get("window")) + second <= memory_budget

    bins = list(np.radians(np.linspace(0.0, plan.theta_max_deg, plan.settings.first_bins)))
    gap = np.radians(plan.min_gap_deg)
    if material.measured_theta_i is not None and not aniso:
        for t in material.measured_theta_i:
            if 0.0 < t <= np.radians(plan.theta_max_deg) and min(abs(t - b) for b in bins) > gap:
                bins.append(float(t))
        bins.sort()

    def midpoint(lo, hi):     # interpolation is linear in cos(theta): test where it errs most
        return float(np.arccos(0.5 * (np.cos(lo) + np.cos(hi))))

    def probes(lo, hi):
        """Where an interval is probed: its midpoint in cos(theta), and near the normal, where
        that sits well above the middle angle (0-12.7 deg: at 9.0), the middle angle too
        (chm_mint at 2 MB lost 8x the ideal's rv at 3.5 deg, 3.9x at the 9.0 probe)."""
        mid = midpoint(lo, hi)
        half = 0.5 * (lo + hi)
        return (mid, half) if mid - half > PROBE_APART else (mid,)

    scores = {}
    reached = {}        # per interval: the midpoint's rv over its target (the probe that lost most)
    split_at = {}       # per interval: the probe that lost most, where a split puts its bin

    def interval_loss(lo, hi):
        """What interpolating between bins at lo and hi loses at the midpoint beyond what the
        bins themselves reach, in units of the midpoint's target: the midpoint's rv above the
        target or the better of the two bins' own rv (both measured on the same pair of bins: a
        bin built at the midpoint costs as much as the pair, and would only be needed for this).
        The midpoint: of probes(lo, hi), the one that loses most (split_at)."""
        if hi - lo <= gap:
            return 0.0
        tab = plan.build(opts, resolution, [lo, hi], worst_phi)
        floor = min(rv_at(tab, lo, worst_phi), rv_at(tab, hi, worst_phi))
        losses = []
        for mid in probes(lo, hi):
            rv_mid = rv_at(tab, mid, worst_phi)
            losses.append((max(rv_mid - max(floor, target(mid)), 0.0) / target(mid), rv_mid / target(mid), mid))
        loss, reached[(lo, hi)], split_at[(lo, hi)] = max(losses)
        return loss

    def extend(placed, room, above):
        """placed plus splits of its intervals at or above `above`, the worst first, while
        room(bins) says they fit (the upper group of a split whose lower group took smaller
        cells: _between_bins)."""
        placed = list(placed)
        while True:
            new = [iv for iv in zip(placed[:-1], placed[1:]) if iv not in scores and iv[0] >= above]
            scores.update(zip(new, _parallel(lambda iv: interval_loss(*iv), new)))
            upper = [(scores[iv], iv) for iv in zip(placed[:-1], placed[1:]) if iv[0] >= above]
            worst, iv = max(upper, default=(0.0, None))
            if worst <= SPLIT_LOSS or not room(sorted(placed + [split_at[iv]])):
                return placed
            placed = sorted(placed + [split_at[iv]])

    def reaches(bins):      # (the worst midpoint's rv over its target, the typical excess)
        ratios = np.array([reached.get(iv, 0.0) for iv in zip(bins[:-1], bins[1:])])
        excess = float(np.exp(np.average(np.log(np.maximum(ratios, 1.0)), weights=np.diff(bins)))) \
            if len(bins) > 1 else 1.0
        return float(ratios.max(initial=0.0)), excess

    while True:
        if len(bins) >= max_bins:       # (a plan that ends on the budget says so: the add-on's progress)
            say(_budget_full(len(bins), memory_budget))
            break
        new = [(lo, hi) for lo, hi in zip(bins[:-1], bins[1:]) if (lo, hi) not in scores]
        if not aniso:       # (the new angle's points first: both of its intervals' builds need them)
            prefetch_points(material, plan.ideal, sorted({t for iv in new for t in iv}), **opts)
        # The new intervals' builds are independent: all of them at once, in threads.
        scores.update(zip(new, _parallel(lambda iv: interval_loss(*iv), new)))
        yield len(bins), len(bins) * resolution ** 2, reaches(bins)[1]
        (lo, hi), worst = max(scores.items(), key=lambda kv: kv[1])
        if worst <= SPLIT_LOSS:
            say(f"bins {len(bins)}: done, the worst midpoint loses {worst:.2f}x its target")
            break
        if beat["cells"] is not None and len(bins) * resolution ** 2 >= beat["cells"]:
            say(f"bins {len(bins)}: stopped, as many cells as a plan that reaches its targets")
            return resolution, bins, phi_bins, worst_phi, (np.inf, np.inf), extend
        if not fits(sorted(bins + [split_at[(lo, hi)]])):
            say(_budget_full(len(bins), memory_budget))
            break
        bins = sorted(bins + [split_at[(lo, hi)]])
        del scores[(lo, hi)]
        say(f"bins {len(bins)}: split {np.degrees(lo):.2f}-{np.degrees(hi):.2f} deg "
            f"(midpoint loss {worst:.2f}x its target)")
    # What the plan reaches, to compare plans: its midpoints over their targets, the worst and
    # the typical excess (the intervals of the last split are scored too when the budget ended it).
    if compared:
        new = [(lo, hi) for lo, hi in zip(bins[:-1], bins[1:]) if (lo, hi) not in scores]
        scores.update(zip(new, _parallel(lambda iv: interval_loss(*iv), new)))
    return resolution, bins, phi_bins, worst_phi, reaches(bins), extend


def _plan_layout(plan, coords, bins, resolution, phi_bins, extend, placement):
    """Step 3: (build_tables' options with the layout's window, bins, resolution, their tables
    from the ideal's points or None). Isotropic, unless `window` is given: the planned bins'
    tables are built from the ideal with each of LAYOUT_WINDOWS (a bin's layout pooled with its
    neighbours', or one for all bins) and split into two layout groups at a few angles (each group
    its own cells), and the one typically closest to the ideal at the bins and between them is
    kept (_between_bins; tables.meta["window"], ["groups"]); the best split is also tried with the
    lower group at coarser cells and the memory it frees spent above (MixedTables;
    meta["resolution"] then lists both). The interval probes of step 2 pool the pair alone.
    placement: "compare" (default) every candidate; "rule" from 6 bins on only the groups split
    nearest RULE_SPLITS_DEG (and the better one's groups of their own resolutions): 2-3 placements
    built instead of 5-6, the same tables where the full comparison keeps one of those, but on
    near-ties it loses rv at single angles (satin_rosaline 1.24x at theta_i 0, vch_golden_yellow
    2.01x at 60: RULE_SPLITS_DEG). The window given: as many bins as its layouts leave room for."""
    options = plan.options
    opts = dict(lobe_width=plan.lobe_width, coords=coords, **options)
    compared = None
    if phi_bins is None and "window" not in options:
        opts["window"], bins, resolution, compared = _between_bins(
            plan.material, plan.ideal, bins, resolution, opts, plan.cache, plan.tol, plan.settings.samples, plan.log,
            plan.memory_budget, extend, plan.carrier, placement, prune=plan.blend == "fixed")
    elif phi_bins is None:
        (bins, _), = _fit([(bins, resolution)], plan.memory_budget, window=options["window"],
                          coords=coords or ISO_COORDS, lobe_width=plan.lobe_width)
    return opts, bins, resolution, compared


def _budget_full(bins, memory_budget):
    """A plan's line when the memory budget ends it (the add-on's progress counts the plan done)."""
    return f"bins {bins}: done, the memory budget holds no more angles ({memory_budget / 1e6:.2f} MB)"


# Plans over several coordinates run in turns, a round of splits each: one whose midpoints are
# typically PLAN_DROP times further over their targets than another's (at the same round, or the
# other's end), both PLAN_DROP_ROUNDS rounds in, is dropped: it would not be kept. Measured
# (default Final plans, wo's typical excess over halfpolar's per round): ilm_solo_m_68, whose wo
# plan is kept (1.02x vs 1.07x at the end), 6.0x at round 1, 2.5x at 3, then 2.1-3.0x; satin_rosaline,
# whose halfpolar plan is kept (1.09x vs 1.45x), 4.8x at round 3, 6.2x at 5, 2.3x at 18;
# paper_white and colodur_napoli_4f within 1.25x all along (both plans run to their end).
PLAN_DROP = 4.0
PLAN_DROP_ROUNDS = 3


def _plan_in_turns(candidates, plan, log):
    """{coords: plan's result} of plan_tables' plans (plan: the generator of plan_tables) over the
    candidates, run in turns a round each. Once a plan ends within its targets (typical excess
    1, the least there is), the others stop where they have as many cells and still split (they
    could only end bigger). A plan typically further over its targets than another's by
    PLAN_DROP after PLAN_DROP_ROUNDS rounds each is dropped (absent from the result)."""
    says = {c: log if len(candidates) == 1 else (lambda text, c=c: log(f"{c}: {text}")) for c in candidates}
    beats = {c: {"cells": None} for c in candidates}
    running = {c: plan(c, says[c], beats[c]) for c in candidates}
    plans, last, rounds = {}, {}, dict.fromkeys(candidates, 0)
    while running:
        for c in list(running):
            try:
                last[c] = next(running[c])
                rounds[c] += 1
            except StopIteration as stop:
                plans[c] = stop.value
                del running[c]
                if stop.value[4][0] <= 1.0:
                    cells = len(stop.value[1]) * stop.value[0] ** 2
                    for beat in beats.values():
                        beat["cells"] = cells if beat["cells"] is None else min(beat["cells"], cells)
        for c in list(running):
            others = {o: (plans[o][4][1] if o in plans else last[o][2]) for o in candidates
                      if o != c and (o in plans or (o in running and rounds[o] >= PLAN_DROP_ROUNDS))}
            if c not in last or rounds[c] < PLAN_DROP_ROUNDS or not others:
                continue
            best, typical = min(others.items(), key=lambda kv: kv[1]), last[c][2]
            if typical > PLAN_DROP * best[1]:
                running.pop(c).close()
                says[c](f"bins {last[c][0]}: dropped, its midpoints typically {typical:.2f}x their targets, "
                        f"{best[0]}'s {best[1]:.2f}x")
    return {c: plans[c] for c in candidates if c in plans}     # in the candidates' order (ties: the first)


# Isotropic layouts plan_tables tries for the planned bins (build_tables' window): a bin's layout
# pooled with its neighbours' follows a moving lobe; one layout for all bins mixes them cell by
# cell, which holds features that appear and fade between bins (measured data between their
# measured angles). Measured on the 2 MB plans of the shared files against the neighbours' layout
# alone (rv over the ideal's): satin_rosaline at 75 deg 4.6x -> 0.96x, chm_mint at 85 deg 9.0x ->
# 2.2x, at 75 7.1x -> 4.5x; colodur_napoli_4f at 85 deg 1.3x -> 1.7x (its typical excess lower);
# angles of a sweep above 1.5x the ideal's rv 468 -> 429 of 1350. At 4 MB: satin at 75 4.3x ->
# 0.5x, chm at 85 3.1x -> 1.5x (all 50 acceptance cells within 1.5x; 48 before), sweep 295 -> 205.
LAYOUT_WINDOWS = (1, None)
# Over the half vector a lobe stays put between bins: a layout pooled with the neighbours' (to follow
# it) is not tried. It was never the closest for the eight shared files planned over halfpolar
# (default Final plans, typical excess: 1.03-1.31x where the kept placement had 1.02-1.22x).
POLAR_WINDOWS = (None,)
GROUP_SPLITS_DEG = (55.0, 65.0, 75.0)
# The placements plan_tables(placement="rule") compares (from 6 bins on, where layout
# groups are tried): two layout groups split at the planned bins nearest RULE_SPLITS_DEG, one layout
# each, then the better split with groups of their own resolutions. The full comparison
# (placement="compare": also one layout for all bins, the neighbours' layouts over wo, the split
# at 65 deg) was 37-44 % of the tables' time (paper_white, cm_military_green, colodur_napoli_4f,
# 5-6 placements). On the ten shared files (default Final plans) the placement it kept was one of
# these on six, and on the other four a near-tie of them (typical excess within 0.01:
# docs/placements.md); the split at 55 deg alone lost rv at single angles where the full
# comparison kept the one at 75 (cm_military_green 85 deg +12 %, colodur_napoli_4f +26 %).
# Not the default: on two near-tie files the rule's tables lost rv at single angles against the
# full comparison's (rv over the ideal's, theta_i 0/30/60/75/85, default Final bakes side by side,
# quiet: satin_rosaline 1.24/1.11/1.11/0.84/0.67x, vch_golden_yellow 1.20/0.92/2.01/1.03/0.85x;
# paper_white and cm_military_green byte-identical) for ~10 % of the bake's time.
RULE_SPLITS_DEG = (55.0, 75.0)


def groups_bytes(groups, coords, lobe_width, window):
    """The bytes (Tables.nbytes) of isotropic tables in layout groups [(bins, resolution), ...]:
    with one placement for a group's bins (window None) the bins whose row knots agree share one
    layout (their edges are placed alike relative to them; the lobe's rings reach the horizon
    at grazing incidence), else each bin has its own."""
    total = 0
    for bins, res in groups:
        layouts = len(bins) if window is not None else len(
            {_row_knots(spherical_dir(t, 0.0), t, coords, lobe_width).tobytes() for t in bins})
        total += len(bins) * bin_bytes(res) + layouts * layout_bytes(res)
    return total


def _fit(groups, memory_budget, keep=(), **layout):
    """groups [(bins, resolution), ...] without the inner bins of the narrowest spans (each dropped
    bin's neighbours the closest), never a group's ends or those in `keep`, until their tables
    fit the budget (groups_bytes; layout: its coords, lobe_width, window)."""
    groups = [(list(bins), res) for bins, res in groups]
    while groups_bytes(groups, **layout) > memory_budget:
        free = [(b[k + 1] - b[k - 1], g, k) for g, (b, _) in enumerate(groups)
                for k in range(1, len(b) - 1) if b[k] not in keep]
        if not free:
            break
        _, g, k = min(free)
        groups[g][0].pop(k)
    return groups


def _carrier(material):
    """tables -> their CarriedTables (the planner's probes measure the blend the tables will have)."""
    from .carried import CarriedTables, check_carriable
    check_carriable(material)       # before any build

    def carry(tables):
        return CarriedTables(tables, material)
    return carry


ABOVE = 1e-9       # angles this far past a layout group's boundary bin are sampled from it alone (radians)


def _bar(best, best_split, j):
    """The typical excess a candidate must get below to change _between_bins' outcome: the best so
    far, or for a split (j given) the best split so far where that is higher (inf before any)."""
    bar = best[0] if best is not None else np.inf
    return bar if j is None else max(bar, best_split[0] if best_split is not None else np.inf)


def _between_bins(material, ideal, bins, resolution, opts, cache, tol, samples, log, memory_budget, extend,
                  carry=lambda tables: tables, placement="compare", prune=True):
    """(window, bins, resolution (one, or one per group), their tables from the ideal's points;
    None when not compared): of the ways to place cells between the planned bins, the one whose
    tables are typically closest to the ideal over the bins and their intervals' midpoints: the
    geometric mean, weighted by theta_i, of the tables' rv over the ideal's (at least tol / 2)
    where above 1, each rv from `samples` of the ideal's draws (ReferencePoints: the same draws
    for every candidate).

    The candidates: each of LAYOUT_WINDOWS (a bin's layout pooled with its neighbours', or one
    for all bins; over halfpolar POLAR_WINDOWS: the latter), and two layout groups (join_groups:
    the bins up to the planned bin nearest one of GROUP_SPLITS_DEG, and from it, each built alone with one layout for all its bins: its own
    cells per segment, not shared out by the weight of bins far away; window None). A group's
    repeated bin is paid for with the bin of the narrowest span when the budget is full, the
    neighbours' pooled layouts (one per bin) with as many as they need.
    The split whose groups came closest is tried also with groups of their own resolutions
    (MixedTables): the lower group one step coarser (of RESOLUTIONS) and the memory it frees spent
    above, on more bins where the plan's intervals lose most (`extend`, the plan's split loop) or on a step finer cells for the
    upper group's bins (as many as the budget keeps, the narrowest spans dropped).
    prune (the fixed blend): a candidate of two groups has its cheaper group (bins x cells; none
    when another candidate built it) built first; where the angles that group alone samples (below the lower group's last bin, above the
    upper group's first) already put the typical excess over _bar, the candidate cannot be kept nor
    decide the split tried with mixed resolutions (the other angles' terms are >= 0): its other
    group is not built. The outcome is that of building every candidate."""
    from .metrics import ReferencePoints
    if len(bins) < 3:
        return LAYOUT_WINDOWS[0], bins, resolution, None
    side = max(int(round(np.sqrt(samples))), 1)
    b = np.asarray(bins)
    # The bins, and in each interval its midpoint and quarter points in cos(theta) (where a
    # candidate with more bins puts them: it is measured between its bins too), each standing
    # for theta_i half-way to its neighbours.
    c0, c1 = np.cos(b[:-1]), np.cos(b[1:])
    angles = np.sort(np.concatenate([b] + [np.arccos((1 - f) * c0 + f * c1) for f in (0.25, 0.5, 0.75)]))
    widths = 0.5 * (np.diff(angles, prepend=angles[0]) + np.diff(angles, append=angles[-1]))

    # The bins planned beside two layouts: a candidate whose bins need more drops the bins of the
    # narrowest spans (a bin's layout pooled with its neighbours' is its own; a group's repeated
    # bin is one more).
    layout = dict(coords=opts.get("coords") or ISO_COORDS, lobe_width=opts.get("lobe_width"))
    candidates = []
    for w in (LAYOUT_WINDOWS if layout["coords"] == "wo" else POLAR_WINDOWS):
        (placed, _), = _fit([(bins, resolution)], memory_budget, window=w, **layout)
        candidates.append(("one placement for all bins" if w is None else f"pooled with {w} neighbour", w, placed,
                           resolution, None))
    splits = sorted({int(np.clip(np.argmin(np.abs(b - np.radians(deg))), 2, len(b) - 3)) for deg in GROUP_SPLITS_DEG}
                    ) if len(b) >= 6 else []
    coarser = [r for r in RESOLUTIONS if r < resolution][-1:]
    finer = [r for r in RESOLUTIONS if r > resolution][:1]
    for j in splits:
        (lower, _), (upper, _) = _fit([(bins[:j + 1], resolution), (bins[j:], resolution)], memory_budget,
                                      keep=(bins[j - 1], bins[j + 1]), window=None, **layout)
        candidates.append((f"two groups split at {np.degrees(bins[j]):.2f} deg", None, lower + upper, resolution, j))

    def mixed(j):
        """The candidates of groups of their own resolutions split at bin j."""
        out, at = [], f"{np.degrees(bins[j]):.2f} deg"
        for lo_res in coarser:
            lower = list(bins[:j + 1])

            def room(upper):
                return groups_bytes([(lower, lo_res), (upper, resolution)], window=None, **layout) <= memory_budget
            upper = extend(bins[j:], room, bins[j])
            if len(upper) > len(bins) - j:
                out.append((f"two groups split at {at}, {lo_res}² cells below, {len(upper) - len(bins) + j} "
                            "more bins above", None, lower + upper, [lo_res, resolution], j))
            for hi_res in finer:
                groups = _fit([(lower, lo_res), (bins[j:], hi_res)], memory_budget, keep=lower, window=None, **layout)
                if groups_bytes(groups, window=None, **layout) <= memory_budget and len(groups[1][0]) >= 3:
                    out.append((f"two groups split at {at}, {lo_res}² cells below, {hi_res}² above",
                                None, lower + groups[1][0], [lo_res, hi_res], j))
        return out

    if placement == "rule" and splits:      # the splits nearest RULE_SPLITS_DEG alone (then the mixed, as below)
        at = {int(np.clip(np.argmin(np.abs(b - np.radians(deg))), 2, len(b) - 3)) for deg in RULE_SPLITS_DEG}
        candidates = [c for c in candidates if c[4] in at]
    if len(candidates) == 1 and not splits:        # nothing to compare
        label, window, placed, res, _ = candidates[0]
        log(f"between bins: {label}")
        return window, placed, res, None

    # Groups of their own resolutions are tried at the split whose groups of one resolution came
    # closest (measured on the shared files at 2 MB, all three splits each: the mixed candidate
    # that won was at that split or tied with it), two builds instead of six.
    total = len(candidates) + (len(coarser) * (1 + len(finer)) if splits else 0)     # at most
    log(f"between bins: comparing {total} cell placements on {len(bins)} angles")
    draws = list(_parallel(lambda t: ReferencePoints(material, spherical_dir(t, 0.0), ideal, side, 0), angles))
    floors = np.maximum(np.array(list(_parallel(lambda d: d.rv(ideal)[0], draws))), 0.5 * tol)
    best, best_split, n = None, None, 0
    groups = {}         # a layout group's tables by its bins and resolution

    def compare(label, window, placed, res, j):
        nonlocal best, best_split, n
        n += 1
        parts, sizes = group_sizes(placed, res)
        if len(parts) == 1:
            tables = build_grouped(material, ideal, placed, res, **{**opts, "window": window, "cache": cache})
        else:   # build_grouped's groups, the cheaper end one first: its angles alone may show that this one loses
            def group(k):       # (the mixed candidates at a split share their lower group: built once)
                key = (parts[k].tobytes(), int(sizes[k]))
                if key not in groups:
                    groups[key] = build_tables(material, ideal, parts[k], sizes[k], sizes[k],
                                               **{**opts, "window": None, "cache": cache})
                return groups[key]
            cost = [0 if (part.tobytes(), int(r)) in groups else len(part) * r * r for part, r in zip(parts, sizes)]
            first = 0 if cost[0] <= cost[-1] else len(parts) - 1
            built = {first: group(first)}
            alone = angles < parts[0][-1] - ABOVE if first == 0 else angles > parts[-1][0] + ABOVE
            if prune and alone.any():
                ratios = np.array(list(_parallel(lambda i: draws[i].rv(built[first])[0], np.flatnonzero(alone)))
                                  ) / floors[alone]
                at_least = float(np.exp(np.sum(np.log(np.maximum(ratios, 1.0)) * widths[alone]) / np.sum(widths)))
                if at_least > _bar(best, best_split, j) * (1.0 + 1e-9):
                    log(f"between bins: placement {n} of {total}, {label}: at least {at_least:.2f}x the ideal's rv "
                        f"(typical excess; its {'lower' if first == 0 else 'upper'} group's angles alone: no better, "
                        "the rest not built)")
                    return
            tables = join_groups([built[k] if k in built else group(k) for k in range(len(parts))])
        measured = carry(tables)
        ratios = np.array(list(_parallel(lambda d: d.rv(measured)[0], draws))) / floors
        excess = float(np.exp(np.average(np.log(np.maximum(ratios, 1.0)), weights=widths)))
        log(f"between bins: placement {n} of {total}, {label}: {excess:.2f}x the ideal's rv (typical excess)")
        if best is None or excess < best[0]:
            best = (excess, label, window, placed, res, tables)
        if j is not None and (best_split is None or excess < best_split[0]):
            best_split = (excess, j)

    # A candidate within the ideal's rv everywhere (typical excess 1, the least there is) cannot be
    # beaten (ties keep the earlier one): the rest are not built.
    for candidate in candidates:
        if best is None or best[0] > 1.0:
            compare(*candidate)
    more = mixed(best_split[1]) if best_split and best[0] > 1.0 else []
    total = len(candidates) + len(more)     # announced as at most this many: now known
    for label, window, placed, res, _ in more:      # (where to try mixed resolutions is decided: no split to track)
        compare(label, window, placed, res, None)
    log(f"between bins: {best[1]}")
    return best[2:]
