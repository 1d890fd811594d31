"""Run numpy's small linear algebra on one BLAS thread.

The fitter multiplies matrices of ~200 x 60: OpenBLAS splits them over all cores, and on a busy
2-core machine the thread hand-off costs far more than the arithmetic (measured: 22 FPS video
tracking with 2 threads vs > 100 FPS with 1). ``one_blas_thread()`` sets numpy's bundled OpenBLAS
to one thread for a block and restores the previous count; it uses ``threadpoolctl`` when
installed, else OpenBLAS's C API through ctypes, else does nothing.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import glob
import os

__all__ = ["one_blas_thread"]


@functools.lru_cache(maxsize=1)
def _openblas():
    """``(get, set)`` C functions of numpy's OpenBLAS, or None."""
    import numpy as np

    libdir = os.path.join(os.path.dirname(os.path.dirname(np.__file__)), "numpy.libs")
    for path in sorted(glob.glob(os.path.join(libdir, "*openblas*"))):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for get, set_ in (("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
                          ("openblas_get_num_threads64_", "openblas_set_num_threads64_"),
                          ("openblas_get_num_threads", "openblas_set_num_threads")):
            if hasattr(lib, get) and hasattr(lib, set_):
                g, s = getattr(lib, get), getattr(lib, set_)
                g.restype, s.argtypes = ctypes.c_int, [ctypes.c_int]
                return g, s
    return None


@contextlib.contextmanager
def one_blas_thread():
    try:
        from threadpoolctl import threadpool_limits  # type: ignore
    except ImportError:
        threadpool_limits = None
    if threadpool_limits is not None:
        with threadpool_limits(limits=1, user_api="blas"):
            yield
        return
    api = _openblas()
    if api is None:
        yield
        return
    get, set_ = api
    n = get()
    set_(1)
    try:
        yield
    finally:
        set_(n)
