"""Store and find PEMs: the shipped ``pemviz/assets/pem_<name>.pt`` and ``noise_<name>.pt`` files (package data),
atomic saves, and the authors' reference PEM.

A PEM file is a ``torch.save`` of a plain dict readable with ``weights_only=True``: format tag ``pemviz-pem``,
version, ``kind`` (``mlp`` :class:`PEM`, ``gbt`` :class:`TreePEM`), name, z-score statistics, the model's tensors
and metadata; a noise PEM file has tag ``pemviz-noise-pem`` and kind ``mlp`` or ``linear``; a :class:`NoisyPEM` file
(``pemviz-noisy-pem``) holds both heads under ``detect`` and ``noise``. Loading does not import torch
(:func:`pemviz.core.torch_payload.load_payload`); saving does."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict

import numpy as np

from pemviz.core.files import atomic_write, load_tagged, repo_root
from pemviz.pem.encoding import POSE_COLUMNS, NormStats
from pemviz.pem.network import PEM, PemFormatError
from pemviz.pem.noise import HomoscedasticNoise, NoiseModel, NoisePEM
from pemviz.pem.perception import NoisyPEM
from pemviz.pem.recipes import DEFAULT_NOISE_NAME, DEFAULT_PEM_NAME
from pemviz.pem.trees import TreePEM

if TYPE_CHECKING:  # annotations only: torch takes about 1 s to import, and only saving needs it
    import torch

ASSETS_DIR_ENV = "PEMVIZ_ASSETS_DIR"
FORMAT_TAG = "pemviz-pem"
FORMAT_VERSION = 1
NOISE_FORMAT_TAG = "pemviz-noise-pem"
NOISE_FORMAT_VERSION = 1
NOISY_FORMAT_TAG = "pemviz-noisy-pem"
NOISY_FORMAT_VERSION = 1

AnyPEM = PEM | TreePEM
"""Every PEM kind: each has ``name``, ``norm``, ``metadata``, ``logit``, ``logit_at_gap``, ``prob_at_gap``."""


def assets_dir() -> Path:
    """``$PEMVIZ_ASSETS_DIR`` if set, else the package's own ``pemviz/assets`` folder (package data, found by a
    wheel install too)."""
    env = os.environ.get(ASSETS_DIR_ENV)
    if env:
        return Path(env).expanduser()
    return Path(str(resources.files("pemviz") / "assets"))


def pem_path(name: str = DEFAULT_PEM_NAME) -> Path:
    """Where the shipped PEM called ``name`` lives: ``<assets>/pem_<name>.pt``."""
    return assets_dir() / f"pem_{name}.pt"


def _plain(value: Any) -> Any:
    """Metadata as plain Python values (what ``torch.load(weights_only=True)`` accepts)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if value is None or isinstance(value, bool):
        return value
    for kind in (int, float, str):  # exact builtins: subclasses (e.g. torch's TorchVersion) are not loadable
        if isinstance(value, kind):
            return kind(value)
    return str(value)


def save_pem(pem: AnyPEM, path: str | os.PathLike[str]) -> Path:
    """Write a PEM atomically (temporary file in the same folder, then ``os.replace``), readable with
    ``torch.load(path, weights_only=True)``.

    Raises:
        OSError: the folder is not writable (nothing is left behind).
        TypeError: ``pem`` is not a :class:`PEM` or :class:`TreePEM`."""
    return _save(_pem_payload(pem), path)


def _save(payload: dict[str, Any], path: str | os.PathLike[str]) -> Path:
    """``torch.save`` a payload dict atomically (temporary file in the same folder, then ``os.replace``)."""
    import torch

    target = Path(path)
    atomic_write(target, lambda tmp: torch.save(payload, tmp))
    return target


