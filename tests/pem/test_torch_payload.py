"""pemviz.core.torch_payload: the torch-free reader of ``torch.save`` archives, against
``torch.load(weights_only=True)``; loading a PEM without torch, and the numpy fold of the weights, bit for bit the torch
module's."""

from __future__ import annotations

import io
import math
import pickle
import struct
import subprocess
import sys
import tempfile
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import Any

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pemviz import pem
from pemviz.core.files import load_tagged
from pemviz.core.torch_payload import UnsupportedPayload, load_payload, read_payload
from pemviz.pem import network, noise, store
from pemviz.pem.ensemble import ensemble_for, load_ensemble
from pemviz.pem.modules import MLNN
from pemviz.pem.network import PemFormatError
from pemviz.pem.noise import NoisePEM

ASSETS = sorted(store.assets_dir().glob("*.pt"))


def assert_same(got: Any, want: Any, where: str = "payload") -> None:
    """``got`` (the numpy reader's) is ``want`` (torch.load's) with each tensor a numpy array of the same dtype, shape
    and bytes (C order, owning its memory); containers of the same type and keys in the same order; plain values of
    the same type and value (NaN equal to NaN)."""
    if isinstance(want, torch.Tensor):
        assert isinstance(got, np.ndarray), f"{where}: {type(got).__name__}, not an array"
        expected = want.detach().contiguous().numpy()
        assert got.dtype == expected.dtype and got.shape == expected.shape, f"{where}: {got.dtype}{got.shape}"
        assert got.tobytes() == expected.tobytes(), f"{where}: values differ"
        assert got.flags.c_contiguous and got.flags.owndata and got.flags.writeable, where
        return
    assert type(got) is type(want), f"{where}: {type(got).__name__} != {type(want).__name__}"
    if isinstance(want, dict):
        assert list(got) == list(want), f"{where}: keys {list(got)} != {list(want)}"
        for key in want:
            assert_same(got[key], want[key], f"{where}[{key!r}]")
    elif isinstance(want, (list, tuple)):
        assert len(got) == len(want), f"{where}: length {len(got)} != {len(want)}"
        for i, (a, b) in enumerate(zip(got, want, strict=False)):
            assert_same(a, b, f"{where}[{i}]")
    elif isinstance(want, float) and math.isnan(want):
        assert math.isnan(got), where
    else:
        assert got == want, f"{where}: {got!r} != {want!r}"


# ------------------------------------------------------------------------------------------- shipped files


@pytest.mark.parametrize("path", ASSETS, ids=[p.name for p in ASSETS])
def test_every_shipped_file_reads_as_torch_load_reads_it(path: Path) -> None:
    assert_same(read_payload(path), torch.load(path, map_location="cpu", weights_only=True))


def test_the_shipped_files_are_all_there() -> None:
    assert {p.name for p in ASSETS} >= {"pem_ml-nn.pt", "pem_gbt.pt", "noise_hetero-t.pt", "ensemble_ml-nn.pt"}


# ------------------------------------------------------------------------------------------ random payloads

DTYPES = [np.float32, np.float64, np.int64, np.int32, np.int8, np.bool_]


@st.composite
def tensors(draw: st.DrawFn) -> torch.Tensor:
    """A tensor of one of :data:`DTYPES`, 0-d to 3-d (empty sides too), as saved or as a view of another layout: a
    slice with a step, a transpose, an offset into its storage, an expand (stride 0)."""
    dtype = draw(st.sampled_from(DTYPES))
    shape = draw(hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=5))
    base = torch.from_numpy(draw(hnp.arrays(dtype, shape)).copy())
    view = draw(st.sampled_from(["plain", "step", "transpose", "offset", "expand"]))
    if view == "step" and base.ndim >= 1:
        return base[::2]
    if view == "transpose" and base.ndim >= 2:
        return base.transpose(0, base.ndim - 1)
    if view == "offset" and base.numel() > 1:
        return base.reshape(-1)[1:]
    if view == "expand":
        return base.unsqueeze(0).expand(3, *base.shape)
    return base


PLAIN = st.none() | st.booleans() | st.integers(-(2**63), 2**63 - 1) | st.floats() | st.text(max_size=8)
VALUES = st.recursive(
    PLAIN | tensors(),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=10,
)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(payload=st.dictionaries(st.text(max_size=6), VALUES, max_size=5), shared=tensors())
def test_random_payloads_read_as_torch_load_reads_them(payload: dict, shared: torch.Tensor) -> None:
    payload["shared"] = [shared, shared.reshape(-1)[:1] if shared.numel() else shared, shared]  # one storage, 3 views
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "p.pt"
        torch.save(payload, path)
        want = torch.load(path, map_location="cpu", weights_only=True)
        assert_same(read_payload(path), want)
        assert_same(load_payload(path), want)


