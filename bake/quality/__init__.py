"""How good and how fast the samplers are: yardsticks, reports, benchmarks, stress tests.

    metrics        relative variance of the albedo estimator; chi-square of sample() vs pdf()
    report         the yardstick table and the speed-vs-error report (plots: matplotlib)
    page           the main job's page, OUT/index.html
    bench          wall-clock throughput of sample() and pdf()
    mitsuba_peer   Mitsuba 3's own `measured` plugin as a peer sampler
    stress         `flowbsdf stress`: hard cases, and a load and soak run
"""
