"""numba's njit with this package's options (numba is a required dependency)."""
from numba import njit as _njit
from numba.core.cpu import CPUTargetOptions as _Options


def njit(func):
    """Compiled, cached on disk, releasing the GIL; strict IEEE arithmetic."""
    return _njit(cache=True, fastmath=False, nogil=True)(func)


# Small kernels that allocate nothing (scalar code writing into arrays they
# are given): compiled without numba's reference-counting runtime, so that
# passing them arrays costs no atomic reference-count updates, and inlined
# by LLVM into their compiled callers (calls between numba functions are
# otherwise not inlined). Both are numba options of the CPU target; where a
# numba lacks them, such a kernel is a plain njit function (same results).
_KERNEL_OPTIONS = {name: value for name, value in (('_nrt', False), ('forceinline', True))
                   if hasattr(_Options, name)}


def njit_kernel(func):
    """``njit`` for small allocation-free kernels, inlined into their callers."""
    return _njit(cache=True, fastmath=False, nogil=True, **_KERNEL_OPTIONS)(func)
