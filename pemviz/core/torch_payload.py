"""Read the payload files pemviz writes with ``torch.save`` without importing torch: tensors come back as numpy arrays.

The reader follows the zip format of PyTorch's ``torch/serialization.py`` (``torch.save`` since torch 1.6): one
folder of records, ``<archive>/data.pkl`` the pickled object (each tensor a ``torch._utils._rebuild_tensor_v2`` call
on a persistent storage id), ``<archive>/data/<key>`` each storage's raw elements in the byte order of
``<archive>/byteorder``, ``<archive>/version`` 1 to 3. The unpickler allows fewer globals than
``torch.load(weights_only=True)``; anything else raises :class:`UnsupportedPayload`, and :func:`load_payload` then
falls back to ``torch.load(weights_only=True)``, so a file this reader does not understand loads, or fails, exactly
as with torch."""

from __future__ import annotations

import io
import os
import pickle
import sys
import zipfile
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np

STORAGE_DTYPES: dict[str, np.dtype] = {
    "DoubleStorage": np.dtype(np.float64),
    "FloatStorage": np.dtype(np.float32),
    "HalfStorage": np.dtype(np.float16),
    "LongStorage": np.dtype(np.int64),
    "IntStorage": np.dtype(np.int32),
    "ShortStorage": np.dtype(np.int16),
    "CharStorage": np.dtype(np.int8),
    "ByteStorage": np.dtype(np.uint8),
    "BoolStorage": np.dtype(np.bool_),
    "ComplexDoubleStorage": np.dtype(np.complex128),
    "ComplexFloatStorage": np.dtype(np.complex64),
}
"""The typed storage classes of ``torch`` (``torch.storage._dtype_to_storage_type_map``) this reader turns into
numpy dtypes; the others (``BFloat16Storage``, the quantised ones) have none and are left to torch."""

FORMAT_VERSIONS = range(1, 4)
"""Archive format versions read here (``version`` record; torch 2.x writes 3); another is left to torch."""


class UnsupportedPayload(ValueError):
    """A file this reader does not understand: not a ``torch.save`` zip archive, a global outside the allowed ones,
    a storage of another type, or a damaged record (:func:`load_payload` then asks torch)."""


class _Storage:
    """A storage read from ``data/<key>``: ``array`` 1-d numpy of its dtype, native byte order, read-only."""

    __slots__ = ("array",)

    def __init__(self, array: np.ndarray) -> None:
        self.array = array


class _StorageType:
    """Stands for ``torch.<Name>Storage`` in a persistent id: only its numpy ``dtype`` is needed."""

    __slots__ = ("dtype",)

    def __init__(self, dtype: np.dtype) -> None:
        self.dtype = dtype


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _rebuild_tensor_v2(
    storage: Any,
    storage_offset: Any,
    size: Any,
    stride: Any,
    requires_grad: Any,
    backward_hooks: Any,
    metadata: Any = None,
) -> np.ndarray:
    """``torch._utils._rebuild_tensor_v2`` as a numpy array: the elements ``storage_offset + sum(i_d * stride_d)``
    (in elements) of the storage, in the shape ``size``, copied (C order, owning its memory).

    Raises:
        UnsupportedPayload: not a storage, sizes or strides not non-negative ints, a view beyond the storage,
            backward hooks, or tensor metadata (the conjugate / negative bits)."""
    if not isinstance(storage, _Storage):
        raise UnsupportedPayload(f"tensor rebuilt from a {type(storage).__name__}, not a storage")
    if not (isinstance(size, tuple) and isinstance(stride, tuple) and len(size) == len(stride)):
        raise UnsupportedPayload(f"tensor size {size!r} and stride {stride!r} do not match")
    if not all(_is_int(v) and v >= 0 for v in (storage_offset, *size, *stride)):
        raise UnsupportedPayload(f"tensor offset {storage_offset!r}, size {size!r}, stride {stride!r}")
    if backward_hooks is not None and not (isinstance(backward_hooks, OrderedDict) and not backward_hooks):
        raise UnsupportedPayload("tensor with backward hooks")
    if metadata:
        raise UnsupportedPayload(f"tensor metadata {metadata!r}")
    flat = storage.array
    if 0 in size:
        return np.empty(size, dtype=flat.dtype)
    last = storage_offset + sum((n - 1) * s for n, s in zip(size, stride, strict=False))
    if last >= flat.shape[0]:
        raise UnsupportedPayload(f"tensor view ends at element {last}, beyond its storage of {flat.shape[0]}")
    item = flat.dtype.itemsize
    view = np.lib.stride_tricks.as_strided(
        flat[storage_offset:], shape=size, strides=[s * item for s in stride], writeable=False
    )
    return view.copy()


def _rebuild_parameter(data: Any, requires_grad: Any, backward_hooks: Any) -> np.ndarray:
    """``torch._utils._rebuild_parameter``: an ``nn.Parameter`` is its data here."""
    if not isinstance(data, np.ndarray):
        raise UnsupportedPayload(f"parameter of a {type(data).__name__}")
    return data


def _encode(text: Any, encoding: Any = "utf-8") -> bytes:
    """``_codecs.encode`` as pickle protocol 2 uses it for ``bytes``: ``encode(str, 'latin1')`` only."""
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise UnsupportedPayload(f"_codecs.encode of {type(text).__name__} with {encoding!r}")
    return text.encode("latin1")


_GLOBALS: dict[tuple[str, str], Any] = {
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor_v2,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
    ("collections", "OrderedDict"): OrderedDict,
    ("builtins", "set"): set,
    ("builtins", "complex"): complex,
    ("builtins", "bytearray"): bytearray,
    ("_codecs", "encode"): _encode,
    **{("torch", name): _StorageType(dtype) for name, dtype in STORAGE_DTYPES.items()},
}