def _tensor(value: Any, dtype: Any = None) -> torch.Tensor:
    """A torch tensor of a numpy array (or of what ``numpy.asarray`` takes), a copy of its own, C order, for
    ``torch.save``; ``dtype`` a numpy dtype, or the array's own."""
    import torch

    return torch.from_numpy(np.array(value, dtype=dtype, order="C", copy=True))


def _array(value: Any) -> np.ndarray:
    """A payload's tensor, read as a numpy array (:func:`pemviz.core.torch_payload.load_payload`).

    Raises:
        TypeError: anything else (the file is damaged)."""
    if not isinstance(value, np.ndarray):
        raise TypeError(f"a {type(value).__name__} where an array belongs")
    return value


def _norm_payload(norm: NormStats) -> dict[str, torch.Tensor]:
    import torch

    return {
        "norm_mean": torch.as_tensor(norm.mean, dtype=torch.float64),
        "norm_std": torch.as_tensor(norm.std, dtype=torch.float64),
    }


def _pem_payload(pem: AnyPEM) -> dict[str, Any]:
    """The plain dict of a PEM file (format tag, version, kind, name, z-score statistics, metadata, model)."""
    payload: dict[str, Any] = {
        "format": FORMAT_TAG,
        "version": FORMAT_VERSION,
        "name": pem.name,
        **_norm_payload(pem.norm),
        "metadata": _plain(pem.metadata),
    }
    if isinstance(pem, PEM):
        payload.update(
            {
                "kind": PEM.kind,
                "hidden": list(pem.hidden),
                "batch_norm": bool(pem.batch_norm),
                "temperature": float(pem.temperature),
                "state_dict": {k: _tensor(v) for k, v in pem.state_dict.items()},
            }
        )
    elif isinstance(pem, TreePEM):
        payload.update({"kind": TreePEM.kind, "baseline": float(pem.baseline), "trees": _pack_trees(pem)})
    else:
        raise TypeError(f"cannot save a {type(pem).__name__} as a PEM")
    return payload


def load_pem(path: str | os.PathLike[str] | None = None) -> AnyPEM:
    """Load a PEM saved by :func:`save_pem`.

    Args:
        path: a file path, or the name of a shipped PEM (``"ml-nn"`` -> ``<assets>/pem_ml-nn.pt``, see
            :func:`pem_path`); default :data:`DEFAULT_PEM_NAME`.
    Returns:
        A :class:`PEM` (kind ``mlp``) or a :class:`TreePEM` (kind ``gbt``).
    Raises:
        FileNotFoundError: no such file (the message lists the shipped PEMs).
        PemFormatError: the file is not a pemviz PEM or is damaged."""
    p = _pem_file(DEFAULT_PEM_NAME if path is None else path)
    return _pem_from_payload(_load_payload(p, FORMAT_TAG, FORMAT_VERSION, "PEM"), p)


def _load_payload(p: Path, tag: str, version: int, what: str) -> dict:
    """:func:`pemviz.core.files.load_tagged`, tensors as numpy arrays: a file that cannot be read is one
    PemFormatError line saying what the file is and what to give instead."""
    allowed = f"give a {what} file pemviz wrote (torch.save)"
    if what == "PEM":
        allowed = (
            f"give a PEM file pemviz wrote (pemviz pem train, save_pem) or a shipped PEM ({', '.join(shipped_pems())})"
        )
    return load_tagged(p, tag, version, what, PemFormatError, as_numpy=True, allowed=allowed)


