"""What the ``pemviz`` program sets in its own process (or its recording process), never when pemviz is imported as a
library.

:func:`settle_pyarrow_without_pandas`: a recording run never hands pyarrow a pandas object, so it need not pay pandas'
import (about 0.2 s of a default run's 3 s) for pyarrow to learn there is none.
"""

from __future__ import annotations

import sys
import types


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
    ``pd.NA``) inside Python sequences. Only the program calls this (:data:`pemviz.cli.AS_PROGRAM`), for a serial
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