class _Unpickler(pickle.Unpickler):
    """The payload's unpickler: globals from :data:`_GLOBALS` only, storages from the archive's records."""

    def __init__(self, data: bytes, read_storage: Callable[[np.dtype, str, int], _Storage]) -> None:
        super().__init__(io.BytesIO(data))
        self._read_storage = read_storage

    def find_class(self, module: str, name: str) -> Any:
        if module == "__builtin__":  # protocol 2 names builtins as Python 2 did
            module = "builtins"
        try:
            return _GLOBALS[(module, name)]
        except (KeyError, TypeError):
            raise UnsupportedPayload(f"global {module}.{name} is not read without torch") from None

    def persistent_load(self, pid: Any) -> _Storage:
        if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"):
            raise UnsupportedPayload(f"persistent id {pid!r}")
        _, storage_type, key, location, numel = pid
        if not (
            isinstance(storage_type, _StorageType)
            and isinstance(key, str)
            and isinstance(location, str)
            and _is_int(numel)
            and numel >= 0
        ):
            raise UnsupportedPayload(f"storage id {pid!r}")
        return self._read_storage(storage_type.dtype, key, numel)


def read_payload(path: str | os.PathLike[str]) -> Any:
    """The object a ``torch.save`` zip archive holds, tensors as numpy arrays, without importing torch.

    Args:
        path: the file.
    Returns:
        What ``torch.load(path, weights_only=True)`` returns, each tensor a numpy array of its dtype and shape (C
            order, native byte order, bit for bit).
    Raises:
        UnsupportedPayload: anything this reader does not understand (see the module docstring).
        OSError: the file cannot be opened or read."""
    try:
        with zipfile.ZipFile(path) as archive:
            return _read_archive(archive)
    except (UnsupportedPayload, OSError):
        raise
    except Exception as exc:  # zipfile, pickle and numpy raise several types for a damaged file
        raise UnsupportedPayload(f"{type(exc).__name__}: {exc}") from None


def _read_archive(archive: zipfile.ZipFile) -> Any:
    names = archive.namelist()
    if not names or "/" not in names[0]:
        raise UnsupportedPayload("not a torch.save archive (its first record is in no folder)")
    prefix = names[0].split("/", 1)[0] + "/"
    present = set(names)

    def record(name: str) -> bytes:
        if prefix + name not in present:
            raise UnsupportedPayload(f"no record {name}")
        return archive.read(prefix + name)

    version_name = ".data/version" if prefix + ".data/version" in present else "version"
    try:
        version = int(record(version_name).decode("ascii").strip())
    except ValueError:
        raise UnsupportedPayload("unreadable format version") from None
    if version not in FORMAT_VERSIONS:
        raise UnsupportedPayload(f"format version {version}")
    order = record("byteorder") if prefix + "byteorder" in present else b"little"
    if order not in (b"little", b"big"):
        raise UnsupportedPayload(f"byte order {order!r}")
    storages: dict[str, _Storage] = {}

    def read_storage(dtype: np.dtype, key: str, numel: int) -> _Storage:
        if key not in storages:
            raw = record(f"data/{key}")
            if len(raw) != numel * dtype.itemsize:
                raise UnsupportedPayload(f"storage {key}: {len(raw)} bytes for {numel} x {dtype}")
            stored = dtype.newbyteorder("<" if order == b"little" else ">")
            storages[key] = _Storage(np.frombuffer(raw, dtype=stored).astype(dtype.newbyteorder("="), copy=False))
        storage = storages[key]
        if storage.array.dtype != dtype or storage.array.shape[0] != numel:
            raise UnsupportedPayload(f"storage {key} read as two types")
        return storage

    return _Unpickler(record("data.pkl"), read_storage).load()


def load_payload(path: str | os.PathLike[str]) -> Any:
    """:func:`read_payload`, or, for a file it does not understand, ``torch.load(path, map_location="cpu",
    weights_only=True)`` (importing torch) with its tensors turned into numpy arrays as :func:`read_payload` gives.

    Raises:
        Whatever ``torch.load`` raises for a file neither reads (several types; some messages span several lines),
        and TypeError for a tensor of a dtype numpy lacks (``bfloat16``)."""
    try:
        return read_payload(path)
    except Exception:  # noqa: BLE001 - torch decides: the same result, or the same error, as before this reader
        pass
    import torch  # ~1 s to import: only for a file the reader above does not understand

    return tensors_to_numpy(torch.load(path, map_location="cpu", weights_only=True))


def tensors_to_numpy(value: Any) -> Any:
    """``value`` with every torch tensor in its dicts, lists and tuples replaced by a numpy array (a copy, C order);
    anything else as it is. Does not import torch.

    Raises:
        TypeError: a tensor of a dtype numpy lacks (``bfloat16``)."""
    torch = sys.modules.get("torch")
    if torch is None:
        return value
    if isinstance(value, torch.Tensor):
        return np.array(value.detach().cpu().resolve_conj().resolve_neg().numpy(), order="C", copy=True)
    if isinstance(value, OrderedDict):
        return OrderedDict((k, tensors_to_numpy(v)) for k, v in value.items())
    if isinstance(value, dict):
        return {k: tensors_to_numpy(v) for k, v in value.items()}
    if isinstance(value, list):
        return [tensors_to_numpy(v) for v in value]
    if isinstance(value, tuple) and not hasattr(value, "_fields"):
        return tuple(tensors_to_numpy(v) for v in value)
    return value
