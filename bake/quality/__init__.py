"""How good and how fast the samplers are: yardsticks, reports, benchmarks, stress tests (the
yardsticks themselves, rv and chi-square, are bake/core/metrics.py).

    report         the yardstick table and the speed-vs-error report (plots: matplotlib)
    page           the main job's page, OUT/index.html
    bench          wall-clock throughput of sample() and pdf()
    mitsuba_peer   Mitsuba 3's own `measured` plugin as a peer sampler
    stress         `flowbsdf stress`: hard cases, and a load and soak run
"""