def _pem_from_payload(payload: Mapping[str, Any], p: Path) -> AnyPEM:
    """The PEM of a payload of :func:`_pem_payload` read from ``p`` (named in errors); raises PemFormatError."""
    kind = payload.get("kind", PEM.kind)
    try:
        norm = NormStats(mean=_array(payload["norm_mean"]), std=_array(payload["norm_std"]))
        meta = dict(payload.get("metadata") or {})
        if kind == PEM.kind:
            return PEM(
                name=str(payload["name"]),
                norm=norm,
                state_dict=dict(payload["state_dict"]),
                hidden=tuple(int(h) for h in payload["hidden"]),
                batch_norm=bool(payload["batch_norm"]),
                temperature=float(payload["temperature"]),
                metadata=meta,
            )
        if kind == TreePEM.kind:
            return TreePEM(
                name=str(payload["name"]),
                norm=norm,
                baseline=float(payload["baseline"]),
                metadata=meta,
                **_unpack_trees(payload["trees"]),
            )
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise PemFormatError(f"{p}: damaged PEM file ({exc!r})") from None
    raise PemFormatError(f"{p}: unknown PEM kind {kind!r} (known: {PEM.kind}, {TreePEM.kind})")


def resolve_pem(ref: str | os.PathLike[str] | None) -> str | os.PathLike[str] | None:
    """What ``--pem`` takes in every command, checked before any work: a shipped PEM's name (no ``.pt`` suffix or
    folder, :func:`shipped_pems`) or a PEM file, returned as given; None (the shipped default) stays None.

    Raises:
        FileNotFoundError: neither a shipped PEM nor a file; the message lists the shipped PEMs."""
    if ref is not None:
        _pem_file(ref)
    return ref


def _pem_file(ref: str | os.PathLike[str]) -> Path:
    """The file of a shipped PEM's name or of a path (see :func:`resolve_pem`); raises FileNotFoundError."""
    return _model_file(ref, pem_path, shipped_pems, "PEM")


def _model_file(
    ref: str | os.PathLike[str], path_of: Callable[[str], Path], shipped: Callable[[], list[str]], what: str
) -> Path:
    """A name without ``.pt`` suffix and folder -> ``path_of(name)``; anything else a path. Raises FileNotFoundError
    (listing ``shipped()``) when the file is absent."""
    p = Path(ref)
    if isinstance(ref, str) and p.suffix != ".pt" and len(p.parts) == 1:
        p = path_of(ref)
    if not p.is_file():
        raise FileNotFoundError(
            f"{ref}: neither a {what} file nor one of the shipped {what}s "
            f"({', '.join(shipped()) or 'none'}, in {assets_dir()})"
        )
    return p


def _pack_trees(pem: TreePEM) -> dict[str, torch.Tensor]:
    """Compact tree tensors: split fields only for internal nodes, values only for leaves, small int types."""
    internal = ~pem.is_leaf
    if pem.feature.size and int(pem.feature[internal].max(initial=0)) > 127:
        raise ValueError("feature index does not fit int8")
    return {
        "is_leaf": _tensor(pem.is_leaf),
        "feature": _tensor(pem.feature[internal], np.int8),
        "threshold": _tensor(pem.threshold[internal]),
        "left": _tensor(pem.left[internal], np.int32),
        "right": _tensor(pem.right[internal], np.int32),
        "value": _tensor(pem.value[pem.is_leaf]),
        "roots": _tensor(pem.roots, np.int32),
    }


