"""Speed of a sampler: wall-clock throughput of sample() and pdf(), one thread, best of k.

    samples_per_second(sampler, wi, n=1 << 16, repeat=5) -> dict

Benchmarks only: never assert on these numbers in tests (machines and loads differ).

One thread. numpy's element-wise operations run on one thread anyway; its BLAS (matrix
products, e.g. flow inference) and some samplers' own pools may use more. This module
limits what it can:
- BLAS/OpenMP pools through `threadpoolctl` when that package is installed (it is not a
  FlowBSDF dependency); otherwise the pools keep the size they got at start-up, which
  only the environment sets, before numpy is imported:
      OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 \\
      VECLIB_MAXIMUM_THREADS=1 NUMEXPR_NUM_THREADS=1 <command>
  (`single_thread_env()` returns that mapping for a subprocess).
- a sampler with a `limit_threads(n)` context manager is run inside it (the Mitsuba
  peer's Dr.Jit pool: Dr.Jit 1.5 ignores DRJIT_NUM_THREADS, only its
  `set_thread_count` limits it).
The returned dict says which of these held (`threads`).
"""
import contextlib
import os
import time

import numpy as np

THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
               "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")


def single_thread_env(base=None):
    """A copy of the environment (or `base`) with every known thread-pool size set to 1."""
    env = dict(os.environ if base is None else base)
    env.update({k: "1" for k in THREAD_VARS})
    return env


@contextlib.contextmanager
def single_threaded(sampler=None):
    """Limit the thread pools this process can limit; yields a short description of what held."""
    notes = []
    with contextlib.ExitStack() as stack:
        try:
            from threadpoolctl import threadpool_limits
        except ImportError:
            unset = [k for k in THREAD_VARS[:3] if os.environ.get(k) != "1"]
            notes.append("blas: env " + ("1 thread" if not unset else
                                         "not limited (" + ", ".join(unset) + " != 1)"))
        else:
            stack.enter_context(threadpool_limits(limits=1))
            notes.append("blas: threadpoolctl 1 thread")
        limit = getattr(sampler, "limit_threads", None)
        if limit is not None:
            stack.enter_context(limit(1))
            notes.append(f"{getattr(sampler, 'name', 'sampler')}: 1 thread")
        yield "; ".join(notes)


def random_incident(n, seed=0):
    """n incident directions uniform in cos(theta) and phi: a new wi per sample, as a path
    tracer asks (the speed runs' "new wi per sample" mode)."""
    rng = np.random.default_rng(seed)
    cos_t, phi = rng.random(n), 2 * np.pi * rng.random(n)
    sin_t = np.sqrt(1 - cos_t ** 2)
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=-1)


def _best_time(fn, repeat):
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def samples_per_second(sampler, wi, n=1 << 16, repeat=5, seed=0, warmup=True):
    """Throughput of sampler.sample(wi, u) (which returns the pdf too) and of sampler.pdf(wi, wo)
    on n directions for one incident direction wi (3,), single thread, best of `repeat`.

    The warm-up call (not timed) pays one-time costs: table building, JIT compilation.
    Returns {sample_per_s, pdf_per_s, both_per_s (one sample() and one pdf() per sample),
    sample_ns, pdf_ns, ns_per_sample (sample + pdf), n, repeat, threads}.
    """
    rng = np.random.default_rng(seed)
    wi = np.asarray(wi, float)
    u = rng.random((n, 2))
    with single_threaded(sampler) as threads:
        if warmup:
            wo, _ = sampler.sample(wi, u)
            sampler.pdf(wi, wo)
        else:
            wo, _ = sampler.sample(wi, u)
        t_sample = _best_time(lambda: sampler.sample(wi, u), repeat)
        t_pdf = _best_time(lambda: sampler.pdf(wi, wo), repeat)
    sample_ns, pdf_ns = 1e9 * t_sample / n, 1e9 * t_pdf / n
    return {
        "sample_per_s": n / t_sample,
        "pdf_per_s": n / t_pdf,
        "both_per_s": n / (t_sample + t_pdf),
        "sample_ns": sample_ns,
        "pdf_ns": pdf_ns,
        "ns_per_sample": sample_ns + pdf_ns,
        "n": n,
        "repeat": repeat,
        "threads": threads,
    }