def test_ordered_dicts_parameters_tuples_and_odd_floats() -> None:
    state = torch.nn.Linear(3, 2).state_dict()  # an OrderedDict, with its _metadata attribute
    payload = {
        "state": state,
        "param": torch.nn.Parameter(torch.arange(4.0)),
        "t": (1, "a", None),
        "floats": [float("nan"), float("inf"), -0.0, 5e-324],
        "complex": torch.tensor([1 + 2j]),
        "half": torch.tensor([1.5, -2.0], dtype=torch.half),
        "u8": torch.arange(5, dtype=torch.uint8),
    }
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "p.pt"
        torch.save(payload, path)
        got, want = read_payload(path), torch.load(path, weights_only=True)
    assert isinstance(got["state"], OrderedDict) and isinstance(got["param"], np.ndarray)
    want["param"] = want["param"].detach()  # a Parameter is its data here
    assert_same(got, want)


def _rewrite(path: Path, out: Path, change: Any) -> None:
    """Copy a zip archive record by record, ``change(name, data)`` giving each record's new bytes (None: drop it)."""
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as dst:
        for info in src.infolist():
            data = change(info.filename, src.read(info.filename))
            if data is not None:
                dst.writestr(info.filename, data)


def test_a_big_endian_archive_reads_as_torch_reads_it(tmp_path: Path) -> None:
    payload = {
        "f": torch.linspace(-3, 7, 11, dtype=torch.float64),
        "i": torch.arange(6, dtype=torch.int32).view(2, 3),
        "b": torch.tensor([True, False]),
        "h": torch.tensor([0.5, 3.0], dtype=torch.float32)[1:],
    }
    torch.save(payload, tmp_path / "little.pt")
    assert_same(read_payload(tmp_path / "little.pt"), payload)
    keys = {"0": np.float64, "1": np.int32, "2": np.bool_, "3": np.float32}  # torch.save numbers storages as met

    def swap(name: str, data: bytes) -> bytes:
        if name.endswith("/byteorder"):
            return b"big"
        if "/data/" in name:
            return np.frombuffer(data, dtype=keys[name.rsplit("/", 1)[1]]).byteswap().tobytes()
        return data

    _rewrite(tmp_path / "little.pt", tmp_path / "big.pt", swap)
    want = torch.load(tmp_path / "big.pt", weights_only=True)
    assert_same(read_payload(tmp_path / "big.pt"), want)
    assert_same(read_payload(tmp_path / "big.pt"), payload)


# --------------------------------------------------------------------------- files the reader leaves to torch


def test_the_legacy_format_and_foreign_globals_are_left_to_torch(tmp_path: Path) -> None:
    payload = torch.load(store.pem_path(), weights_only=True)
    torch.save(payload, tmp_path / "legacy.pt", _use_new_zipfile_serialization=False)
    with pytest.raises(UnsupportedPayload):
        read_payload(tmp_path / "legacy.pt")
    assert_same(load_payload(tmp_path / "legacy.pt"), payload)
    legacy = pem.load_pem(tmp_path / "legacy.pt")
    gaps = np.linspace(0, 80, 401)
    assert np.array_equal(legacy.logit_at_gap(gaps), pem.load_pem().logit_at_gap(gaps))

    torch.save({"size": torch.Size([2, 3])}, tmp_path / "size.pt")  # a global weights_only allows and this reader not
    with pytest.raises(UnsupportedPayload, match="torch.Size"):
        read_payload(tmp_path / "size.pt")
    assert load_payload(tmp_path / "size.pt") == {"size": (2, 3)}