def _unpack_trees(packed: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Inverse of :func:`_pack_trees` on the arrays read back: full-length node arrays (leaves get feature 0,
    threshold 0, children -1).

    Raises:
        KeyError, TypeError, ValueError: a field missing, not an array, or of another length (a damaged file)."""
    is_leaf = _array(packed["is_leaf"]).astype(bool)
    internal = ~is_leaf
    m = is_leaf.shape[0]
    out = {
        "is_leaf": is_leaf,
        "feature": np.zeros(m, dtype=np.int64),
        "threshold": np.zeros(m, dtype=np.float64),
        "left": np.full(m, -1, dtype=np.int64),
        "right": np.full(m, -1, dtype=np.int64),
        "value": np.zeros(m, dtype=np.float64),
        "roots": _array(packed["roots"]).astype(np.int64),
    }
    out["feature"][internal] = _array(packed["feature"])
    out["threshold"][internal] = _array(packed["threshold"])
    out["left"][internal] = _array(packed["left"])
    out["right"][internal] = _array(packed["right"])
    out["value"][is_leaf] = _array(packed["value"])
    return out


def shipped_pems() -> list[str]:
    """Names of the PEM files in :func:`assets_dir` (``pem_<name>.pt``), sorted."""
    return sorted(f.stem[len("pem_") :] for f in assets_dir().glob("pem_*.pt"))


def reference_pem_dir() -> Path:
    """``<repository root>/../shared/reference/carla-stuff-pem``: the authors' PEM (never copied into pemviz)."""
    return repo_root().parent / "shared" / "reference" / "carla-stuff-pem"


def load_reference_pem(folder: str | os.PathLike[str] | None = None) -> PEM:
    """The authors' ML-NN (CarlaStuff ``models/det_baseline_full/pem_class_train_full`` with ``norm_stats_mu.pt`` /
    ``norm_stats_std.pt``, pose columns 7..10) as a :class:`PEM` named ``authors``, read by
    :func:`pemviz.core.torch_payload.load_payload`.

    Raises:
        FileNotFoundError: the folder or one of its three files is missing."""
    d = Path(folder) if folder is not None else reference_pem_dir()
    files = [d / "pem_class_train_full.pt", d / "norm_stats_mu.pt", d / "norm_stats_std.pt"]
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        raise FileNotFoundError(f"authors' PEM files missing: {', '.join(missing)}")
    from pemviz.core.torch_payload import load_payload

    state = load_payload(files[0])
    mu = np.asarray(load_payload(files[1]), dtype=np.float64)
    sd = np.asarray(load_payload(files[2]), dtype=np.float64)
    cols = list(POSE_COLUMNS)
    return PEM(
        name="authors",
        norm=NormStats(mean=mu[cols], std=sd[cols]),
        state_dict=dict(state),
        metadata={"source": "craigiedon/CarlaStuff models/det_baseline_full/pem_class_train_full"},
    )


# ------------------------------------------------------------------------------------------ noise PEMs


def noise_pem_path(name: str = DEFAULT_NOISE_NAME) -> Path:
    """Where the shipped noise PEM called ``name`` lives: ``<assets>/noise_<name>.pt``."""
    return assets_dir() / f"noise_{name}.pt"


def shipped_noise_pems() -> list[str]:
    """Names of the noise PEM files in :func:`assets_dir` (``noise_<name>.pt``), sorted."""
    return sorted(f.stem[len("noise_") :] for f in assets_dir().glob("noise_*.pt"))


def _noise_payload(model: NoiseModel) -> dict[str, Any]:
    """The plain dict of a noise PEM file (see the module docstring)."""
    payload: dict[str, Any] = {
        "format": NOISE_FORMAT_TAG,
        "version": NOISE_FORMAT_VERSION,
        "kind": model.kind,
        "name": model.name,
        "family": model.family,
        "df": None if model.df is None else _tensor(model.df, np.float64),
        **_norm_payload(model.norm),
        "metadata": _plain(model.metadata),
    }
    if isinstance(model, NoisePEM):
        payload.update(
            {
                "hidden": list(model.hidden),
                "target_scale": _tensor(model.target_scale, np.float64),
                "state_dict": {k: _tensor(v) for k, v in model.state_dict.items()},
            }
        )
    elif isinstance(model, HomoscedasticNoise):
        payload.update({k: _tensor(getattr(model, k), np.float64) for k in ("coef", "intercept", "log_scale")})
    else:
        raise TypeError(f"cannot save a {type(model).__name__} as a noise PEM")
    return payload


class _NoiseFields(TypedDict):
    """The fields every noise PEM shares (:class:`pemviz.pem.noise.NoiseModel`)."""

    name: str
    norm: NormStats
    family: str
    df: np.ndarray | None
    metadata: dict[str, Any]


def _noise_from_payload(payload: Mapping[str, Any], p: Path) -> NoiseModel:
    """The noise PEM of a payload of :func:`_noise_payload` read from ``p``; raises PemFormatError."""
    kind = payload.get("kind")
    try:
        common: _NoiseFields = {
            "name": str(payload["name"]),
            "norm": NormStats(mean=_array(payload["norm_mean"]), std=_array(payload["norm_std"])),
            "family": str(payload["family"]),
            "df": None if payload["df"] is None else _array(payload["df"]),
            "metadata": dict(payload.get("metadata") or {}),
        }
        if kind == NoisePEM.kind:
            return NoisePEM(
                **common,
                state_dict=dict(payload["state_dict"]),
                hidden=tuple(int(h) for h in payload["hidden"]),
                target_scale=_array(payload["target_scale"]),
            )
        if kind == HomoscedasticNoise.kind:
            return HomoscedasticNoise(
                **common,
                coef=_array(payload["coef"]),
                intercept=_array(payload["intercept"]),
                log_scale=_array(payload["log_scale"]),
            )
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise PemFormatError(f"{p}: damaged noise PEM file ({exc!r})") from None
    raise PemFormatError(f"{p}: unknown noise PEM kind {kind!r} (known: {NoisePEM.kind}, {HomoscedasticNoise.kind})")


def save_noise_pem(model: NoiseModel, path: str | os.PathLike[str]) -> Path:
    """Write a noise PEM atomically (a few KB; ``torch.load(path, weights_only=True)`` reads it).

    Raises:
        OSError: the folder is not writable (nothing is left behind).
        TypeError: ``model`` is not a :class:`NoisePEM` or :class:`HomoscedasticNoise`."""
    return _save(_noise_payload(model), path)


def load_noise_pem(path: str | os.PathLike[str] | None = None) -> NoiseModel:
    """Load a noise PEM saved by :func:`save_noise_pem`: a file path, or the name of a shipped one (``"hetero-t"`` ->
    ``<assets>/noise_hetero-t.pt``); default :data:`DEFAULT_NOISE_NAME`.

    Raises:
        FileNotFoundError: no such file (the message lists the shipped noise PEMs).
        PemFormatError: the file is not a pemviz noise PEM or is damaged."""
    p = _model_file(DEFAULT_NOISE_NAME if path is None else path, noise_pem_path, shipped_noise_pems, "noise PEM")
    return _noise_from_payload(_load_payload(p, NOISE_FORMAT_TAG, NOISE_FORMAT_VERSION, "noise PEM"), p)


def save_noisy_pem(model: NoisyPEM, path: str | os.PathLike[str]) -> Path:
    """Write a perception model (detection head and noise head) atomically as one file.

    Raises:
        OSError: the folder is not writable (nothing is left behind).
        TypeError: a head of a kind that cannot be saved."""
    return _save(
        {
            "format": NOISY_FORMAT_TAG,
            "version": NOISY_FORMAT_VERSION,
            "detect": _pem_payload(model.detect),
            "noise": _noise_payload(model.noise),
        },
        path,
    )


def load_noisy_pem(path: str | os.PathLike[str]) -> NoisyPEM:
    """Load a perception model saved by :func:`save_noisy_pem`.

    Raises:
        FileNotFoundError: no such file.
        PemFormatError: the file is not a pemviz perception model, is damaged, or its heads disagree on the encoding."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such perception model file")
    payload = _load_payload(p, NOISY_FORMAT_TAG, NOISY_FORMAT_VERSION, "perception model")
    detect, noise = payload.get("detect"), payload.get("noise")
    if not (isinstance(detect, Mapping) and isinstance(noise, Mapping)):
        raise PemFormatError(f"{p}: damaged perception model file (no detect or noise head)")
    heads = _pem_from_payload(detect, p), _noise_from_payload(noise, p)
    try:
        return NoisyPEM(detect=heads[0], noise=heads[1])
    except ValueError as exc:
        raise PemFormatError(f"{p}: {exc}") from None
