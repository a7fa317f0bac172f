"""numba kernels. Each takes and returns whole batches as arrays; all are
compiled with cache=True so the compile cost is paid once per machine."""


def run_serially() -> None:
    """Run this thread's parallel kernels on one thread (numba's thread
    count is per thread). For a thread that calls them on small batches
    beside processes that hold every core, as the render server's message
    loop does for each photon job: an OpenMP launch there waits for
    workers the tracers keep off the cores (measured: 312 ns a photon to
    emit and locate 1,024-photon jobs on 2 threads, 195 on one; under load
    531 against 311)."""
    use_threads(1)


def use_threads(n: int) -> None:
    """Run this thread's parallel kernels on at most `n` threads (numba's
    count is per thread; at most the cores numba found)."""
    import numba
    numba.set_num_threads(max(1, min(int(n), numba.config.NUMBA_NUM_THREADS)))
