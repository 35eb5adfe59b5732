"""What the ``pemviz`` program sets in its own process (or its recording process), never when pemviz is imported as a
library.

:func:`settle_pyarrow_without_pandas`: a recording run never hands pyarrow a pandas object, so it need not pay pandas'
import (about 0.2 s of a default run's 3 s) for pyarrow to learn there is none.

:func:`import_scipy_special_lean`: scipy.special, which a run needs before its first stage, without the two numpy
submodules its array-API shim imports only to copy them (about 40 ms of the run's start).
"""

from __future__ import annotations

import sys
import types
from collections.abc import Callable
from typing import Any


class _NoPandas:
    """A module finder that refuses ``pandas`` (:func:`settle_pyarrow_without_pandas`)."""

    @staticmethod
    def find_spec(name: str, path: object = None, target: object = None) -> None:
        if name == "pandas":
            raise ImportError("pandas: not imported to convert numpy arrays and Python values")


def settle_pyarrow_without_pandas() -> bool:
    """Settle pyarrow's two lazy pandas probes without importing pandas; returns whether it did (False where pandas
    is imported already).

    rerun turns every logged value into Arrow with ``pyarrow.array`` / ``pyarrow.scalar``. On its first use pyarrow
    imports pandas twice over, only to learn whether a value is a pandas one: its Python shim
    (``pyarrow.lib._pandas_api``, for arrays) and its C++ converter's static data (``InitPandasStaticData`` in
    ``arrow/python/helpers.cc``, for Python sequences: pandas' ``NaT``, ``NA``, ``Timestamp``). Here the shim's
    import is refused (it records that pandas is absent), and the converter is shown an empty module named pandas
    (it records none of pandas' types); then the process's modules are as before, and importing pandas later works.
    The price, in this process only: pyarrow no longer recognises pandas' missing-value objects (``pd.NaT``,
    ``pd.NA``) inside Python sequences. Only the program calls this (:data:`pemviz.commands.AS_PROGRAM`), for a serial
    recording run, which converts numpy arrays and plain Python values only.
    """
    if "pandas" in sys.modules:
        return False
    import numpy as np
    import pyarrow as pa

    finder = _NoPandas()
    sys.meta_path.insert(0, finder)
    try:
        pa.array(np.zeros(1, dtype=np.bool_))  # the Python shim: pandas tried once, recorded as absent
    finally:
        sys.meta_path.remove(finder)
    sys.modules["pandas"] = types.ModuleType("pandas")
    try:
        pa.array([True])  # the C++ converter's static data: a module without pandas' types
    finally:
        del sys.modules["pandas"]
    return True


UNUSED_NUMPY_SUBMODULES = ("f2py", "testing")
"""numpy's lazily imported submodules that scipy's array-API shim copies at import and pemviz's run never uses (the
Fortran wrapper generator and the test helpers): about 40 ms of imports on a quiet 2-core machine, 60 ms under load
(``python -X importtime -c "import scipy.special"``, numpy 2.4, scipy 1.17). ``numpy.ma`` is not one of them:
``numpy.unique`` imports it."""


def import_scipy_special_lean() -> bool:
    """Import ``scipy.special`` without importing :data:`UNUSED_NUMPY_SUBMODULES`; returns whether it did (False
    where scipy.special or one of them is imported already, or numpy does not list them).

    scipy.special imports its array-API shim, ``scipy._lib.array_api_compat.numpy``, which copies numpy's namespace
    into its own (``clone_module`` in ``scipy/_lib/array_api_compat/_internal.py``: ``from numpy import *``, then
    every name of ``dir(numpy)``); each of numpy's lazy submodules it meets is imported then (numpy's module
    ``__getattr__``, ``numpy/__init__.py``). Here numpy's ``__all__`` and ``__dir__`` leave them out while
    scipy.special is imported, and are restored at once; the shim then gets them back as names that import their
    module when first read (a module ``__getattr__``, PEP 562), and in its ``__all__``: every name of the shim still
    reads what it read before, numpy's included. Only the program calls this (:data:`pemviz.commands.AS_PROGRAM`), in a
    process that has started no thread yet.
    """
    if "scipy.special" in sys.modules:
        return False
    import numpy as np

    names = set(getattr(np, "__all__", ()))
    skipped = tuple(n for n in UNUSED_NUMPY_SUBMODULES if n in names and f"numpy.{n}" not in sys.modules)
    if len(skipped) != len(UNUSED_NUMPY_SUBMODULES) or "__dir__" not in vars(np):
        return False
    full_all, full_dir = np.__all__, np.__dir__
    numpy_names = vars(np)  # numpy's own namespace: setting a name there is setting numpy's attribute
    numpy_names["__all__"] = [n for n in full_all if n not in skipped]
    numpy_names["__dir__"] = lambda: [n for n in full_dir() if n not in skipped]
    try:
        import scipy.special  # noqa: F401
    finally:
        numpy_names["__all__"], numpy_names["__dir__"] = full_all, full_dir
    shim: Any = sys.modules.get("scipy._lib.array_api_compat.numpy")  # a module given names at run time
    if shim is not None and "__getattr__" not in vars(shim):
        shim.__getattr__ = _numpy_submodule(shim.__name__, skipped)
        shim.__all__ = sorted(set(shim.__all__) | set(skipped))
    return True


def _numpy_submodule(module: str, names: tuple[str, ...]) -> Callable[[str], object]:
    """A module ``__getattr__`` (PEP 562) for ``module`` that reads each of ``names`` from numpy (importing the
    submodule then) and raises ``AttributeError`` for any other name."""

    def __getattr__(name: str) -> object:
        if name in names:
            import numpy as np

            return getattr(np, name)
        raise AttributeError(f"module {module!r} has no attribute {name!r}")

    return __getattr__
