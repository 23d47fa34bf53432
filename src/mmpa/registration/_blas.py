"""One BLAS thread for the small matrix products of the registration, and Open3D's thread cap.

The products here are small (an 850 x 33 by 33 x 850 descriptor product, 7 x 30000 normal
equations): a second OpenBLAS thread saves at most a fraction of a millisecond, and on a
busy machine it can cost tens of milliseconds (measured 24 ms instead of 0.5 ms for the FGR
descriptor product on 2 shared cores: the calling thread waits for a helper thread that is
not scheduled). ``openblas_set_num_threads_local`` limits only the calling thread and is
restored on exit; without OpenBLAS (another BLAS) this is a no-op.
"""

from __future__ import annotations

import ctypes
import glob
import os
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache
from typing import Any

import numpy as np
import open3d as o3d

__all__ = ["open3d_threads", "single_threaded_blas"]


@cache
def _set_local() -> Any:
    """``openblas_set_num_threads_local`` of numpy's bundled OpenBLAS, or None."""
    libs = os.path.join(os.path.dirname(os.path.dirname(np.__file__)), "numpy.libs")
    for path in sorted(glob.glob(os.path.join(libs, "lib*openblas*.so*"))):
        try:
            f = ctypes.CDLL(path).openblas_set_num_threads_local
        except (OSError, AttributeError):
            continue
        f.restype, f.argtypes = ctypes.c_int, [ctypes.c_int]
        return f
    return None


@contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Run the block with one BLAS thread on the calling thread (restored afterwards)."""
    f = _set_local()
    if f is None:
        yield
        return
    previous = f(1)
    try:
        yield
    finally:
        f(previous)


@contextmanager
def open3d_threads(n: int | None) -> Iterator[None]:
    """Cap Open3D's worker threads at ``n`` for the block (``None``: leave as is).

    Open3D's parallel loops (normals, FPFH, ICP correspondences) run a few thousand points
    each here; on 2 shared cores a second worker mostly waits to be scheduled (a cold
    registration measured 10-15 % faster with one thread under load). The cap is
    process-wide (``open3d.utility.set_max_threads``) and restored on exit.
    """
    if n is None:
        yield
        return

    previous = o3d.utility.get_max_threads()
    if previous == n:  # e.g. prepare inside register: nothing to set or restore
        yield
        return
    o3d.utility.set_max_threads(n)
    try:
        yield
    finally:
        o3d.utility.set_max_threads(previous)
