"""numba's njit when numba is installed, else a no-op (same results, slower)."""
try:
    from numba import njit as _njit

    def njit(func):
        return _njit(cache=True, fastmath=False, nogil=True)(func)
    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - numba is a declared dependency
    def njit(func):
        return func
    HAVE_NUMBA = False
