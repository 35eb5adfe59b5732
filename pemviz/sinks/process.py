"""What the ``pemviz`` program sets in its own process (or its recording process), never when pemviz is imported as
a library: :func:`settle_pyarrow_without_pandas` (pyarrow need not import pandas to learn there is none) and
:func:`import_scipy_special_lean` (scipy.special without the numpy submodules its array-API shim would import only
to copy)."""

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
    """Settle pyarrow's two lazy pandas probes without importing pandas; returns whether it did (False where pandas is
    imported already).

    pyarrow imports pandas on first use only to recognise pandas values: its Python shim
    (``pyarrow.lib._pandas_api``) and its C++ converter (``InitPandasStaticData``). Here the shim's import is
    refused and the converter is shown an empty module named pandas; importing pandas later still works, but pyarrow
    then no longer recognises ``pd.NaT`` / ``pd.NA`` inside Python sequences in this process. Only the program calls
    this (:data:`pemviz.commands.AS_PROGRAM`), for a serial recording run."""
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
Fortran wrapper generator and the test helpers). ``numpy.ma`` is not one of them: ``numpy.unique`` imports it."""


def import_scipy_special_lean() -> bool:
    """Import ``scipy.special`` without importing :data:`UNUSED_NUMPY_SUBMODULES`; returns whether it did (False
    where scipy.special or one of them is imported already, or numpy does not list them).

    scipy.special's array-API shim copies numpy's namespace (``clone_module``,
    ``scipy/_lib/array_api_compat/_internal.py``), importing each lazy submodule it meets; here numpy's ``__all__``
    and ``__dir__`` leave them out during the import, and the shim gets them back as lazily imported names (PEP
    562). Only the program calls this (:data:`pemviz.commands.AS_PROGRAM`), before any thread starts."""
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