def _damaged(tmp_path: Path) -> dict[str, Path]:
    """Files that are not pemviz payloads, or damaged ones, by name."""
    good = store.pem_path().read_bytes()
    files = {
        "junk": b"not a torch file",
        "empty": b"",
        "two bytes": b"\x00\x01",
        "zip magic only": b"PK\x03\x04",
        "truncated 90%": good[: int(len(good) * 0.9)],
        "truncated 50%": good[: len(good) // 2],
        "truncated 200": good[:200],
        "pickle not zip": pickle.dumps({"format": "pemviz-pem", "version": 1}, protocol=2),
    }
    out = {}
    for name, content in files.items():
        out[name] = tmp_path / f"{name.replace(' ', '_')}.pt"
        out[name].write_bytes(content)
    foreign = tmp_path / "foreign_zip.pt"
    with zipfile.ZipFile(foreign, "w") as z:
        z.writestr("readme.txt", "hello")
    out["foreign zip"] = foreign
    numpy_global = tmp_path / "numpy_global.pt"
    torch.save({"format": "pemviz-pem", "a": np.zeros(3)}, numpy_global)  # numpy's globals: weights_only refuses them
    out["numpy global"] = numpy_global
    for name, change in {
        "damaged pickle": lambda n, d: d[: len(d) // 2] if n.endswith("data.pkl") else d,
        "short storage": lambda n, d: d[:-4] if n.endswith("/data/2") else d,
        "odd byteorder": lambda n, d: b"middle" if n.endswith("/byteorder") else d,
        "future version": lambda n, d: b"99\n" if n.endswith("/version") else d,
    }.items():
        out[name] = tmp_path / f"{name.replace(' ', '_')}.pt"
        _rewrite(store.pem_path(), out[name], change)
    return out


def _no_byteorder(tmp_path: Path) -> Path:
    """The shipped PEM without its ``byteorder`` record: read as little-endian, as torch reads it."""
    _rewrite(store.pem_path(), tmp_path / "no_byteorder.pt", lambda n, d: None if n.endswith("/byteorder") else d)
    return tmp_path / "no_byteorder.pt"


def _flipped(tmp_path: Path) -> Path:
    """The shipped PEM with one byte of a weight flipped: the zip CRC no longer matches its record."""
    good = bytearray(store.pem_path().read_bytes())
    with zipfile.ZipFile(store.pem_path()) as z:
        info = z.getinfo("archive/data/2")  # ff_nn.0.weight, 280 float32
        name_len, extra_len = struct.unpack("<HH", good[info.header_offset + 26 : info.header_offset + 30])
        start = info.header_offset + 30 + name_len + extra_len  # the local header's lengths, not the directory's
        assert bytes(good[start : start + info.file_size]) == z.read(info)
    good[start + 101] ^= 0x40
    (tmp_path / "flipped.pt").write_bytes(bytes(good))
    return tmp_path / "flipped.pt"


def _outcome(fn: Any) -> tuple:
    try:
        return ("ok", fn())
    except Exception as exc:  # noqa: BLE001 - the type and message are the outcome
        return ("error", type(exc), str(exc))


def test_damaged_and_foreign_files_fail_as_they_did_with_torch_load(tmp_path: Path) -> None:
    odd = {"flipped byte": _flipped(tmp_path), "no byteorder": _no_byteorder(tmp_path)}
    for name, path in [*_damaged(tmp_path).items(), *odd.items()]:
        new = _outcome(
            lambda: load_tagged(
                path,  # noqa: B023 (called within the iteration)
                "pemviz-pem",
                1,
                "PEM",
                PemFormatError,
                as_numpy=True,
            )
        )
        old = _outcome(
            lambda: load_tagged(
                path,  # noqa: B023 (called within the iteration)
                "pemviz-pem",
                1,
                "PEM",
                PemFormatError,
            )
        )
        if old[0] == "ok":  # torch reads it (no byte order, a flipped byte torch does not check): so does the reader
            assert new[0] == "ok", name
            assert_same(new[1], old[1], name)
        else:
            assert new == old, name
        loaded = _outcome(lambda: pem.load_pem(path))  # noqa: B023 (called within the iteration)
        if loaded[0] == "error":
            assert loaded[1] is PemFormatError and "\n" not in loaded[2] and str(path) in loaded[2], (name, loaded)


@pytest.mark.parametrize("loader", [pem.load_pem, pem.load_noise_pem, pem.load_noisy_pem, load_ensemble])
def test_every_loader_gives_one_line_for_a_damaged_file(tmp_path: Path, loader: Any) -> None:
    for name, path in _damaged(tmp_path).items():
        with pytest.raises(PemFormatError) as info:
            loader(path)
        assert "\n" not in str(info.value) and str(path) in str(info.value), (name, str(info.value))


def test_a_payload_with_lists_where_arrays_belong_is_damaged(tmp_path: Path) -> None:
    payload = torch.load(store.pem_path(), weights_only=True)
    payload["norm_mean"] = [0.0, 1.0, 2.0, 3.0]
    torch.save(payload, tmp_path / "list.pt")
    with pytest.raises(PemFormatError, match="damaged PEM file"):
        pem.load_pem(tmp_path / "list.pt")


# ------------------------------------------------------------------------------------------- without torch

TORCH_FREE = """
import sys
import pemviz.pem
from pemviz.pem.store import load_pem, load_noise_pem, load_noisy_pem
from pemviz.pem.ensemble import ensemble_for, load_ensemble
from pemviz.commands import pem_argument
p = load_pem()
assert isinstance(p.state_dict["ff_nn.0.weight"], __import__("numpy").ndarray)
load_pem("gbt"), load_noise_pem(), load_ensemble(ensemble_for(None)), pem_argument(None), pem_argument("gbt")
assert p.logit_at_gap([5.0]).shape == (1,)
assert "torch" not in sys.modules, "torch was imported"
from pemviz.pem.modules import MLNN  # the torch modules' one home: now torch comes
assert "torch" in sys.modules
"""


def test_loading_the_shipped_pems_does_not_import_torch() -> None:
    proc = subprocess.run([sys.executable, "-c", TORCH_FREE], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]


def test_the_torch_modules_have_one_import_path() -> None:
    """``MLNN`` and ``NoiseNLL`` are :mod:`pemviz.pem.modules`'s alone: the package and the modules that evaluate PEMs
    without torch lend neither."""
    from pemviz.pem import modules

    for module, name in ((pem, "MLNN"), (network, "MLNN"), (noise, "NoiseNLL")):
        assert not hasattr(module, name), f"{module.__name__}.{name}"
    assert modules.NoiseNLL.FAMILIES == noise.FAMILIES and modules.NoiseNLL.DF_MIN == noise.DF_MIN
    with pytest.raises(AttributeError):
        pem.NoSuchName  # noqa: B018
    with pytest.raises(ValueError, match="noise family"):
        modules.NoiseNLL("cauchy")


# ------------------------------------------------------------------------------ the fold, against torch's


def fold_layers(module: Any) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """Affine layers ``(W [out, in], b [out])`` in float64 of a torch :class:`MLNN`, each BatchNorm (eval mode)
    folded into the Linear before it, in torch: the reference of the numpy fold pemviz uses
    (:func:`pemviz.pem.network.fold_state_dict`)."""
    from torch import nn

    folded: list[tuple[np.ndarray, np.ndarray]] = []
    mods = list(module.ff_nn)
    for i, mod in enumerate(mods):
        if isinstance(mod, nn.Linear):
            w = mod.weight.detach().to(torch.float64).numpy().copy()
            b = mod.bias.detach().to(torch.float64).numpy().copy()
            nxt = mods[i + 1] if i + 1 < len(mods) else None
            if isinstance(nxt, nn.BatchNorm1d):
                assert nxt.running_mean is not None and nxt.running_var is not None
                scale = nxt.weight.detach().to(torch.float64).numpy() / np.sqrt(
                    nxt.running_var.detach().to(torch.float64).numpy() + nxt.eps
                )
                b = (
                    scale * (b - nxt.running_mean.detach().to(torch.float64).numpy())
                    + nxt.bias.detach().to(torch.float64).numpy()
                )
                w = scale[:, None] * w
            folded.append((np.ascontiguousarray(w), np.ascontiguousarray(b)))
    return tuple(folded)


def _torch_folded(state_pem: Any, build: Any) -> Any:
    """``build()`` with :func:`pemviz.pem.network.fold_state_dict` replaced by the torch module's fold
    (:func:`fold_layers` of the :class:`MLNN` loaded with the state): the path before the numpy
    fold."""
    original = network.fold_state_dict

    def via_torch(state: Any, hidden: Any, *, batch_norm: bool = True, in_dim: int = 14, out_dim: int = 1) -> Any:
        module = MLNN(in_dim, hidden, batch_norm=batch_norm, out_dim=out_dim)
        module.load_state_dict({k: torch.from_numpy(np.array(v)) for k, v in state.items()})
        return fold_layers(module.eval())

    network.fold_state_dict = via_torch
    noise.fold_state_dict = via_torch
    try:
        return build()
    finally:
        network.fold_state_dict = original
        noise.fold_state_dict = original


def _raw(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack(
        [
            rng.integers(0, 7, n),
            rng.uniform(0, 1, n),
            rng.integers(0, 3, n),
            rng.normal(size=(n, 4)),
            rng.normal(0, 8, n),
            rng.normal(1.6, 0.4, n),
            rng.uniform(2, 80, n),
            rng.uniform(-3, 3, n),
        ]
    )


def _same_bits(a: Any, b: Any) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _mlp_pems() -> list[pem.PEM]:
    return [pem.load_pem(), *load_ensemble(ensemble_for(None))]


@pytest.mark.parametrize("index", range(21))
def test_shipped_pem_logits_are_bit_identical_to_the_torch_fold(index: int) -> None:
    p = _mlp_pems()[index]
    ref = _torch_folded(
        p,
        lambda: pem.PEM(
            name=p.name,
            norm=p.norm,
            state_dict=p.state_dict,
            hidden=p.hidden,
            batch_norm=p.batch_norm,
            temperature=p.temperature,
        ),
    )
    torch_layers = fold_layers(p.to_module())
    assert all(_same_bits(a, c) and _same_bits(b, d) for (a, b), (c, d) in zip(p._layers, torch_layers, strict=False))
    raw = _raw(3000, index)
    gaps = np.concatenate([np.linspace(-20, 200, 5001), p._gap_knots, np.nextafter(p._gap_knots, np.inf)])
    assert _same_bits(p.logit(raw), ref.logit(raw))
    assert _same_bits(p.logit_at_gap(gaps), ref.logit_at_gap(gaps))
    assert _same_bits(p._gap_knots, ref._gap_knots)


def test_shipped_noise_pem_is_bit_identical_to_the_torch_fold() -> None:
    n = pem.load_noise_pem()
    ref = _torch_folded(
        n,
        lambda: NoisePEM(
            name=n.name,
            norm=n.norm,
            family=n.family,
            df=n.df,
            state_dict=n.state_dict,
            hidden=n.hidden,
            target_scale=n.target_scale,
        ),
    )
    x = n.features(_raw(3000, 7))
    assert all(_same_bits(a, b) for a, b in zip(n.noise_params(x), ref.noise_params(x), strict=False))


def test_weights_of_another_architecture_are_refused_in_one_line() -> None:
    p = pem.load_pem()
    with pytest.raises(PemFormatError, match="weights do not fit hidden=\\(20, 30\\)") as info:
        pem.PEM(name="x", norm=p.norm, state_dict=p.state_dict, hidden=(20, 30))
    assert "ff_nn.3.weight has shape [20, 20], needs [30, 20]" in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(PemFormatError, match="ff_nn.0.weight is a NoneType, not an array"):
        pem.PEM(name="x", norm=p.norm, state_dict={**p.state_dict, "ff_nn.0.weight": None})
    with pytest.raises(PemFormatError, match=r"missing keys \['ff_nn.6.bias'\]"):
        pem.PEM(name="x", norm=p.norm, state_dict={k: v for k, v in p.state_dict.items() if k != "ff_nn.6.bias"})
    with pytest.raises(PemFormatError, match="unexpected keys"):
        pem.PEM(name="x", norm=p.norm, state_dict=p.state_dict, batch_norm=False)


def test_state_dicts_are_numpy_and_to_module_gives_the_weights_back() -> None:
    p = pem.load_pem()
    assert all(isinstance(v, np.ndarray) for v in p.state_dict.values())
    assert p.state_dict["ff_nn.0.weight"].dtype == np.float32
    module = p.to_module()
    for key, value in module.state_dict().items():
        assert _same_bits(value.numpy(), p.state_dict[key]), key
    q = pem.PEM.from_module(module, p.norm, name="again")  # tensors in: copied into numpy arrays
    assert isinstance(q.state_dict["ff_nn.0.weight"], np.ndarray)
    assert _same_bits(q.logit_at_gap(np.linspace(0, 50, 101)), p.logit_at_gap(np.linspace(0, 50, 101)))


def test_a_saved_pem_is_still_a_torch_file_of_tensors(tmp_path: Path) -> None:
    store.save_pem(pem.load_pem(), tmp_path / "p.pt")
    payload = torch.load(tmp_path / "p.pt", weights_only=True)
    assert all(isinstance(v, torch.Tensor) for v in payload["state_dict"].values())
    assert payload["norm_mean"].dtype == torch.float64
    assert_same(read_payload(tmp_path / "p.pt"), payload)
    buffer = io.BytesIO()  # the reader takes what zipfile takes
    buffer.write((tmp_path / "p.pt").read_bytes())
    assert_same(read_payload(buffer), payload)  # type: ignore[arg-type]
