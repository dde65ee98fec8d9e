"""numba's njit with this package's options (numba is a required dependency)."""
from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

from numba import njit as _njit
from numba.core.cpu import CPUTargetOptions as _Options

if TYPE_CHECKING:
    from numba.core.dispatcher import Dispatcher

#: The Python function handed to the decorators (numba's stubs type the
#: dispatcher by it, as ``Dispatcher[_F]``).
_F = TypeVar('_F', bound=Callable[..., Any])


def njit(func: _F) -> Dispatcher[_F]:
    """Compiled, cached on disk, releasing the GIL; strict IEEE arithmetic.

    Args:
        func: the Python function to compile (lazily, on its first call, for
            the argument types of that call).

    Returns:
        numba's ``Dispatcher`` of ``func``: called as ``func`` is, with the
        same results (to the rounding of strict IEEE arithmetic); the Python
        function is its ``py_func``.
    """
    return _njit(cache=True, fastmath=False, nogil=True)(func)


# Small kernels that allocate nothing (scalar code writing into arrays they
# are given): compiled without numba's reference-counting runtime, so that
# passing them arrays costs no atomic reference-count updates, and inlined
# by LLVM into their compiled callers (calls between numba functions are
# otherwise not inlined). Both are numba options of the CPU target; where a
# numba lacks them, such a kernel is a plain njit function (same results).
_KERNEL_OPTIONS = {name: value for name, value in (('_nrt', False), ('forceinline', True))
                   if hasattr(_Options, name)}


def njit_kernel(func: _F) -> Dispatcher[_F]:
    """``njit`` for small allocation-free kernels, inlined into their callers.

    Args:
        func: the kernel: scalar code that allocates nothing (no numba
            reference-counting runtime where numba allows it off).

    Returns:
        numba's ``Dispatcher`` of ``func``, called as ``func`` is.
    """
    return _njit(cache=True, fastmath=False, nogil=True, **_KERNEL_OPTIONS)(func)
