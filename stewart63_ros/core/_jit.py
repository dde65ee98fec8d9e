"""numba's njit when numba is installed, else a no-op (same results, slower)."""
try:
    from numba import njit as _njit

    def njit(func):
        return _njit(cache=True, fastmath=False, nogil=True)(func)

    # Small kernels that allocate nothing (scalar code writing into arrays they
    # are given): compiled without numba's reference-counting runtime, so that
    # passing them arrays costs no atomic reference-count updates, and inlined
    # by LLVM into their compiled callers (calls between numba functions are
    # otherwise not inlined). Both are numba options of the CPU target; where
    # a numba lacks them, such a kernel is a plain njit function (same results).
    try:
        from numba.core.cpu import CPUTargetOptions as _Options
    except ImportError:  # pragma: no cover
        _Options = None
    _KERNEL_OPTIONS = {name: value for name, value in (('_nrt', False), ('forceinline', True))
                       if hasattr(_Options, name)}

    def njit_kernel(func):
        return _njit(cache=True, fastmath=False, nogil=True, **_KERNEL_OPTIONS)(func)
    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - numba is a declared dependency
    def njit(func):
        return func
    njit_kernel = njit
    HAVE_NUMBA = False
