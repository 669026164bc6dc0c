"""The sampler contract (bake/core/sampler.py) as one assertion, for the tests of every sampler."""
import numpy as np

from bake.core.metrics import chi2_test


def assert_sampler_contract(sampler, wi, u, *, pdf_rtol, max_lost=0.0, invert_atol=None, invert_rtol=1e-7,
                            chi2=None, where=""):
    """At one incident direction wi, for the uniform points u (N, 2):
    - sample(wi, u) gives one finite wo and pdf >= 0 per row of u (a single wi serves all);
      a sample with pdf 0 is lost: none when max_lost is 0, else fewer than that fraction;
      every kept sample lies above the horizon;
    - pdf(wi, wo) is the pdf sample() returned (rtol pdf_rtol) at every kept sample;
    - with invert_atol: invert(wi, wo) gives u back (np.testing.assert_allclose's tolerances);
    - with chi2 (bake.core.metrics.chi2_test's keywords: n, n_tests, seed, binning, ...): sample()
      draws from pdf(), lost samples counted against the mass pdf() leaves out.
    Returns (wo, pdf)."""
    wo, pdf = sampler.sample(wi, u)
    assert wo.shape == (len(u), 3) and pdf.shape == (len(u),), (where, wo.shape, pdf.shape)
    assert np.all(np.isfinite(wo)) and np.all(np.isfinite(pdf)) and np.all(pdf >= 0), where
    kept = pdf > 0
    lost = 1.0 - kept.mean()
    assert lost == 0.0 or lost < max_lost, (where, f"lost {lost:.3g} of the samples")
    assert np.all(wo[kept, 2] > 0), (where, "a sample below the horizon")
    np.testing.assert_allclose(sampler.pdf(wi, wo[kept]), pdf[kept], rtol=pdf_rtol, err_msg=str(where))
    if invert_atol is not None:
        np.testing.assert_allclose(sampler.invert(wi, wo[kept]), u[kept], rtol=invert_rtol, atol=invert_atol,
                                   err_msg=str(where))
    if chi2 is not None:
        result = chi2_test(sampler, wi, **chi2)
        assert result.passed and result.dof > 0, (where, result)      # dof 0: nothing was compared
    return wo, pdf
